"""Round 5 of the batch probes (docs/reliability.md, "Round 5"): culprit
isolation (an item that kills its pool worker fails alone, as
``worker_killed``; the items that shared the pool with it end done), and the
faults found by probing ``python -m service``, each with its regression test."""

from __future__ import annotations

import contextlib
import json
import os
import time

import pytest

from service import jobs
from testing.dngwriter import scene_dng
from testing.faults import process_or_die


@pytest.fixture(scope="module")
def dngs(tmp_path_factory):
    d = tmp_path_factory.mktemp("round5")
    for i in range(6):
        scene_dng(d / f"im{i}.dng", "Nikon 5100 (NPL)", "D65", 400, 600, seed=i)
    return d


def _batch(store, d, n=6, **options):
    bid = store.new_batch_id()
    store.create_batch(bid, jobs.batch_options(format="png", **options), [(f"im{i}.dng", str(d / f"im{i}.dng"))
                                                                        for i in range(n)])
    return bid


def _run_with_fault(tmp_path, make_batch, **fault):
    """A two-worker runner with ``fault`` (``item_fn=`` or ``sample_fn=``,
    :mod:`testing.faults`) set from Python, the batch ``make_batch(store)``
    run to its end. Returns the runner, the batch's id, its progress
    document and its items by name."""
    runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), workers=2, poll_s=0.05))
    for k, v in fault.items():
        setattr(runner, k, v)
    bid = make_batch(runner.store)
    runner.start()
    try:
        doc = runner.wait(bid, 400)
    finally:
        runner.stop()
    return runner, bid, doc, {r["name"]: r for r in runner.store.items(bid)}


def test_an_item_that_kills_its_worker_fails_alone_and_the_others_end_done(tmp_path, dngs):
    """One of six items kills its pool worker (SIGKILL, as a segfault in a
    decoder or the OOM killer would) every time it runs. The pool breaks with
    several items in flight; they run again one at a time, alone in the pool:
    only the culprit is charged, and it fails as ``worker_killed`` after
    MAX_ATTEMPTS runs alone; the five innocent items end done, each written
    once."""
    runner, bid, doc, items = _run_with_fault(tmp_path, lambda store: _batch(store, dngs),
                                              item_fn=process_or_die({"im2.dng"}))
    assert doc["counts"]["done"] == 5 and doc["counts"]["failed"] == 1, doc["counts"]
    bad = items["im2.dng"]
    assert bad["status"] == "failed"
    assert bad["error"].startswith("worker_killed:") and f"{jobs.MAX_ATTEMPTS} times" in bad["error"], bad["error"]
    assert all(r["status"] == "done" for n, r in items.items() if n != "im2.dng")
    assert runner.worker_kills == 1 and runner.executor_rebuilds >= jobs.MAX_ATTEMPTS
    with open(os.path.join(runner.store.batch_dir(bid), "writes.log")) as f:
        writes = [json.loads(line)["name"] for line in f]
    assert sorted(writes) == sorted(n for n in items if n != "im2.dng")   # each innocent written once
    # the runs alone are journalled: the culprit's losses, and the innocents' uncharged re-queues
    with open(os.path.join(runner.store.batch_dir(bid), jobs.JOURNAL)) as f:
        journal = [json.loads(line) for line in f]
    assert sum("(it ran alone)" in (j.get("requeued") or "") for j in journal) == jobs.MAX_ATTEMPTS - 1
    assert runner.health()["isolating"] == 0


def test_suspects_run_alone_and_nothing_else_runs_meanwhile(tmp_path, dngs):
    """While a suspect runs alone, the runner hands out nothing else: it is
    the only item in flight."""
    runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), workers=2, poll_s=0.05))
    runner.item_fn = process_or_die({"im0.dng"}, delay_s=0.0)
    bid = _batch(runner.store, dngs, n=4)
    runner.start()
    most, seen = 0, 0
    try:
        t_end = time.monotonic() + 400
        while time.monotonic() < t_end:
            with runner._lock:
                if runner._solo is not None:   # a suspect running alone: nothing else in flight
                    seen += 1
                    most = max(most, len(runner._inflight))
            doc = runner.store.progress(bid)
            if doc["status"] == "done" and doc["settled"]:
                break
            time.sleep(0.01)
    finally:
        runner.stop()
    assert doc["counts"]["done"] == 3 and doc["counts"]["failed"] == 1, doc["counts"]
    assert seen > 0 and most == 1


# --------------------------------------------------------------------------- faults found by probing the server

