"""White-balance speed and memory benchmark (issue 3).

``python -m service.bench [--height 4000 --width 6000] [--repeat 3]``

Writes a 24-megapixel DNG with the fixture code (:mod:`service.dngwriter`),
then measures, side by side in one run:

* rawpy's own default ``postprocess()`` of the file (imread + postprocess),
* the full ``POST /v1/white-balance`` request through the real FastAPI app
  and its ASGI stack (decode, estimate, correct, encode 16-bit TIFF),
* the estimate alone (``POST /v1/analyze``),

and prints the ratios. Peak memory is the resident-set high-water mark
(``VmHWM``, reset through ``/proc/self/clear_refs``) above the process's
resident size just before the step, against the size of the decoded 16-bit
image (H x W x 3 x 2 bytes).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time


def _rss_kb(field: str) -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    return 0


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def measure(fn, repeat: int):
    """Median wall time (s) and peak extra resident memory (MB) of ``fn``."""
    times, peaks = [], []
    for _ in range(repeat):
        import gc

        gc.collect()
        base = _rss_kb("VmRSS")
        _reset_peak()
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        peaks.append((_rss_kb("VmHWM") - base) / 1024)
    return statistics.median(times), max(peaks)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--height", type=int, default=4000)
    ap.add_argument("--width", type=int, default=6000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--camera", default="Nikon 5100 (NPL)")
    ap.add_argument("--illuminant", default="A")
    args = ap.parse_args(argv)

    import rawpy
    from fastapi.testclient import TestClient

    from service.app import app
    from service.dngwriter import scene_dng

    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "bench.dng")
        t0 = time.perf_counter()
        scene_dng(path, args.camera, args.illuminant, args.height, args.width, seed=1, layout="mondrian",
                  surfaces="all", n_surfaces=24)
        print(f"wrote {args.width}x{args.height} DNG ({os.path.getsize(path) / 1e6:.0f} MB) "
              f"in {time.perf_counter() - t0:.1f} s")
        data = open(path, "rb").read()
        decoded_mb = args.height * args.width * 3 * 2 / 2**20

        def rawpy_default():
            with rawpy.imread(path) as raw:
                raw.postprocess()

        client = TestClient(app)
        files = {"file": ("bench.dng", data, "application/octet-stream")}

        def white_balance():
            r = client.post("/v1/white-balance", files=files, data={"format": "tiff"})
            assert r.status_code == 200, r.text
            return r

        def analyze():
            r = client.post("/v1/analyze", files=files)
            assert r.status_code == 200, r.text

        white_balance()  # warm-up: imports, colour-science data, caches
        rows = [("rawpy postprocess() default", *measure(rawpy_default, args.repeat)),
                ("POST /v1/white-balance (16-bit TIFF)", *measure(white_balance, args.repeat)),
                ("POST /v1/analyze (estimate only)", *measure(analyze, args.repeat))]
        base_t = rows[0][1]
        print(f"\n{'step':40s} {'median s':>9s} {'x rawpy':>8s} {'peak MB':>8s} {'x image':>8s}")
        for name, t, mem in rows:
            print(f"{name:40s} {t:9.2f} {t / base_t:8.2f} {mem:8.0f} {mem / decoded_mb:8.2f}")
        print(f"\ndecoded 16-bit image: {decoded_mb:.0f} MB; targets: white-balance <= 1.20 x rawpy, "
              f"estimate <= 0.10 x rawpy, peak <= 3.00 x image")
        r = white_balance()
        print("last request timings (ms):", r.headers.get("X-Illuminant", "")[:0] or
              __import__("json").loads(r.headers["X-Illuminant"])["timings_ms"])


if __name__ == "__main__":
    main()
