"""White-balance speed and memory benchmark (issue 3).

``python -m benchmarks.white_balance [--height 4000 --width 6000] [--repeat 3]``

Writes a 24-megapixel DNG with the fixture code (:mod:`testing.dngwriter`),
starts the real service (uvicorn, as the README starts it) on a free
loopback port, and measures side by side in one run:

* rawpy's own default ``postprocess()`` of the file (imread +
  postprocess) in a fresh worker process,
* the full ``POST /v1/white-balance`` request over HTTP (upload, decode,
  estimate, demosaic, correct, encode a 16-bit TIFF, download),
* the estimate alone: ``POST /v1/analyze`` over HTTP, and the estimation
  step inside the server (half-size decode + estimate, from the response's
  ``timings_ms``).

Peak memory is the resident-set high-water mark (``VmHWM``, reset through
``/proc/<pid>/clear_refs``) of the process doing the work, above its
resident size just before the step, against the decoded 16-bit image
(H x W x 3 x 2 bytes).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time


_RAWPY_WORKER = r"""
import sys, time, rawpy
path = sys.argv[1]
with rawpy.imread(path) as raw:   # warm-up: library loaded, file in page cache
    raw.postprocess(half_size=True)
print("ready", flush=True)
for line in sys.stdin:
    t0 = time.perf_counter()
    with rawpy.imread(path) as raw:
        rgb = raw.postprocess()
    del rgb
    print(time.perf_counter() - t0, flush=True)
"""


def bench_arguments(doc: str, argv=None, **extra) -> argparse.Namespace:
    """The options the 24-megapixel benches share (size, repeats, camera, light)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--height", type=int, default=4000)
    ap.add_argument("--width", type=int, default=6000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--camera", default="Nikon 5100 (NPL)")
    ap.add_argument("--illuminant", default="A")
    for name, kw in extra.items():
        ap.add_argument(f"--{name.replace('_', '-')}", **kw)
    return ap.parse_args(argv)


def write_bench_dng(tmp: str, args: argparse.Namespace) -> str:
    """Write the bench's Mondrian DNG (testing.dngwriter) into ``tmp``; print its size."""
    from testing.dngwriter import scene_dng

    path = os.path.join(tmp, "bench.dng")
    t0 = time.perf_counter()
    scene_dng(path, args.camera, args.illuminant, args.height, args.width, seed=1, layout="mondrian",
              surfaces="all", n_surfaces=24)
    print(f"wrote {args.width}x{args.height} DNG ({os.path.getsize(path) / 1e6:.0f} MB) "
          f"in {time.perf_counter() - t0:.1f} s")
    return path


def main(argv=None) -> None:
    args = bench_arguments(__doc__, argv)

    import httpx

    from .load import reset_peak, status_kb, start_server

    with tempfile.TemporaryDirectory() as tmp:
        path = write_bench_dng(tmp, args)
        decoded_mb = args.height * args.width * 3 * 2 / 2**20

        worker = subprocess.Popen([sys.executable, "-c", _RAWPY_WORKER, path], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True)
        server, base = start_server()
        try:
            assert worker.stdout.readline().strip() == "ready"
            client = httpx.Client(timeout=600)

            def post(endpoint, fields):
                with open(path, "rb") as fh:
                    r = client.post(base + endpoint, files={"file": ("bench.dng", fh, "image/x-adobe-dng")},
                                    data=fields)
                assert r.status_code == 200, r.text[:500]
                return r

            def timed(pid, fn):
                times, peaks, extra = [], [], []
                for _ in range(args.repeat):
                    before = status_kb(pid, "VmRSS")
                    reset_peak(pid)
                    t0 = time.perf_counter()
                    out = fn()
                    times.append(time.perf_counter() - t0)
                    peaks.append((status_kb(pid, "VmHWM") - before) / 1024)
                    extra.append(out)
                return statistics.median(times), max(peaks), extra

            def rawpy_once():
                worker.stdin.write("go\n")
                worker.stdin.flush()
                return float(worker.stdout.readline())

            post("/v1/white-balance", {"format": "tiff"})  # warm-up: imports, data, caches
            t_raw, m_raw, _ = timed(worker.pid, rawpy_once)
            t_wb, m_wb, wb_resp = timed(server.pid, lambda: post("/v1/white-balance", {"format": "tiff"}))
            t_an, m_an, an_resp = timed(server.pid, lambda: post("/v1/analyze", {}))
            inner = [r.json()["timings_ms"] for r in an_resp]
            t_est = statistics.median((t["decode"] + t["estimate"]) / 1e3 for t in inner)
            wb_t = json.loads(wb_resp[-1].headers["X-Illuminant"])["timings_ms"]
            assert len(wb_resp[-1].content) > decoded_mb * 2**20
        finally:
            server.terminate()
            worker.kill()
            server.wait()

    rows = [("rawpy postprocess() default", t_raw, m_raw),
            ("POST /v1/white-balance (16-bit TIFF)", t_wb, m_wb),
            ("POST /v1/analyze over HTTP", t_an, m_an),
            ("estimation in the server (decode+estimate)", t_est, float("nan"))]
    print(f"\n{'step':44s} {'median s':>9s} {'x rawpy':>8s} {'peak MB':>8s} {'x image':>8s}")
    for name, t, mem in rows:
        print(f"{name:44s} {t:9.2f} {t / t_raw:8.2f} {mem:8.0f} {mem / decoded_mb:8.2f}")
    print(f"\ndecoded 16-bit image: {decoded_mb:.0f} MB; targets: white-balance <= 1.20 x rawpy, "
          "estimate <= 0.10 x rawpy, peak <= 3.00 x image")
    print("white-balance server timings (ms):", {k: round(v) for k, v in wb_t.items()})


if __name__ == "__main__":
    main()
