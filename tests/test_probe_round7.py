"""Round 7 of probing, as a hostile client and as a new user
(docs/probe_round7.md): each test is the minimal reproduction of one fault
found, through the command line as users run it (``python -m service.cli``)
or the real ASGI stack (FastAPI's TestClient), and holds once the fault is
fixed."""

from __future__ import annotations

import json
import time

import pytest

from .conftest import run_cli as _cli
from .conftest import scene_dng_bytes


@pytest.fixture(scope="module")
def dng() -> bytes:
    return scene_dng_bytes(64, 96)



# --- 1. wandell batch DIR DIR, run again ----------------------------------------------------

def test_a_rerun_of_batch_into_its_own_input_folder_does_not_take_its_outputs_as_photographs(tmp_path, dng):
    """``wandell batch DIR DIR`` (the corrected pictures beside the RAWs) is
    accepted; run again (a rerun, as after Ctrl-C or to add photographs), it
    took its own outputs for new photographs: ``a.png`` failed as an 8-bit
    image (exit 1), and with ``png16`` each output was corrected again into
    ``a (2).png``, one generation more each run. Its outputs (those with a
    record in ``DIR/.wandell``) are now left out, as the sidecars are."""
    src = tmp_path / "shoot"
    src.mkdir()
    for name in ("a.dng", "b.dng"):
        (src / name).write_bytes(dng)
    for fmt in ("png", "png16"):
        args = ("batch", "--format", fmt, "--workers", "1", "--force", str(src), str(src))
        r = _cli(*args)
        assert r.returncode == 0, (r.stdout, r.stderr)
        first = sorted(p.name for p in src.iterdir())
        assert first == [".wandell", "a.dng", "a.png", "b.dng", "b.png", "batch.json"], first
        r = _cli(*args[:-3], str(src), str(src))          # the same command without --force: a rerun
        assert r.returncode == 0, (fmt, r.stdout, r.stderr)
        assert "0 done, 2 skipped" in r.stdout and "2 in all" in r.stdout, (fmt, r.stdout)
        assert "not processed" not in r.stdout, r.stdout      # batch.json is ours too
        assert sorted(p.name for p in src.iterdir()) == first, "its outputs were processed as photographs"
    # a PNG of the user's own (no record of ours) in the folder is still a photograph
    (src / "c.png").write_bytes((src / "a.png").read_bytes())
    r = _cli("batch", "--format", "png16", "--workers", "1", str(src), str(src))
    assert "c.png" in r.stdout and "3 in all" in r.stdout, (r.stdout, r.stderr)


# --- 2. output paths that are files or folders ----------------------------------------------

def test_an_output_folder_that_is_a_file_is_a_usage_error_in_words(tmp_path, dng):
    """``wandell batch IN OUT`` with OUT an existing file (or a path through
    one) printed Python's ``[Errno 17] File exists: 'OUT'`` and exited 1,
    the status of "some file failed"; ``wandell white-balance FILE OUT``
    with OUT an existing folder failed the file with ``IsADirectoryError:
    [Errno 21] ... .part' -> 'OUT'``. Both are usage errors (exit 2) saying
    what is wrong, before any work."""
    src = tmp_path / "in"
    src.mkdir()
    (src / "a.dng").write_bytes(dng)
    afile = tmp_path / "notes.txt"
    afile.write_text("mine\n")
    for out in (afile, afile / "sub"):
        r = _cli("batch", "--workers", "1", str(src), str(out))
        assert r.returncode == 2, (out, r.returncode, r.stdout, r.stderr)
        assert "not_a_folder" in r.stderr and str(afile) in r.stderr and "Errno" not in r.stderr, r.stderr
    assert afile.read_text() == "mine\n"
    folder = tmp_path / "x.png"
    folder.mkdir()
    for out in (folder, afile / "x.png"):
        r = _cli("white-balance", str(src / "a.dng"), str(out))
        assert r.returncode == 2, (out, r.returncode, r.stdout, r.stderr)
        assert "Errno" not in r.stderr + r.stdout and ("not_a_file" in r.stderr or "not_a_folder" in r.stderr), \
            r.stderr
    assert list(folder.iterdir()) == []


# --- 3. --workers --------------------------------------------------------------------------

def test_batch_workers_are_bounded_not_spawned_by_the_hundred_thousand(tmp_path, dng):
    """``wandell batch --workers 100000`` on one photograph started a pool of
    100,000 spawned Python processes (every worker is started at once): on
    the 2-core machine it had not finished after 300 s, memory climbing.
    ``--workers -1`` was taken silently. Now both are usage errors (exit 2)
    naming the accepted range, at once; the local pool itself never starts
    more than that bound (``WANDELL_BATCH_WORKERS`` goes through it too)."""
    from service.batch.executors import max_local_workers

    src = tmp_path / "in"
    src.mkdir()
    (src / "a.dng").write_bytes(dng)
    limit = max_local_workers()
    for n in ("100000", "-1", str(limit + 1)):
        t0 = time.monotonic()
        r = _cli("batch", "--workers", n, str(src), str(tmp_path / "out"), timeout=120)
        assert r.returncode == 2, (n, r.returncode, r.stdout, r.stderr)
        assert "--workers" in r.stderr and f"0..{limit}" in r.stderr, r.stderr
        assert time.monotonic() - t0 < 60
    assert not (tmp_path / "out").exists()
    r = _cli("batch", "--workers", "1", "--format", "png", str(src), str(tmp_path / "out"))
    assert r.returncode == 0, (r.stdout, r.stderr)


