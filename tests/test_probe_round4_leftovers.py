"""The faults the fourth probing round noticed and left alone
(docs/probe_round4.md, "Noticed and left alone" and "Round-4 leftovers
fixed"): each test is the minimal reproduction, through the real ASGI stack
(FastAPI's TestClient, or ``httpx.ASGITransport`` where two requests must
interleave) or the CLI as users run it, and fails without its fix."""

from __future__ import annotations

import io
import os
import subprocess
import sys

import numpy as np
import pytest

from service.schemas import responses as R

# the round's fixtures (module-scoped: this module gets its own store) and helpers
from .test_probe_round4 import _strict, client, dng, settled, zip_while  # noqa: F401
from .test_response_models import undeclared

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


# --- 1. `wandell batch FILE OUT` ---------------------------------------------------


def _cli(*args, cwd=ROOT):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
                          timeout=120, env=env, cwd=cwd)


def test_batch_of_a_file_says_it_is_a_file_not_a_missing_folder(tmp_path, dng):
    """``wandell batch FILE OUT`` with FILE an existing file said "input
    folder 'FILE' does not exist": the user, looking at the file, is told
    it is not there. Now: the path is a file, not a folder, and
    ``wandell white-balance`` is the command for one file (a usage error,
    exit 2, nothing written). A missing folder still says it does not
    exist."""
    f = tmp_path / "one.dng"
    f.write_bytes(dng)
    out = tmp_path / "out"
    r = _cli("batch", str(f), str(out))
    assert r.returncode == 2, (r.returncode, r.stdout, r.stderr)
    assert "does not exist" not in r.stderr, r.stderr
    assert "is a file, not a folder" in r.stderr and "wandell white-balance" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and not out.exists()
    assert "white-balance" in _cli("--help").stdout      # the command the message suggests exists
    r = _cli("batch", str(tmp_path / "missing"), str(out))
    assert r.returncode == 2 and "does not exist" in r.stderr, r.stderr


# --- 2. the retention sweep during a zip download -------------------------------------


def test_the_retention_sweep_does_not_remove_a_batch_whose_zip_is_being_downloaded(client, dng):
    """The result-retention sweep (``WANDELL_BATCH_RESULT_RETENTION``) removed
    an expired batch even while ``GET .../zip`` streamed it (fix 4 of round 4
    covered the user's DELETE only): the zip opens the results one after
    the other, so the client got a cut, unreadable zip. Now the sweep
    postpones such a batch: while the zip is sent, the sweep (the runner's
    own, here with a retention of 0 s) removes nothing and a second request
    still finds the batch; the zip is whole; the next sweep after it removes
    the batch. The two requests go through the ASGI stack on one event
    loop: the sweep runs and the second request is sent when the zip's
    first bytes have gone out."""
    import zipfile

    from service.routers import batches

    r = client.post("/v1/batches", files=[("files", (f"{i}.dng", dng)) for i in range(3)], data={"format": "tiff"})
    assert r.status_code == 202, r.text
    bid = r.json()["id"]
    assert settled(client, bid)["counts"]["done"] == 3
    runner = batches.get_runner()
    kept_retention = runner.config.result_retention_s
    swept = []

    async def sweep(other):
        runner.config.result_retention_s = 0.0     # the batch has expired
        swept.append(runner.remove_expired_batches())
        return await other.get(f"/v1/batches/{bid}")

    try:
        got = zip_while(bid, sweep)
        assert got["status"] == 200
        assert swept == [[]], swept
        assert got["during"].status_code == 200, got["during"].text
        names = zipfile.ZipFile(io.BytesIO(got["body"])).namelist()
        assert sorted(n for n in names if n.endswith(".tif")) == ["0.tif", "1.tif", "2.tif"], names
        # the download is over: the next sweep removes it (or the runner's own loop did already)
        after = runner.remove_expired_batches()
        assert after in ([bid], []), after
        assert client.get(f"/v1/batches/{bid}").status_code == 404
    finally:
        runner.config.result_retention_s = kept_retention


