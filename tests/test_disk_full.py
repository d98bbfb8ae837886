"""Issue 17, item 8: a full temporary directory (TMPDIR) is a 507
``insufficient_storage`` with a JSON body, never a 500 (white-balance
output) or a 400 "error parsing the body" (upload spooling), and leaves no
partial file behind."""

from __future__ import annotations

import errno
import io
import os
import shutil
import subprocess
import tempfile

import numpy as np
import pytest
from fastapi.testclient import TestClient

from testing.dngwriter import scene_dng

from .conftest import running_server


def _dng(h=96, w=128) -> bytes:
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", h, w, seed=1)
    return buf.getvalue()


@pytest.fixture
def client():
    from service.app import app

    with TestClient(app, raise_server_exceptions=False) as c:
        yield c


@pytest.fixture
def tmpdir_only(tmp_path, monkeypatch):
    """TMPDIR for this test alone (what is left in it is checked)."""
    d = tmp_path / "tmp"
    d.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(d))
    return d


@pytest.mark.parametrize("error", [OSError(errno.ENOSPC, "No space left on device"),
                                   OSError(errno.EDQUOT, "Disk quota exceeded"),
                                   OSError("Not enough free space to write 53084160 bytes after offset 272")])
@pytest.mark.parametrize("fmt", ["png", "jpeg"])
def test_white_balance_output_on_a_full_tmpdir_is_507(client, tmpdir_only, monkeypatch, error, fmt):
    from service import pipeline

    def full(decoded, run, path, **kw):
        with open(path, "wb") as f:
            f.write(b"partial")
        raise error

    monkeypatch.setattr(pipeline, "write_corrected", full)
    r = client.post("/v1/white-balance", data={"format": fmt}, files={"file": ("a.dng", _dng())})
    assert r.status_code == 507, r.text
    assert r.json()["error"] == "insufficient_storage" and "TMPDIR" in r.json()["detail"]
    assert os.listdir(tmpdir_only) == []


def test_a_tiff_answer_needs_no_tmpdir(client, tmpdir_only, monkeypatch):
    """A 16-bit TIFF answer is its header and the corrected pixels sent from
    memory (issue 19): no output file, so a full TMPDIR does not stop it, and
    the bytes are the TIFF the encoder writes."""
    import numpy as np
    import tifffile

    from service import pipeline

    def full(*a, **kw):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(pipeline, "write_corrected", full)
    monkeypatch.setattr(tempfile, "mkstemp", full)
    r = client.post("/v1/white-balance", data={"format": "tiff"}, files={"file": ("a.dng", _dng())})
    assert r.status_code == 200, r.text
    assert int(r.headers["content-length"]) == len(r.content)
    img = tifffile.imread(io.BytesIO(r.content))
    assert img.dtype == np.uint16 and img.shape[2] == 3
    with tifffile.TiffFile(io.BytesIO(r.content)) as t:
        tags = {tag.name for tag in t.pages[0].tags}
    assert "InterColorProfile" in tags and "Software" in tags
    assert os.listdir(tmpdir_only) == []


def test_tiff_answers_held_in_memory_are_bounded_by_the_work_slots(client, tmpdir_only, monkeypatch):
    """A TIFF answer sent from memory holds its corrected image until the
    client has read it, after its work slot is free; at most as many are
    held as there are work slots, and beyond that the answer is a file in
    TMPDIR (removed after sending) with the same bytes. Every answer gives
    its place back once sent."""
    from service.routers import analysis

    held = analysis.held_answers
    assert held.n == 0
    first = client.post("/v1/white-balance", data={"format": "tiff"}, files={"file": ("a.dng", _dng())})
    assert first.status_code == 200 and held.n == 0
    made = []
    real = analysis.temp_output

    def counting(**kw):
        made.append(kw)
        return real(**kw)

    monkeypatch.setattr(analysis, "temp_output", counting)
    monkeypatch.setattr(held, "limit", lambda: 0)      # every place taken
    second = client.post("/v1/white-balance", data={"format": "tiff"}, files={"file": ("a.dng", _dng())})
    assert second.status_code == 200 and made and made[0]["suffix"] == ".tiff"
    assert second.content == first.content
    assert held.n == 0 and os.listdir(tmpdir_only) == []