def _start_server(env: dict, log_path: str):
    """``python -m service`` (as users start it) on a free port."""
    import socket
    import subprocess
    import sys

    import httpx

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    full = {**os.environ, "WANDELL_HOST": "127.0.0.1", "WANDELL_PORT": str(port), "WANDELL_BATCH_WORKERS": "1",
            **env}
    proc = subprocess.Popen([sys.executable, "-m", "service"], env=full, stdout=open(log_path, "w"),
                            stderr=subprocess.STDOUT, cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    base = f"http://127.0.0.1:{port}"
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end and proc.poll() is None:
        try:
            if httpx.get(base + "/health", timeout=2).status_code == 200:
                return base, proc
        except httpx.HTTPError:
            time.sleep(0.2)
    proc.kill()
    pytest.fail(f"the server did not start: {open(log_path).read()[-2000:]}")


def _tree(path, fn):
    for dirpath, dirs, files in os.walk(path):
        for n in dirs + files:
            fn(os.path.join(dirpath, n))
    fn(path)


@contextlib.contextmanager
def _read_only(data: str):
    """``data`` made read-only: its files' and folders' write bits removed;
    as root (which permissions do not stop) a read-only bind mount of it
    instead, or a skip where mounting is not permitted."""
    import stat
    import subprocess

    if os.geteuid() != 0:
        _tree(data, lambda p: os.chmod(p, os.stat(p).st_mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH)))
        try:
            yield
        finally:
            _tree(data, lambda p: os.chmod(p, os.stat(p).st_mode | stat.S_IWUSR))
        return
    if subprocess.run(["mount", "--bind", data, data], capture_output=True).returncode != 0:
        pytest.skip("running as root (permissions do not stop it) and a read-only bind mount is not permitted")
    try:
        if subprocess.run(["mount", "-o", "remount,bind,ro", data], capture_output=True).returncode != 0:
            pytest.skip("running as root and the bind mount cannot be made read-only")
        yield
    finally:
        subprocess.run(["umount", "-l", data], capture_output=True)


def test_a_read_only_data_directory_serves_its_batches_read_only_and_says_so(tmp_path, dngs):
    """A server started on a data directory whose files are read-only (a
    restored backup, another owner's volume) used to say ``/health`` ok while
    every batch URL was a 503 (the runner could not re-queue, so nothing
    started). Now the finished results are served, ``/health`` is degraded
    with ``job_store.status = read_only``, and every write (a new batch, a
    cancel, a removal) is a 503 ``job_store_read_only``: no 500, nothing
    changed on disk."""
    data = str(tmp_path / "data")
    runner = jobs.BatchRunner(jobs.RunnerConfig(data, workers=1, poll_s=0.05))
    done = _batch(runner.store, dngs, n=2)
    runner.start()
    try:
        assert runner.wait(done, 300)["counts"]["done"] == 2
    finally:
        runner.stop()
    queued = _batch(runner.store, dngs, n=2)          # made, never run
    result = runner.store.item_by_index(done, 0)["out"]
    before = {p: os.stat(p).st_mtime_ns for p in [os.path.join(data, "jobs.sqlite"), result]}
    log = str(tmp_path / "server.log")
    with _read_only(data):
        base, proc = _start_server({"WANDELL_DATA_DIR": data}, log)
        try:
            _read_only_answers(base, done, queued, result, dngs)
        finally:
            proc.terminate()
            proc.wait(30)
    assert {p: os.stat(p).st_mtime_ns for p in before} == before
    text = open(log).read()
    assert " 500 " not in text and "Traceback" not in text, text[-3000:]


def _read_only_answers(base, done, queued, result, dngs):
    import httpx

    h = httpx.get(base + "/health").json()
    assert h["status"] == "degraded" and h["job_store"]["status"] == "read_only", h
    assert "read_only_store" in h["job_store"]["error"]
    assert httpx.get(f"{base}/v1/batches/{done}").json()["counts"]["done"] == 2
    r = httpx.get(f"{base}/v1/batches/{done}/items/by-index/0")
    assert r.status_code == 200 and r.content == open(result, "rb").read()
    assert httpx.get(f"{base}/v1/batches/{done}/zip").status_code == 200
    q = httpx.get(f"{base}/v1/batches/{queued}").json()
    assert q["status"] == "queued" and q["runner_error"].startswith("read_only_store"), q
    with open(dngs / "im0.dng", "rb") as f:
        r = httpx.post(f"{base}/v1/batches", files={"files": ("a.dng", f.read())})
    assert r.status_code == 503 and r.json()["error"] == "job_store_read_only", r.text
    r = httpx.post(f"{base}/v1/batches/{queued}/cancel")
    assert r.status_code == 503 and r.json()["error"] == "job_store_read_only", r.text
    r = httpx.delete(f"{base}/v1/batches/{done}", params={"remove": "true"})
    assert r.status_code == 503 and r.json()["error"] == "job_store_read_only", r.text


