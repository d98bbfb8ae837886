"""Shared fixtures: in-model scenes with known truth."""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

# The in-process clients' host names (Starlette's TestClient sends
# "testserver", the httpx ASGI clients here "t" and "test"): served like the
# names WANDELL_ALLOWED_HOSTS adds in a deployment. Tests of the Host check
# itself set the variable through env_settings.
os.environ.setdefault("WANDELL_ALLOWED_HOSTS", "testserver,t,test")
# The command line keeps the light posterior's models on disk (issue 19,
# recovery.bayes.disk_cache_dir): the tests' CLI runs write theirs to a
# folder of this session, not the user's cache.
if "WANDELL_MODEL_CACHE_DIR" not in os.environ:
    import atexit
    import shutil

    os.environ["WANDELL_MODEL_CACHE_DIR"] = _model_cache = tempfile.mkdtemp(prefix="wandell-test-cache-")
    atexit.register(shutil.rmtree, _model_cache, True)

# Batches keep their store, inputs and results under WANDELL_DATA_DIR (default
# ~/.cache/wandell): every test and every server a test starts (they inherit
# the environment) writes into a folder of this session instead, never into
# the user's store (issue 29, item 6). Tests that need their own set it.
if "WANDELL_DATA_DIR" not in os.environ:
    import atexit
    import shutil

    os.environ["WANDELL_DATA_DIR"] = _data_dir = tempfile.mkdtemp(prefix="wandell-test-data-")
    atexit.register(shutil.rmtree, _data_dir, True)

from models import DEFAULT_WAVELENGTHS

#: The shared folder next to the project (real camera files, reproductions).
SHARED = Path(os.environ.get("WANDELL_SHARED_DIR", Path(__file__).resolve().parents[2] / "shared"))


def unavailable(reason: str):
    """Skip the test, saying why; fail it instead when the environment
    variable ``CI`` is set (CI must run every test)."""
    if os.environ.get("CI"):
        pytest.fail(f"{reason}; CI is set, so this test must run")
    pytest.skip(reason)


def shared_file(relpath: str) -> Path:
    """A file of the shared folder (:data:`SHARED`), or :func:`unavailable`
    when it is absent."""
    path = SHARED / relpath
    if not path.is_file():
        unavailable(f"{path} is absent (the shared data folder is not next to the project)")
    return path


def run_cli(*args: str, timeout: float = 300):
    """``python -m service.cli ARGS`` from the checkout, as a user runs it: the finished process."""
    root = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=root)
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env, cwd=root)


def gaussian_sensors(centres, width=30.0, wavelengths=DEFAULT_WAVELENGTHS):
    """Sensors with Gaussian sensitivities, one column per centre (nm)."""
    wl = np.asarray(wavelengths, float)[:, None]
    return np.exp(-0.5 * ((wl - np.asarray(centres, float)[None]) / width) ** 2)


