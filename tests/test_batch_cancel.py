"""Issue 19, item 2: cancelling a batch stops the items already handed to the
workers, not only the queued ones; results finished before are kept, and
the progress document says when every count is final (``settled``).

A real runner on a real local process pool, real DNGs (testing.dngwriter)
large enough that items are still running when the cancel comes.
"""

from __future__ import annotations

import os
import time

import pytest

from service import jobs
from testing.dngwriter import scene_dng

from .test_jobs import task


def test_an_item_of_a_cancelled_batch_stops_without_writing(tmp_path):
    src = tmp_path / "a.dng"
    scene_dng(src, "Nikon 5100 (NPL)", "D4000", 64, 96, seed=1)
    flag = tmp_path / "cancelled"
    flag.write_text("")
    out = tmp_path / "out" / "a.png"
    out.parent.mkdir()
    res = jobs.process_item(task(src, out, cancel_file=str(flag)))
    assert res["status"] == "cancelled"
    assert not out.exists() and not os.path.exists(jobs.meta_path(str(out), ".json"))
    flag.unlink()  # the same task without the marker runs
    assert jobs.process_item(task(src, out, cancel_file=str(flag)))["status"] == "done" and out.exists()


@pytest.fixture(scope="module")
def big_dngs(tmp_path_factory):
    d = tmp_path_factory.mktemp("cancel-shoot")
    for i in range(8):
        scene_dng(d / f"im{i}.dng", "Nikon 5100 (NPL)", "D4000", 1000, 1500, seed=i)
    return sorted(d.glob("*.dng"))


def test_cancel_stops_running_items_keeps_done_ones_and_settles(tmp_path, big_dngs):
    ex = jobs.LocalExecutor(2)
    runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), poll_s=0.05), executor=ex)
    try:
        runner.start()
        store = runner.store
        bid = store.new_batch_id()
        store.create_batch(bid, jobs.batch_options(format="png"), [(p.name, str(p)) for p in big_dngs])
        runner.wake()
        t_end = time.monotonic() + 180
        while True:  # one item done, others handed to the workers
            c = store.counts(bid)
            if c["done"] >= 1 and c["running"] >= 2:
                break
            assert c["done"] + c["failed"] < len(big_dngs), "finished before the cancel: the test proves nothing"
            assert time.monotonic() < t_end, c
            time.sleep(0.02)
        running = {r["name"] for r in store.items(bid) if r["status"] == "running"}
        done_before = {r["name"] for r in store.items(bid) if r["status"] == "done"}
        t0 = time.monotonic()
        assert runner.cancel(bid)
        doc = store.progress(bid)
        assert doc["status"] == "cancelled" and not doc["settled"]  # running ones still answering
        doc = runner.wait(bid, timeout=60)
        took = time.monotonic() - t0
        assert doc["settled"] and doc["counts"]["running"] == 0 and doc["counts"]["pending"] == 0
        by = {it["name"]: it for it in doc["items"]}
        assert all(by[n]["status"] == "done" for n in done_before)  # kept
        stopped = {n for n in running if by[n]["status"] == "cancelled"}
        assert stopped, f"every running item ran to its end: {[by[n]['status'] for n in running]}"
        assert took < 20, took
        c = doc["counts"]
        assert c["done"] + c["cancelled"] + c["failed"] == len(big_dngs)
        out_dir = os.path.join(store.batch_dir(bid), "out")
        on_disk = {f for f in os.listdir(out_dir) if not f.startswith(".")}
        assert on_disk == {os.path.splitext(n)[0] + ".png" for n, it in by.items() if it["status"] == "done"}
        assert not [f for f in os.listdir(out_dir) if f.endswith(".part")]
    finally:
        runner.stop(wait=False)
