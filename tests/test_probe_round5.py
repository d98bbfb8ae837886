"""Round 5 of the batch probes (docs/reliability.md, "Round 5"): culprit
isolation (an item that kills its pool worker fails alone, as
``worker_killed``; the items that shared the pool with it end done), and the
faults found by probing ``python -m service``, each with its regression test."""

from __future__ import annotations

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


def _batch(store, d, n=6):
    bid = store.new_batch_id()
    store.create_batch(bid, jobs.batch_options(format="png"), [(f"im{i}.dng", str(d / f"im{i}.dng"))
                                                             for i in range(n)])
    return bid


def test_an_item_that_kills_its_worker_fails_alone_and_the_others_end_done(tmp_path, dngs):
    """One of six items kills its pool worker (SIGKILL, as a segfault in a
    decoder or the OOM killer would) every time it runs. The pool breaks with
    several items in flight; they run again one at a time, alone in the pool:
    only the culprit is charged, and it fails as ``worker_killed`` after
    MAX_ATTEMPTS runs alone; the five innocent items end done, each written
    once."""
    runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), workers=2, poll_s=0.05))
    runner.item_fn = process_or_die({"im2.dng"})
    bid = _batch(runner.store, dngs)
    runner.start()
    try:
        doc = runner.wait(bid, 400)
    finally:
        runner.stop()
    items = {r["name"]: r for r in runner.store.items(bid)}
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