def in_model_scene(rng, camera, surface_basis, light_weights, light_basis, n_pixels=4096, shape=None):
    """Pixels generated exactly by eq. 26: rho = Lambda_E sigma, with random
    surface weights (first weight positive and dominant, as for real
    surfaces). Returns image (H, W, C) and the true surface weights."""
    d_s = surface_basis.shape[1]
    sig = rng.normal(scale=0.3, size=(n_pixels, d_s))
    sig[:, 0] = 1.0 + np.abs(sig[:, 0])
    spd = light_basis @ light_weights
    refl = sig @ surface_basis.T
    rho = camera.response(refl * spd)
    shape = shape or (64, n_pixels // 64)
    return rho.reshape(*shape, camera.channels), sig


def pytest_collection_finish(session):
    """A test module may start a long, mostly idle step of its tests when
    the session starts (a function ``start_in_background()``, its
    ``stop_background()`` called at the end): run only when one of its
    tests was selected, so the wait passes while other tests run."""
    seen = set()
    if session.config.option.collectonly:
        return
    for item in session.items:
        mod = getattr(item, "module", None)
        if mod is not None and mod not in seen and hasattr(mod, "start_in_background"):
            seen.add(mod)
            mod.start_in_background()
    session.config._wandell_background = seen


def pytest_sessionfinish(session):
    for mod in getattr(session.config, "_wandell_background", ()):
        mod.stop_background()


@pytest.fixture
def rng():
    return np.random.default_rng(20261121)


@pytest.fixture
def env_settings(monkeypatch):
    """Set WANDELL_* variables for one test; settings are re-read from the
    environment (get_settings is cached per process) and restored after."""
    from service.settings import get_settings

    def set_env(**values):
        for k, v in values.items():
            monkeypatch.setenv(f"WANDELL_{k.upper()}", str(v))
        get_settings.cache_clear()
    yield set_env
    monkeypatch.undo()
    get_settings.cache_clear()


@pytest.fixture(scope="session")
def blackmagic_dng() -> bytes:
    """The real Blackmagic DNG of the issue-10 reproductions (2176 x 4128)."""
    path = shared_file("data/raw/Blackmagic.dng")
    with open(path, "rb") as f:
        return f.read()


@pytest.fixture(scope="session")
def load_real_once():
    """``benchmarks.realdata.load_real`` of a folder, loaded once a session
    (the 7,524 thumbnails of the three benchmarks, 370 MB: test_bayes_spectra
    and test_learned both use all of them); the arrays are shared, so a test
    must not write into them."""
    from benchmarks.realdata import load_real

    loaded = {}

    def load(directory):
        key = str(Path(directory).resolve())
        if key not in loaded:
            rs = load_real(directory)
            rs.images.flags.writeable = False
            rs.truth.flags.writeable = False
            loaded[key] = rs
        return loaded[key]
    return load


def scene_dng_bytes(height: int, width: int, camera: str = "Nikon 5100 (NPL)", light: str = "D65",
                    seed: int = 1) -> bytes:
    """A small synthetic scene as DNG bytes (:func:`testing.dngwriter.scene_dng`)."""
    import io

    from testing.dngwriter import scene_dng

    buf = io.BytesIO()
    scene_dng(buf, camera, light, height, width, seed=seed)
    return buf.getvalue()


def mondrian_u16(h=48, w=64) -> np.ndarray:
    """A linear 16-bit camera-RGB picture of 16 x 16 patches, no two rows alike."""
    rng = np.random.default_rng(9)
    cols = rng.uniform(0.05, 0.9, (h // 16 + 1, w // 16 + 1, 3)) * np.array([0.5, 1.0, 0.7])
    img = np.kron(cols, np.ones((16, 16, 1)))[:h, :w]
    img *= np.linspace(0.8, 1.0, h)[:, None, None]          # nothing symmetric: a turn shows
    return (img * 60000).astype(np.uint16)


def tiff_bytes(arr: np.ndarray, **kw) -> bytes:
    import tifffile

    import io

    buf = io.BytesIO()
    tifffile.imwrite(buf, arr, **kw)
    return buf.getvalue()


@pytest.fixture()
def app_with(tmp_path):
    """``make(**settings)``: a TestClient of the real app on a fresh data directory with the given
    ``WANDELL_*`` settings (one batch worker; the batch runner stopped before and after), and that
    directory: ``client, data = app_with(batch_result_retention=0.5)``."""
    from fastapi.testclient import TestClient

    from service.app import app
    from service.routers import batches
    from service.settings import get_settings

    mp = pytest.MonkeyPatch()
    clients = []

    def make(**settings):
        mp.setenv("WANDELL_DATA_DIR", str(tmp_path / "data"))
        mp.setenv("WANDELL_BATCH_WORKERS", "1")
        for k, v in settings.items():
            mp.setenv(f"WANDELL_{k.upper()}", str(v))
        get_settings.cache_clear()
        batches.stop_runner()
        c = TestClient(app)
        c.__enter__()
        clients.append(c)
        return c, tmp_path / "data"

    yield make
    for c in clients:
        c.__exit__(None, None, None)
    batches.stop_runner()
    mp.undo()
    get_settings.cache_clear()


def strict_json(text: str):
    """JSON with NaN/Infinity refused (what a strict client parses)."""
    def no(c):
        raise ValueError(f"non-finite number {c} in the answer")
    return json.loads(text, parse_constant=no)


def isolated_app_client(store: Path, **client_kw):
    """Yield a TestClient of the real app on a store of its own (``store``;
    settings re-read, the process-wide batch runner stopped before and
    after), for a module-scoped fixture."""
    from fastapi.testclient import TestClient

    from service.app import app
    from service.routers import batches
    from service.settings import get_settings

    mp = pytest.MonkeyPatch()
    mp.setenv("WANDELL_DATA_DIR", str(store))
    get_settings.cache_clear()
    batches.stop_runner()
    try:
        with TestClient(app, **client_kw) as c:
            yield c
    finally:
        batches.stop_runner()
        mp.undo()
        get_settings.cache_clear()


@contextlib.contextmanager
def running_server(env: dict | None = None, timeout: float = 60.0):
    """``python -m service`` (as the README starts it) on a free loopback
    port with ``WANDELL_*`` from ``env``: yields ``(base URL, process, log
    path)``, and stops that process (by its own id) afterwards."""
    import httpx

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    log = tempfile.NamedTemporaryFile(prefix="wandell-server-", suffix=".log", delete=False)
    full_env = {**os.environ, "WANDELL_HOST": "127.0.0.1", "WANDELL_PORT": str(port),
                **{f"WANDELL_{k.upper()}": str(v) for k, v in (env or {}).items()}}
    proc = subprocess.Popen([sys.executable, "-m", "service"], env=full_env, stdout=log, stderr=subprocess.STDOUT,
                            cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + timeout
        while True:
            if proc.poll() is not None:
                pytest.fail(f"the server exited with {proc.returncode}: {open(log.name).read()[-2000:]}")
            try:
                if httpx.get(base + "/health", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"the server did not answer /health within {timeout} s")
            time.sleep(0.2)
        yield base, proc, log.name
    finally:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        log.close()
        os.unlink(log.name)


def asgi_post_stream(path: str, chunks: list, headers: list):
    """POST ``chunks`` (consumed from the list as the app reads them) to the
    real app straight through ASGI, as a client streaming a body would:
    returns the response-start messages, the JSON body and the bytes the
    app read."""
    import asyncio
    import json

    from service.app import app

    consumed = 0
    sent = []

    async def receive():
        nonlocal consumed
        if not chunks:
            return {"type": "http.disconnect"}
        body = chunks.pop(0)
        consumed += len(body)
        return {"type": "http.request", "body": body, "more_body": bool(chunks)}

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
             "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"", "root_path": "",
             "headers": [(b"host", b"127.0.0.1:8000")] + headers,
             "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 8000)}
    asyncio.run(app(scope, receive, send))
    start = [m for m in sent if m["type"] == "http.response.start"]
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    return start, json.loads(body), consumed
