"""Batch throughput benchmark (issue 6).

``python -m benchmarks.batch [--files 6] [--height 4000 --width 6000]
[--format tiff] [--rounds 2] [--no-dask]``

Writes ``--files`` 24-megapixel DNGs once (:func:`testing.dngwriter.scene_dng`,
Mondrian scenes under different lights) into a temporary folder, then in the
same run corrects all of them with the batch item function
(:func:`service.jobs.process_item`: decode, estimate, demosaic, one 3x3
matrix per pixel, encode, atomic write) on

* a local process pool of 1 worker,
* a local process pool of 2 workers,
* a Dask ``LocalCluster`` of 2 worker processes (1 thread each),

and prints images per minute for each and the 2-vs-1 ratio (target >= 1.7).
Every worker runs with its numerical libraries capped at one thread
(:func:`service.jobs.limit_threads`), so two workers use two cores without
fighting. Each pool is warmed up first (imports, colour data) on a small
DNG, so the figures are steady-state throughput.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import tempfile
import time

from service import jobs

LIGHTS = ("A", "D65", "D50", "FL2", "D75", "FL11", "D55", "LED-B3")


def _tasks(src_dir: str, out_dir: str, names: list[str], options) -> list:
    os.makedirs(out_dir, exist_ok=True)
    return [jobs.ItemTask(src=os.path.join(src_dir, n), out=os.path.join(out_dir, os.path.splitext(n)[0] + "."
                                                                           + options.extension),
                          name=n, options=options, max_pixels=200_000_000, estimation_pixels=1_000_000)
            for n in names]


def _run(executor, tasks) -> tuple[float, list]:
    t0 = time.perf_counter()
    futs = [executor.submit(jobs.process_item, t) for t in tasks]
    res = [f.result() for f in futs]
    return time.perf_counter() - t0, res


def _warm(executor, warm_tasks) -> None:
    res = [f.result() for f in [executor.submit(jobs.process_item, t) for t in warm_tasks]]
    bad = [r for r in res if r["status"] != "done"]
    if bad:
        raise SystemExit(f"warm-up failed: {bad[0]}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=6)
    ap.add_argument("--height", type=int, default=4000)
    ap.add_argument("--width", type=int, default=6000)
    ap.add_argument("--format", default="tiff")
    ap.add_argument("--no-dask", action="store_true")
    ap.add_argument("--rounds", type=int, default=2, help="alternating rounds; the best of each is reported")
    ap.add_argument("--dir", help="keep the DNGs here (reused when present)")
    args = ap.parse_args(argv)

    from testing.dngwriter import scene_dng

    options = jobs.batch_options(format=args.format)
    tmp = tempfile.mkdtemp(prefix="wandell-batch-bench-")
    src = args.dir or os.path.join(tmp, "dng")
    os.makedirs(src, exist_ok=True)
    for k in jobs.THREAD_ENV:  # spawned pool and Dask workers inherit these
        os.environ[k] = "1"
    try:
        names = [f"scene{i:02d}.dng" for i in range(args.files)]
        t0 = time.perf_counter()
        for i, n in enumerate(names):
            p = os.path.join(src, n)
            if not os.path.exists(p):
                scene_dng(p, "Nikon 5100 (NPL)", LIGHTS[i % len(LIGHTS)], args.height, args.width, seed=i,
                          layout="mondrian", surfaces="all", n_surfaces=24)
        scene_dng(os.path.join(src, "warm.dng.small"), "Nikon 5100 (NPL)", "D65", 256, 384, seed=99)
        mp = args.height * args.width / 1e6
        print(f"{args.files} DNGs of {args.width}x{args.height} ({mp:.0f} MP, "
              f"{os.path.getsize(os.path.join(src, names[0])) / 1e6:.0f} MB each) ready in "
              f"{time.perf_counter() - t0:.0f} s; output {args.format}")

        def warm_tasks(k, tag):
            return [jobs.ItemTask(src=os.path.join(src, "warm.dng.small"),
                                  out=os.path.join(tmp, f"warm-{tag}-{j}.png"), name="warm",
                                  options=jobs.batch_options(format="png"), max_pixels=10**8,
                                  estimation_pixels=10**6, exactly_once=False) for j in range(k)]

        executors, stack = {}, contextlib.ExitStack()
        with stack:
            for workers in (1, 2):
                ex = jobs.LocalExecutor(workers)
                stack.callback(ex.shutdown)
                _warm(ex, warm_tasks(2 * workers, f"l{workers}"))
                executors[f"local pool, {workers} worker{'s' if workers > 1 else ''}"] = ex
            if not args.no_dask:
                import dask
                from distributed import Client, LocalCluster

                # Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 in its
                # workers, which turns off glibc's dynamic mmap threshold:
                # every large buffer is then a fresh mmap whose page faults
                # cost about 0.6 s of CPU per 24 MP image (measured). The
                # workers here run without it (see README).
                stack.enter_context(dask.config.set(
                    {"distributed.nanny.pre-spawn-environ": {"MALLOC_TRIM_THRESHOLD_": None}}))
                cl = stack.enter_context(LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                                      dashboard_address=None))
                client = stack.enter_context(Client(cl))
                client.run(jobs.limit_threads)
                ex = jobs.DaskExecutor(client=client)
                _warm(ex, warm_tasks(4, "dask"))
                executors["Dask LocalCluster, 2 workers"] = ex
            # rounds alternate between the executors so that a burst of other
            # load on the machine does not land on one of them only
            rows = {name: [] for name in executors}
            for rnd in range(args.rounds):
                for name, ex in executors.items():
                    out = os.path.join(tmp, f"out-{rnd}-{list(executors).index(name)}")
                    el, res = _run(ex, _tasks(src, out, names, options))
                    shutil.rmtree(out, ignore_errors=True)
                    rows[name].append((el, res))
                    print(f"round {rnd + 1}: {name:30s} {len(res) / el * 60:7.2f} images/min", flush=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)

    print(f"\nbest of {args.rounds} rounds")
    print(f"{'executor':32s} {'images':>6s} {'failed':>6s} {'seconds':>8s} {'images/min':>10s} "
          f"{'s/image in worker':>17s} {'CPU s/image':>11s}")
    rate = {}
    for name, runs in rows.items():
        el, res = min(runs, key=lambda r: r[0])
        failed = sum(r["status"] != "done" for r in res)
        per = sum(r.get("seconds", 0) for r in res) / max(1, len(res))
        cpu = sum(r.get("cpu_seconds", 0) for r in res) / max(1, len(res))
        rate[name] = len(res) / el * 60
        print(f"{name:32s} {len(res):6d} {failed:6d} {el:8.1f} {rate[name]:10.2f} {per:17.2f} {cpu:11.2f}")
        if failed:
            print("  first failure:", next(r["error"] for r in res if r["status"] != "done"))
    r1, r2 = rate["local pool, 1 worker"], rate["local pool, 2 workers"]
    print(f"\n2 workers / 1 worker = {r2 / r1:.2f} (target >= 1.7)")
    if "Dask LocalCluster, 2 workers" in rate:
        print(f"Dask 2 workers / local 1 worker = {rate['Dask LocalCluster, 2 workers'] / r1:.2f}")
    print(f"cores available: {jobs.default_workers()}; load average now {os.getloadavg()[0]:.1f} "
          "(other processes on the machine make these figures noisy)")


if __name__ == "__main__":
    main()
