"""Issue 28, part A: the mechanisms that make an item end exactly once
whatever happens to the process running it (docs/reliability.md), each on
its own: re-queue on a graceful stop, a broken pool replaced and its items
retried (a bounded number of times), a closed Dask client replaced, a lost
or empty store rebuilt from the batch folders, results the store could not
take recorded later, items opened under their root with no symlink followed,
a folder scanned no further than the item limit, a busy store a 503."""

from __future__ import annotations

import os
import signal
import sqlite3
import time

import pytest

from service import jobs
from service.errors import ServiceError
from testing.dngwriter import scene_dng


@pytest.fixture(scope="module")
def dngs(tmp_path_factory):
    d = tmp_path_factory.mktemp("survival")
    for i in range(4):
        scene_dng(d / f"im{i}.dng", "Nikon 5100 (NPL)", "D65", 400, 600, seed=i)
    return d


def _batch(store, d, n=4, fmt="png"):
    bid = store.new_batch_id()
    store.create_batch(bid, jobs.batch_options(format=fmt), [(f"im{i}.dng", str(d / f"im{i}.dng"))
                                                             for i in range(n)])
    return bid


def _wait(pred, timeout=120.0):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if pred():
            return True
        time.sleep(0.05)
    return False


def test_graceful_stop_requeues_items_in_flight_and_leaves_no_lock(tmp_path, dngs):
    """stop(wait=False) (SIGTERM, Ctrl-C) ends the pool at once: the items in
    flight go back to pending (journalled), none is failed, no .lock stays;
    a new runner on the same store finishes them."""
    cfg = jobs.RunnerConfig(str(tmp_path / "data"), workers=1, poll_s=0.05)
    runner = jobs.BatchRunner(cfg)
    bid = _batch(runner.store, dngs)
    runner.start()
    assert _wait(lambda: runner.store.counts(bid)["running"] >= 1)
    runner.stop(wait=False)
    c = runner.store.counts(bid)
    assert c["failed"] == 0 and c["running"] == 0, c
    assert c["pending"] >= 1, c
    out = os.path.join(runner.store.batch_dir(bid), "out", ".wandell")
    assert not [f for f in (os.listdir(out) if os.path.isdir(out) else []) if f.endswith(".lock")]
    journal = open(os.path.join(runner.store.batch_dir(bid), jobs.JOURNAL)).read()
    assert '"status": "pending"' in journal            # the re-queue is journalled (a rebuilt store keeps it)
    again = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), workers=1, poll_s=0.05))
    again.start()
    try:
        doc = again.wait(bid, 180)
    finally:
        again.stop()
    assert doc["counts"]["done"] == 4, doc["counts"]


def test_killed_pool_worker_is_replaced_and_its_items_retried(tmp_path, dngs):
    """A pool worker killed (as by the OOM killer) breaks the pool: the
    runner replaces it, the items it failed run again, and a later batch runs."""
    runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), workers=2, poll_s=0.05))
    bid = _batch(runner.store, dngs)
    runner.start()
    try:
        assert _wait(lambda: runner.store.counts(bid)["running"] >= 1)
        pids = list(runner.executor._pool._processes)
        os.kill(pids[0], signal.SIGKILL)
        doc = runner.wait(bid, 180)
        assert doc["counts"]["done"] == 4, doc
        assert runner.executor_rebuilds >= 1
        later = _batch(runner.store, dngs, n=1)
        runner.wake()
        assert runner.wait(later, 120)["counts"]["done"] == 1
    finally:
        runner.stop()


def test_an_item_whose_worker_is_always_lost_fails_after_max_attempts(tmp_path, dngs):
    """requeue_item with a bound: pending again until the item was run
    MAX_ATTEMPTS times, then failed with the reason and the count."""
    store = jobs.JobStore(str(tmp_path / "data"))
    bid = _batch(store, dngs, n=1)
    store.start_batch(bid)
    states = []
    for _ in range(jobs.MAX_ATTEMPTS):
        assert len(store.claim(bid, 1)) == 1
        states.append(store.requeue_item(bid, 0, "worker_lost: BrokenProcessPool", jobs.MAX_ATTEMPTS))
    assert states == ["pending"] * (jobs.MAX_ATTEMPTS - 1) + ["failed"]
    row = store.item_by_index(bid, 0)
    assert row["status"] == "failed" and f"run {jobs.MAX_ATTEMPTS} times" in row["error"]
    # a cancelled batch's item is cancelled, not re-queued (else the batch never settles)
    bid2 = _batch(store, dngs, n=1)
    store.start_batch(bid2)
    store.claim(bid2, 1)
    store.cancel(bid2)
    assert store.requeue_item(bid2, 0, "stopped") == "cancelled"
    assert store.progress(bid2)["settled"]


