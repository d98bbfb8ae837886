"""Batches under faults, counted (issue 28): for each fault class, how many
items end done / failed / stuck / written more than once, over repeated runs.

``python -m benchmarks.batch_faults [--runs 10] [--items 6] [--faults stop,kill9,...] [--dask-runs 3]``

Each run makes a fresh data directory and a batch of ``--items`` DNGs
(:mod:`testing.dngwriter`, 600 x 900), runs it on the real runner
(:class:`service.batch.runner.BatchRunner`, a spawn process pool of 2
workers, or a real ``dask scheduler`` + ``dask worker`` for
``scheduler_lost``), injects the fault once at least one item is running,
lets the service recover as it would (a restart where the fault is one), and
waits up to 180 s for the batch to settle. Counted per run:

- **done**, **failed**: the items' final states (no input is bad, so every
  failure is the fault's);
- **stuck**: items still ``pending``/``running`` after the wait;
- **duplicated**: outputs renamed into place more than once (the batch's
  ``writes.log``, one line per rename);
- **lock files left** in ``out/.wandell`` and **re-queued**: how often an item went
  back to pending (the journal ``states.jsonl``);
- **the fault reached items**: runs in which it did (an item re-queued; for
  ``disk_full`` and ``store_locked``, where the journal itself may miss the
  line: the runner kept a state change for later, or re-queued an item whose
  output could not be written, :attr:`BatchRunner.records_deferred` /
  ``disk_full_retries``).

Faults: ``stop`` (graceful stop mid-batch: SIGTERM/Ctrl-C's path, then a
restart), ``kill9`` (the runner's process and its pool killed with SIGKILL,
then a restart), ``worker_killed`` (one pool worker SIGKILLed, as by the OOM
killer; no restart), ``store_lost`` (a stop, ``jobs.sqlite`` deleted, a
restart), ``store_locked`` (another connection holds the store's write lock
mid-batch until an item's end has met it, and 2 s more; at most 60 s),
``disk_full`` (root only: the data directory a 200 MB tmpfs, filled
mid-batch until an item's output or state change has met it, and 2 s more;
at most 60 s, then freed), ``scheduler_lost`` (the Dask
scheduler and worker killed, back after 25 s: longer than the client's
20 s reconnection timeout), ``culprit`` (one item of the batch, the third,
kills its pool worker with SIGKILL each time it runs, as a file that crashes
the decoder or meets the OOM killer would, through the test-only
:func:`testing.faults.process_or_die`; the others must end done, it alone
``failed`` as ``worker_killed``).

Prints one line per fault with the totals over its runs, and exits 1 if any
item was stuck or duplicated, or failed under a fault that must not fail
items (under ``culprit``: if any item but the culprit failed, or it did not).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FAULTS = ("stop", "kill9", "worker_killed", "store_lost", "store_locked", "disk_full", "scheduler_lost",
          "culprit")
#: faults under which exactly one item must fail (the others done): the item that kills its worker
ONE_FAILS = ("culprit",)


def _inputs(folder: str, n: int) -> list[tuple[str, str]]:
    from testing.dngwriter import scene_dng

    os.makedirs(folder, exist_ok=True)
    out = []
    for i in range(n):
        p = os.path.join(folder, f"im{i}.dng")
        if not os.path.exists(p):
            scene_dng(p, "Nikon 5100 (NPL)", "D65", 600, 900, seed=i)
        out.append((f"im{i}.dng", p))
    return out


def _runner(data: str, scheduler: str | None = None):
    from service import jobs

    return jobs.BatchRunner(jobs.RunnerConfig(data, workers=2, poll_s=0.05, dask_scheduler=scheduler,
                                              reconnect_s=2.0))


def _wait_running(store, bid: str, timeout: float = 120.0) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if store.counts(bid)["running"] >= 1 and store.counts(bid)["done"] == 0:
            return
        time.sleep(0.02)
    raise RuntimeError("no item started within the wait")


def _settle(store, bid: str, timeout: float = 180.0) -> None:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        doc = store.progress(bid)
        if doc and doc["settled"]:
            return
        time.sleep(0.2)


def _count(store, bid: str) -> dict:
    from service import jobs

    c = store.counts(bid)
    writes: dict = {}
    with open(os.path.join(store.batch_dir(bid), "writes.log")) if os.path.exists(
            os.path.join(store.batch_dir(bid), "writes.log")) else open(os.devnull) as f:
        for line in f:
            with_name = json.loads(line)["out"]
            writes[with_name] = writes.get(with_name, 0) + 1
    locks = [f for f in os.listdir(os.path.join(store.batch_dir(bid), "out", ".wandell"))
             if f.endswith(".lock")] if os.path.isdir(os.path.join(store.batch_dir(bid), "out", ".wandell")) else []
    del jobs
    requeued = 0
    with open(os.path.join(store.batch_dir(bid), "states.jsonl")) as f:
        for line in f:
            with_requeue = json.loads(line)
            requeued += "requeued" in with_requeue
    return {"done": c["done"], "failed": c["failed"], "stuck": c["pending"] + c["running"],
            "duplicated": sum(v - 1 for v in writes.values() if v > 1), "locks_left": len(locks),
            "requeued": requeued}


def _until(cond, timeout: float) -> bool:
    """Wait until ``cond()`` (True) or ``timeout`` seconds (False)."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.05)
    return False