def test_a_store_that_cannot_be_opened_makes_health_degraded(tmp_path):
    """A data directory that cannot hold the store (here a regular file in
    its place) used to leave ``/health`` ok (``not_started``) while the batch
    endpoints answered 503: it now says ``unavailable`` and why."""
    from .conftest import isolated_app_client

    bad = tmp_path / "not-a-dir"
    bad.write_text("x")
    for c in isolated_app_client(bad):
        r = c.get("/v1/batches")
        assert r.status_code == 503 and r.json()["error"] == "job_store_unavailable"
        h = c.get("/health").json()
        assert h["status"] == "degraded" and h["job_store"]["status"] == "unavailable", h
        assert "cannot be opened" in h["job_store"]["error"]


def test_a_result_removed_by_hand_is_410_result_gone_not_409_done(tmp_path, dngs):
    """A result file (or the whole ``out/`` folder) removed by hand while the
    server runs: the item's download and the zip used to answer 409
    ``not_ready`` with "item is done" / "no finished results yet". Now
    410 ``result_gone``; the progress document is unchanged."""
    import shutil

    from .conftest import isolated_app_client

    for c in isolated_app_client(tmp_path / "store"):
        files = [("files", (f"im{i}.dng", open(dngs / f"im{i}.dng", "rb").read())) for i in range(2)]
        bid = c.post("/v1/batches", files=files, data={"format": "png"}).json()["id"]
        t_end = time.monotonic() + 300
        while time.monotonic() < t_end and not (d := c.get(f"/v1/batches/{bid}").json())["settled"]:
            time.sleep(0.2)
        assert d["counts"]["done"] == 2, d
        out = os.path.join(str(tmp_path / "store"), "batches", bid, "out")
        os.unlink(os.path.join(out, "im0.png"))
        r = c.get(f"/v1/batches/{bid}/items/by-index/0")
        assert r.status_code == 410 and r.json()["error"] == "result_gone", r.text
        assert c.get(f"/v1/batches/{bid}/items/by-index/1").status_code == 200
        assert c.get(f"/v1/batches/{bid}/zip").status_code == 200       # the other result, and FAILURES.txt
        shutil.rmtree(out)
        r = c.get(f"/v1/batches/{bid}/zip")
        assert r.status_code == 410 and r.json()["error"] == "result_gone", r.text
        assert c.get(f"/v1/batches/{bid}").json()["counts"]["done"] == 2


def test_shared_light_with_an_image_that_kills_its_worker_ends(tmp_path, dngs):
    """``lighting=shared``: the per-image estimation of one image kills its
    worker each time. It used to estimate every image again after each lost
    worker, for ever (the batch never ended, the pool broke every few
    seconds). Now the images not yet estimated run one at a time, alone;
    the culprit fails as ``worker_killed`` and the light is made from the
    others, whose items end done."""
    from testing.faults import sample_or_die

    runner, bid, doc, items = _run_with_fault(tmp_path, lambda store: _batch(store, dngs, 4, lighting="shared"),
                                              sample_fn=sample_or_die({"im1.dng"}, delay_s=0.0))
    assert doc["counts"]["done"] == 3 and doc["counts"]["failed"] == 1, doc["counts"]
    assert items["im1.dng"]["error"].startswith("worker_killed:"), items["im1.dng"]["error"]
    assert runner.store.batch(bid)["light"] is not None


def test_batch_folders_left_by_a_post_cut_by_a_crash_are_removed(tmp_path, dngs):
    """kill -9 while 20 batches were being POSTed left up to 20 batch folders
    (uploads half written, no manifest) that no batch owned: never listed,
    never expired, kept for ever (``benchmarks.batch_many_restart --stop
    kill9 --during 0.38``: 11 of them). They are removed once unchanged for
    ``orphan_age_s``; a batch, one waiting for registration and a folder
    still being written are kept."""
    runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), workers=1, orphan_age_s=60))
    store = runner.store
    owned = _batch(store, dngs, n=1)
    cut, fresh, waiting = store.new_batch_id(), store.new_batch_id(), store.new_batch_id()
    for bid in (cut, fresh, waiting):
        with open(os.path.join(store.batch_dir(bid), "in", "00000-a.dng"), "wb") as f:
            f.write(b"half an upload")
    store.defer(waiting)   # (its manifest would be there too; the marker is what keeps it)
    old = time.time() - 3600
    for bid in (cut, owned, waiting):
        for d, dirs, files in os.walk(store.batch_dir(bid)):
            for n in dirs + files + ["."]:
                os.utime(os.path.join(d, n), (old, old))
    assert runner.remove_orphan_folders() == [cut]
    left = set(os.listdir(os.path.join(store.data_dir, "batches")))
    assert left == {owned, fresh, waiting}
    # a store rebuilt from the folders (store lost) no longer brings the cut one back as a batch
    os.unlink(store.path)
    rebuilt = jobs.JobStore(store.data_dir)
    assert rebuilt.batch(cut) is None and rebuilt.batch(owned) is not None
