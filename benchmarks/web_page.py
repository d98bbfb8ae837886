"""What the web page waits for after an upload (issue 6), on a large DNG.

``python -m benchmarks.web_page [--height 4000 --width 6000] [--repeat 3]``

Writes a DNG with the fixture code (:mod:`testing.dngwriter`), starts the
real service (uvicorn) on a free loopback port and times, over HTTP, each
request the page makes for one file and the three together as the page sends
them (concurrently: the time until the result is shown), next to
``POST /v1/white-balance`` as JPEG, which is what showing the full-resolution
correction instead of a preview would cost. Prints the median time and the
bytes each response carries. Figures are wall-clock on a shared machine: run
it on a quiet one for numbers to quote.
"""

from __future__ import annotations

import os
import statistics
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor

from .white_balance import bench_arguments, write_bench_dng
from .load import start_server


def main(argv=None) -> None:
    args = bench_arguments(__doc__, argv)

    import httpx

    with tempfile.TemporaryDirectory() as tmp:
        path = write_bench_dng(tmp, args)
        with open(path, "rb") as fh:
            data = fh.read()
        server, base = start_server()
        try:
            client = httpx.Client(timeout=600)

            def post(endpoint, fields):
                r = client.post(base + endpoint, files={"file": ("bench.dng", data, "image/x-adobe-dng")},
                                data=fields)
                assert r.status_code == 200, r.text[:500]
                return len(r.content)

            requests = {
                "POST /v1/preview wb=camera (jpeg, 1024)": ("/v1/preview", {"wb": "camera"}),
                "POST /v1/preview wb=corrected (jpeg, 1024)": ("/v1/preview", {"wb": "corrected"}),
                "POST /v1/analyze": ("/v1/analyze", {}),
                "POST /v1/white-balance jpeg (full size)": ("/v1/white-balance", {"format": "jpeg"}),
            }
            page = list(requests.values())[:3]

            def page_round():
                with ThreadPoolExecutor(3) as pool:
                    return sum(pool.map(lambda a: post(*a), page))

            for args_ in requests.values():   # warm-up: imports, models, caches
                post(*args_)
            rows = []
            for name, (endpoint, fields) in requests.items():
                times, size = [], 0
                for _ in range(args.repeat):
                    t = time.perf_counter()
                    size = post(endpoint, fields)
                    times.append(time.perf_counter() - t)
                rows.append((name, statistics.median(times), size))
            times = []
            for _ in range(args.repeat):
                t = time.perf_counter()
                size = page_round()
                times.append(time.perf_counter() - t)
            rows.append(("the page's three requests, concurrent", statistics.median(times), size))
        finally:
            server.terminate()
            server.wait()

    print(f"\n{'request':46s} {'median s':>9s} {'response kB':>12s}")
    for name, t, size in rows:
        print(f"{name:46s} {t:9.2f} {size / 1e3:12.0f}")
    print(f"\n{args.width}x{args.height}, {args.repeat} repeats, {os.cpu_count()} CPUs; wall-clock on this "
          "machine (noisy if it is shared)")


if __name__ == "__main__":
    main()