def _child_runner(data: str) -> None:  # the process killed by the kill9 fault
    r = _runner(data)
    r.start()
    while True:
        time.sleep(3600)


def run_once(fault: str, work: str, srcs: list, dask: dict | None = None) -> dict:
    from service import jobs

    data = os.path.join(work, "data")
    mounted = False
    if fault == "disk_full":
        os.makedirs(data)
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=200m", "tmpfs", data],
                                 capture_output=True).returncode == 0
        if not mounted:
            raise PermissionError("disk_full needs root (mount -t tmpfs)")
    hit = None
    try:
        store = jobs.JobStore(data)
        bid = store.new_batch_id()
        store.create_batch(bid, jobs.batch_options(format="png"), srcs)
        if fault == "kill9":
            child = subprocess.Popen([sys.executable, "-c", "import sys; from benchmarks.batch_faults import "
                                      "_child_runner; _child_runner(sys.argv[1])", data], cwd=ROOT,
                                     start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            _wait_running(store, bid)
            time.sleep(0.3)
            os.killpg(child.pid, signal.SIGKILL)
            child.wait()
            runner = _runner(data)
            runner.start()
        elif fault == "scheduler_lost":
            runner = _runner(data, dask["address"])
            runner.start()
            _wait_running(store, bid)
            dask["kill"]()
            time.sleep(25)
            dask["start"]()
        else:
            runner = _runner(data)
            if fault == "culprit":
                from testing.faults import process_or_die

                runner.item_fn = process_or_die({srcs[min(2, len(srcs) - 1)][0]})
            runner.start()
            _wait_running(store, bid)
            if fault in ("stop", "store_lost"):
                runner.stop(wait=False)
                if fault == "store_lost":
                    for s in ("", "-wal", "-shm"):
                        if os.path.exists(store.path + s):
                            os.unlink(store.path + s)
                runner = _runner(data)
                runner.start()
                store = runner.store
            elif fault == "worker_killed":
                os.kill(next(iter(runner.executor._pool._processes)), signal.SIGKILL)
            elif fault == "store_locked":
                db = sqlite3.connect(store.path, isolation_level=None)
                db.execute("BEGIN IMMEDIATE")
                hit = _until(lambda: runner.records_deferred > 0, 60.0)   # held until an item's end meets it
                time.sleep(2)
                db.execute("ROLLBACK")
                db.close()
            elif fault == "disk_full":
                filler = os.path.join(data, "filler")
                with open(filler, "wb") as f:
                    try:
                        while True:
                            f.write(b"\0" * (1 << 20))
                            f.flush()
                    except OSError:
                        pass
                hit = _until(lambda: runner.records_deferred > 0 or runner.disk_full_retries > 0, 60.0)
                time.sleep(2)
                os.unlink(filler)
        _settle(runner.store, bid)
        got = _count(runner.store, bid)
        got["hit"] = int(hit if hit is not None else got["requeued"] > 0)
        if fault == "culprit":   # the culprit failed as worker_killed, and no other item failed
            bad = [r["name"] for r in runner.store.items(bid) if r["status"] == "failed"]
            killed = [r["name"] for r in runner.store.items(bid) if (r["error"] or "").startswith("worker_killed")]
            got["wrong_failed"] = int(bad != killed or len(killed) != 1)
        runner.stop()
        return got
    finally:
        if mounted:
            subprocess.run(["umount", "-l", data], capture_output=True)


def _dask_cluster(work: str) -> dict:
    dask = os.path.join(os.path.dirname(sys.executable), "dask")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    procs: list = []
    log = open(os.path.join(work, "dask.log"), "a")

    def start():
        procs.append(subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                       "--no-dashboard"], stdout=log, stderr=subprocess.STDOUT,
                                      start_new_session=True))
        time.sleep(3)
        procs.append(subprocess.Popen([dask, "worker", f"tcp://127.0.0.1:{port}", "--nthreads", "1", "--nworkers",
                                       "2", "--host", "127.0.0.1", "--no-dashboard"], cwd=ROOT, stdout=log,
                                      stderr=subprocess.STDOUT, start_new_session=True))
        time.sleep(5)

    def kill():
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
        procs.clear()

    return {"address": f"tcp://127.0.0.1:{port}", "start": start, "kill": kill}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--dask-runs", type=int, default=None, help="runs of scheduler_lost (default --runs)")
    ap.add_argument("--items", type=int, default=6)
    ap.add_argument("--faults", default=",".join(FAULTS))
    args = ap.parse_args(argv)
    faults = [f for f in args.faults.split(",") if f]
    base = tempfile.mkdtemp(prefix="batch-faults-")
    srcs = _inputs(os.path.join(base, "inputs"), args.items)
    bad = False
    try:
        for fault in faults:
            runs = args.dask_runs if fault == "scheduler_lost" and args.dask_runs is not None else args.runs
            total = {"done": 0, "failed": 0, "stuck": 0, "duplicated": 0, "locks_left": 0, "requeued": 0, "hit": 0,
                     "wrong_failed": 0}
            dask = _dask_cluster(base) if fault == "scheduler_lost" else None
            t0 = time.monotonic()
            try:
                if dask:
                    dask["start"]()
                for i in range(runs):
                    work = tempfile.mkdtemp(prefix=f"{fault}-{i}-", dir=base)
                    try:
                        got = run_once(fault, work, srcs, dask)
                    except PermissionError as e:
                        print(f"{fault:15s} skipped: {e}", flush=True)
                        break
                    for k in total:
                        total[k] += got.get(k, 0)
                    shutil.rmtree(work, ignore_errors=True)
                else:
                    n = runs * len(srcs)
                    print(f"{fault:15s} {runs} runs x {len(srcs)} items: done {total['done']}/{n}, failed "
                          f"{total['failed']}, stuck {total['stuck']}, duplicated {total['duplicated']}, lock files "
                          f"left {total['locks_left']}, re-queued {total['requeued']} times, the fault reached items in "
                          f"{total['hit']} of {runs} runs"
                          + (f", runs where another item failed or the culprit did not: {total['wrong_failed']}"
                             if fault in ONE_FAILS else "") + "  "
                          f"({time.monotonic() - t0:.0f} s)", flush=True)
                    bad |= bool(total["stuck"] or total["duplicated"] or total["wrong_failed"]
                                or total["failed"] != (runs if fault in ONE_FAILS else 0))
            finally:
                if dask:
                    dask["kill"]()
    finally:
        shutil.rmtree(base, ignore_errors=True)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