def test_a_held_place_is_given_back_once_when_the_stream_ends_or_is_closed():
    """The place a TIFF answer holds is given back by its stream, when the
    last piece is sent or when the stream is closed early (a client that
    went away), not whenever the garbage collector frees the image (a
    reference cycle kept it, and a request right after saw the place still
    taken); the image's finalizer calling the same releaser later gives
    nothing back twice."""
    import asyncio

    from service.routers.analysis import _from_memory, _HeldAnswers

    held = _HeldAnswers()
    img = np.zeros((3000, 400, 3), np.uint16)            # 7 MB: several pieces
    for early in (False, True):
        assert held.take() and held.n == 1
        release = held.releaser()

        async def read():
            gen = _from_memory(b"head", img, release)
            got = [await gen.__anext__(), await gen.__anext__()]
            if early:
                await gen.aclose()                       # the client went away after two pieces
            else:
                got += [c async for c in gen]
            return got

        pieces = asyncio.run(read())
        assert held.n == 0, early
        release()                                        # the finalizer's call
        assert held.n == 0
        if not early:
            assert sum(len(bytes(p)) for p in pieces) == 4 + img.nbytes
    assert held.take() and held.take() and held.n == 2   # the places are really free
    held.releaser()()
    assert held.n == 1


def test_upload_spooling_on_a_full_tmpdir_is_507(client, monkeypatch):
    """Starlette spools each upload part to TMPDIR; ENOSPC there was
    FastAPI's 400 "There was an error parsing the body"."""
    from starlette.datastructures import UploadFile

    async def full(self, data):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(UploadFile, "write", full)
    for path in ("/v1/white-balance", "/v1/analyze"):
        r = client.post(path, files={"file": ("a.dng", _dng())})
        assert r.status_code == 507 and r.json()["error"] == "insufficient_storage", (path, r.text)


def test_a_real_small_tmpfs(tmp_path, monkeypatch):
    """``python -m service`` with TMPDIR on an 8 MB tmpfs (needs root for
    mount): a 1500 x 2000 DNG's 18 MB 16-bit PNG does not fit (507, TMPDIR
    left empty; its 18 MB TIFF is sent from memory and needs none of it); a
    12 MB upload cannot even be spooled (507); /health still 200."""
    import httpx

    small = tmp_path / "small"
    small.mkdir()
    if shutil.which("mount") is None:
        pytest.skip("no mount command")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(small)], capture_output=True,
                       text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root): {r.stderr.strip()[:200]}")
    try:
        (small / "tmp").mkdir()
        dng = _dng(1500, 2000)
        monkeypatch.setenv("TMPDIR", str(small / "tmp"))
        with running_server({"data_dir": tmp_path / "data"}) as (base, _, _log):
            r = httpx.post(base + "/v1/white-balance", files={"file": ("big.dng", dng)}, data={"format": "png16"},
                           timeout=120)
            assert r.status_code == 507 and r.json()["error"] == "insufficient_storage", r.text
            assert os.listdir(small / "tmp") == []
            r = httpx.post(base + "/v1/white-balance", files={"file": ("big.dng", dng)}, timeout=120)
            assert r.status_code == 200 and len(r.content) > 18_000_000, r.text[:300]
            assert os.listdir(small / "tmp") == []
            r = httpx.post(base + "/v1/analyze", files={"file": ("huge.dng", b"\0" * (12 << 20))}, timeout=120)
            assert r.status_code == 507 and r.json()["error"] == "insufficient_storage", r.text
            assert os.listdir(small / "tmp") == []
            assert httpx.get(base + "/health", timeout=10).status_code == 200
    finally:
        subprocess.run(["umount", "-l", str(small)], capture_output=True)