def test_closed_dask_client_is_replaced_and_capacity_follows_the_cluster(tmp_path):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"),
                                                    dask_scheduler=cluster.scheduler_address))
        ex = runner.executor
        assert ex.workers == 1 and ex.broken is None
        cluster.scale(2)
        assert _wait(lambda: (setattr(ex, "_asked", float("-inf")) or ex.workers) == 2, 60)
        ex.client.close()
        assert ex.broken
        runner._replace_broken_executor()
        assert runner.executor_rebuilds == 1
        again = runner.executor                 # a new client to the same scheduler
        assert again is not ex and again.broken is None and again.workers == 2
        runner.stop()


def test_no_dask_worker_is_said_in_the_runner_state(tmp_path, dngs):
    """A cluster with no worker: nothing is handed out, the progress and
    /health say the runner waits for workers (no silent 'running')."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster:
        runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"),
                                                    dask_scheduler=cluster.scheduler_address))
        bid = _batch(runner.store, dngs, n=1)
        runner._tick()
        assert runner.executor_error.startswith("waiting_for_workers"), runner.executor_error
        assert runner.store.counts(bid)["pending"] == 1
        h = runner.health()
        assert h["status"] == "degraded" and h["since"] is not None
        runner.stop()


@pytest.mark.parametrize("how", ["deleted", "empty"])
def test_lost_store_is_rebuilt_from_the_batch_folders(tmp_path, dngs, how):
    data = str(tmp_path / "data")
    store = jobs.JobStore(data)
    bid = _batch(store, dngs, n=2)
    store.start_batch(bid)
    store.claim(bid, 2)
    store.finish_item(bid, 0, {"status": "failed", "error": "corrupt_file: x"})
    db = os.path.join(data, "jobs.sqlite")
    del store
    for suffix in ("", "-wal", "-shm"):
        if os.path.exists(db + suffix):
            os.unlink(db + suffix)
    if how == "empty":
        open(db, "wb").close()
    again = jobs.JobStore(data)
    assert again.recovered and again.recovered["batches_recovered"] == 1, again.recovered
    assert how in again.recovered["error"] or (how == "deleted" and "missing" in again.recovered["error"])
    by = {r["idx"]: r["status"] for r in again.items(bid)}
    assert by == {0: "failed", 1: "pending"}, by          # journalled failure kept; unfinished re-queued


def test_store_deleted_while_running_is_noticed_and_rebuilt(tmp_path, dngs):
    data = str(tmp_path / "data")
    store = jobs.JobStore(data)
    bid = _batch(store, dngs, n=1)
    assert store.check_file() == 0
    os.unlink(os.path.join(data, "jobs.sqlite"))
    assert store.check_file() == 1
    assert store.batch(bid) is not None


def test_result_the_store_cannot_take_is_recorded_later(tmp_path, dngs):
    """A done callback whose store write fails (disk full, locked) keeps the
    transition and records it at a later step: the item never stays running."""
    runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), poll_s=0.05))
    bid = _batch(runner.store, dngs, n=1)
    runner.store.start_batch(bid)
    runner.store.claim(bid, 1)
    real = runner.store.finish_item
    calls = []

    def full(*a):
        calls.append(a)
        if len(calls) == 1:
            raise sqlite3.OperationalError("database or disk is full")
        return real(*a)

    runner.store.finish_item = full
    from concurrent.futures import Future

    f: Future = Future()
    f.set_result({"status": "done", "illuminant": {"cct": 6500}})
    runner._done((bid, 0), f)
    assert runner.store.counts(bid)["running"] == 1 and len(runner._unrecorded) == 1
    runner._flush_unrecorded()
    assert runner.store.counts(bid)["done"] == 1 and not runner._unrecorded
    assert runner.store.batch(bid)["status"] == "done"


def test_items_are_opened_under_their_root_with_no_symlink_followed(tmp_path):
    root, outside = tmp_path / "root", tmp_path / "outside"
    (root / "shoot").mkdir(parents=True)
    outside.mkdir()
    (root / "shoot" / "a.dng").write_bytes(b"inside")
    (outside / "a.dng").write_bytes(b"outside")
    task = jobs.ItemTask(src=str(root / "shoot" / "a.dng"), out=str(tmp_path / "o.png"), name="a.dng",
                         options=jobs.batch_options(), max_pixels=1, estimation_pixels=1, root=str(root),
                         max_bytes=100)
    assert jobs.read_source(task) == b"inside"
    os.rename(root / "shoot", root / "shoot.old")
    os.symlink(outside, root / "shoot")                      # swapped after the batch was checked
    with pytest.raises(ServiceError) as e:
        jobs.read_source(task)
    assert e.value.code == "path_outside_root"
    os.unlink(root / "shoot")
    os.rename(root / "shoot.old", root / "shoot")
    (root / "shoot" / "a.dng").write_bytes(b"x" * 101)       # grew past the limit after creation
    with pytest.raises(ServiceError) as e:
        jobs.read_source(task)
    assert e.value.status == 413


def test_folder_scan_stops_at_the_item_limit_and_keeps_odd_names_as_failed_items(tmp_path):
    root = tmp_path / "root"
    big = root / "big"
    big.mkdir(parents=True)
    for i in range(50):
        (big / f"f{i:03d}.dng").write_bytes(b"x")
    with pytest.raises(ServiceError) as e:
        jobs.scan_folder(str(root), "big", limit=10)
    assert e.value.status == 413 and e.value.code == "too_many_items"
    odd = root / "odd"
    odd.mkdir()
    (odd / "ok.dng").write_bytes(b"x")
    with open(os.path.join(os.fsencode(str(odd)), b"caf\xe9.dng"), "wb") as f:
        f.write(b"x")
    out, refused = jobs.scan_folder(str(root), "odd", limit=10)
    assert len(out) == 2 and len(refused) == 1
    (i, err), = refused.items()
    assert "not UTF-8" in err and out[i][1] == "" and "\ufffd" in out[i][0]
    store = jobs.JobStore(str(tmp_path / "data"))
    bid = store.new_batch_id()
    store.create_batch(bid, jobs.batch_options(), out, refused)    # no UnicodeEncodeError
    assert {r["status"] for r in store.items(bid)} == {"pending", "failed"}


def test_busy_store_is_a_503_with_retry_after_not_a_blocked_server(tmp_path):
    from service.routers.batches import StoreBusy, store_errors

    store = jobs.JobStore(str(tmp_path / "data"), busy_timeout=0.2)
    bid = store.new_batch_id()
    lock = sqlite3.connect(store.path, isolation_level=None)
    lock.execute("BEGIN IMMEDIATE")
    t0 = time.monotonic()
    try:
        with pytest.raises(StoreBusy) as e, store_errors():
            store.create_batch(bid, jobs.batch_options(), [("a.dng", str(tmp_path / "a.dng"))])
    finally:
        lock.execute("ROLLBACK")
        lock.close()
    assert time.monotonic() - t0 < 5
    assert e.value.status == 503 and e.value.headers["Retry-After"]
    # the manifest was written first: the deferred batch is registered once the store is free
    store.defer(bid)
    assert store.unregistered() == [bid] and store.manifest_progress(bid)["status"] == "queued"
    assert store.adopt_batch(bid) and store.unregistered() == []


def test_scheduler_that_never_answers_is_said_not_hidden(tmp_path, dngs):
    """A listener that accepts connections and never speaks (a hung
    scheduler): the items wait, the runner says why (progress, /health),
    and it tries again later instead of blocking at every step."""
    pytest.importorskip("distributed")
    import socket

    srv = socket.socket()
    srv.bind(("127.0.0.1", 0))
    srv.listen(16)
    try:
        runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), dask_timeout=2,
                                                    dask_scheduler=f"tcp://127.0.0.1:{srv.getsockname()[1]}"))
        bid = _batch(runner.store, dngs, n=1)
        t0 = time.monotonic()
        runner._tick()
        assert runner.executor_error.startswith("executor_unavailable"), runner.executor_error
        assert runner.health()["status"] == "degraded"
        runner._tick()                       # within reconnect_s: no second 2 s wait
        assert time.monotonic() - t0 < 2 * 2 + 10
        assert runner.store.counts(bid)["pending"] == 1
        runner.stop()
    finally:
        srv.close()