# --- 3. a user's white that cannot be rendered -----------------------------------------


def test_an_unrenderable_white_the_user_set_is_named_as_the_users(client):
    """``white=50000/+150`` with the generic camera (a camera-RGB TIFF) and
    ``target=A`` was refused as "the estimated light renders white with no
    luminance": the light was the user's white, not an estimate. The 422
    ``unrenderable`` stays; its detail names the white given, and the
    estimate's own refusal is not blamed on the user."""
    import tifffile

    buf = io.BytesIO()
    tifffile.imwrite(buf, (np.random.default_rng(0).random((48, 64, 3)) * 60000).astype(np.uint16))
    f = {"file": ("t.tif", buf.getvalue())}
    r = client.post("/v1/white-balance", files=f,
                    data={"white": "50000/+150", "camera": "generic", "target": "A", "format": "png"})
    assert r.status_code == 422, r.text[:300]
    body = _strict(r.text)
    assert body["error"] == "unrenderable"
    assert "estimated" not in body["detail"] and "50000/+150" in body["detail"], body["detail"]
    assert "white you set" in body["detail"] and "'A'" in body["detail"], body["detail"]
    # the same white and camera under the default target renders: the refusal is of this pairing only
    r = client.post("/v1/white-balance", files=f, data={"white": "50000/+150", "camera": "generic", "format": "png"})
    assert r.status_code == 200, r.text[:300]


# --- 4. /v1/sampling's refusals ---------------------------------------------------------


@pytest.mark.parametrize("query,why,accepts", [
    ("strategy=quasi-gauss-xyz&n=5", "does not match degrees", "n omitted, or equal to the sum of the degrees"),
    ("strategy=quasi-gauss-xyz&channel=A", "quasi-gauss-xyz takes no channel", "degrees=x,y,z"),
    ("strategy=riemann", "riemann needs n", "no degrees"),
])
def test_a_sampling_refusal_says_what_was_wrong_and_what_is_accepted(client, query, why, accepts):
    """A ``quasi-gauss-xyz`` refusal on ``/v1/sampling`` printed the rule's
    options as a Python dict, empty when only ``n`` was given
    (``quasi-gauss-xyz with n=5 {}: ...``), and a ``channel`` it does not
    take as Python's "got an unexpected keyword argument". Now the detail
    names what was given, why it is refused and what the strategy accepts,
    with no ``{}``."""
    r = client.get(f"/v1/sampling?{query}")
    assert r.status_code == 422, r.text[:300]
    body = _strict(r.text)
    assert body["error"] == "invalid_parameter"
    detail = body["detail"]
    assert "{" not in detail and "unexpected keyword" not in detail, detail
    assert why in detail and "accepts:" in detail and accepts in detail, detail


# --- 5. /v1/surfaces: lights.found 2 comes with its light_map -----------------------------


def test_surfaces_with_two_lights_answers_the_light_map_it_used(client, dng):
    """``/v1/surfaces`` with a light map (``spatial=true``, or ``auto`` on a
    mixed-light photograph) answered ``lights.found: 2`` ("a light map is
    given and used") without a ``light_map``: the surfaces were estimated
    under a map the answer did not show. Now ``light_map`` is present
    exactly when ``found`` is 2, declared in ``SurfacesResult``, and it is
    the map ``/v1/analyze`` gives for the same request."""
    f = {"file": ("s.dng", dng)}
    for spatial, found in (("true", 2), ("false", 1)):
        r = client.post("/v1/surfaces", files=f, data={"spatial": spatial, "grid": "2x2"})
        assert r.status_code == 200, r.text[:300]
        body = _strict(r.text)
        assert undeclared(R.SurfacesResult, body) == []
        R.SurfacesResult.model_validate(body)
        assert body["lights"]["found"] == found
        assert ("light_map" in body) == (found == 2), (spatial, sorted(body))
        if found == 2:
            a = _strict(client.post("/v1/analyze", files=f, data={"spatial": spatial}).text)
            assert a["light_map"] == body["light_map"]