def test_the_local_pool_is_clamped_to_its_bound():
    """The server's pool (``WANDELL_BATCH_WORKERS``) is made by the same
    class: a huge count starts at most :func:`max_local_workers` processes."""
    from service.batch.executors import LocalExecutor, max_local_workers

    pool = LocalExecutor(10 ** 6)
    try:
        assert pool.workers == max_local_workers()
        assert len(pool._pool._processes) <= max_local_workers()
    finally:
        pool.terminate(kill=True)


# --- 4. a file field that is not a file ----------------------------------------------------

@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from .conftest import isolated_app_client

    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")


@pytest.mark.parametrize("path, field", [("/v1/analyze", "file"), ("/v1/white-balance", "file"),
                                         ("/v1/batches", "files")])
def test_a_file_field_sent_as_text_says_it_must_be_a_file_not_a_python_type(client, dng, path, field):
    """A ``file`` part without a file name (as ``curl -F file=<PHOTO``
    sends it) was a 422 whose detail was pydantic's "Value error, Expected
    UploadFile, received: <class 'str'>". It is still a 422
    ``invalid_parameter`` naming the field, and now says what to send. (A
    browser's empty file input, ``filename=""``, was and is "Field
    required", or for a batch "give either files ... or folder".)"""
    for disposition in (f'name="{field}"', f'name="{field}"; filename=""'):
        body = (b"--B\r\nContent-Disposition: form-data; " + disposition.encode() + b"\r\n\r\n"
                + (dng if "filename" not in disposition else b"") + b"\r\n--B--\r\n")
        r = client.post(path, content=body, headers={"content-type": "multipart/form-data; boundary=B"})
        assert r.status_code == 422, (disposition, r.status_code, r.text)
        err = r.json()
        assert err["error"] == "invalid_parameter" and "<class" not in err["detail"], err
        if "filename" not in disposition:     # (an empty one is "Field required", or files-or-folder)
            assert err["detail"].startswith(field) and "must be a file" in err["detail"], err


# --- 5. /v1/surfaces: one limit for points, rectangles and grid cells ----------------------

def _points(n: int) -> str:
    return json.dumps([[i % 64, (i // 64) % 96] for i in range(n)])


def test_surface_points_are_bounded_by_the_documented_setting_alone(client, dng, env_settings):
    """``WANDELL_MAX_SURFACE_REGIONS`` (README: points + rectangles + grid
    cells per request, 413 ``too_many_regions`` over it) was not the only
    bound: ``points`` or ``rects`` alone were capped at 10,000 by the
    parser, a 422 ``invalid_parameter`` "at most 10000 entries", while 5,000
    points and 5,001 rectangles were the documented 413. A server whose
    setting is raised refused 10,001 points all the same. Now the setting
    decides, whichever lists the regions come in (the 1,000,000-character
    limit of a JSON field still bounds the parsing)."""
    r = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data={"points": _points(10001)})
    assert r.status_code == 413 and r.json()["error"] == "too_many_regions", r.text
    assert "WANDELL_MAX_SURFACE_REGIONS" in r.json()["detail"]
    rects = json.dumps([[0, 0, 1, 1]] * 10001)
    r = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data={"rects": rects})
    assert r.status_code == 413 and r.json()["error"] == "too_many_regions", r.text
    env_settings(max_surface_regions=10002)
    r = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data={"points": _points(10001),
                                                                          "format": "csv"})
    assert r.status_code == 200, r.text[:300]
    assert len(r.text.strip().splitlines()) == 10001 + 1          # a header and a row per point


# --- 6. an existing read-only output ---------------------------------------------------------

def test_white_balance_keeps_an_existing_read_only_output(tmp_path, dng):
    """``wandell white-balance FILE OUT`` writes OUT beside and renames it
    over: an OUT the user had made read-only (``chmod a-w``) was replaced
    without a word (exit 0). It is kept now, a usage error (exit 2) saying
    why and what to do; a writable OUT is still replaced."""
    src = tmp_path / "a.dng"
    src.write_bytes(dng)
    out = tmp_path / "a.png"
    out.write_bytes(b"the user's own picture")
    out.chmod(0o444)
    r = _cli("white-balance", str(src), str(out))
    assert r.returncode == 2 and "output_read_only" in r.stderr and "read-only" in r.stderr, (r.stdout, r.stderr)
    assert out.read_bytes() == b"the user's own picture"
    out.chmod(0o644)
    r = _cli("white-balance", str(src), str(out))
    assert r.returncode == 0 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", (r.stdout, r.stderr)
