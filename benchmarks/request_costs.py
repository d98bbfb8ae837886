"""What one request costs, per input kind and endpoint: the figures of
``docs/limits.md``.

Memory: ``python -m service`` started as users start it (a fresh data dir and
TMPDIR), one warm-up request, then for each case the server's peak RSS rise
(``VmHWM`` after resetting it through ``/proc/PID/clear_refs``, and RSS
sampled every 50 ms) while the request runs, divided by the megapixels.
Each case runs on a server of its own, so one case's freed-but-kept memory
does not hide the next one's.

Time: the literal light map (``method=maloney-wandell``, ``spatial=true``)
estimated in-process on random 16-bit images whose default regions number
about 1,000 to 25,000 (``max_regions`` lifted): seconds per 1,000 regions.

Memory after many requests (``--arenas``): the server's anonymous memory
(``RssAnon``) once N requests of a 10 MP uncompressed linear 16-bit TIFF to
``/v1/white-balance`` have been answered, made one after another and sent all
at once (served through ``WANDELL_MAX_CONCURRENT_WORK`` slots), with glibc's
default malloc arenas (``MALLOC_ARENA_MAX`` set to glibc's own default, 8 per
CPU) and with the service's cap (``service.workers.MALLOC_ARENAS``), side by
side; each figure on a fresh server, the median of ``--repeat`` runs.

Usage (from the checkout root)::

    .venv/bin/python -m benchmarks.request_costs [--port 8660] [--mp 10] [--skip-memory] [--skip-map]
        [--only TEXT] [--endpoint PATH] [--wb-format tiff|png|png16|jpeg]
    .venv/bin/python -m benchmarks.request_costs --arenas [--requests 16] [--slots 1,2] [--repeat 3]

``--only`` keeps the input kinds whose name contains TEXT (e.g. ``LinearRaw``),
``--endpoint`` one endpoint (e.g. ``/v1/white-balance``), ``--wb-format`` the
white balance's output format (default tiff).

Linux only (``/proc``). Prints one line per case.
"""

from __future__ import annotations

import argparse
import http.client
import io
import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _status(pid: int, key: str) -> int | None:
    try:
        for line in open(f"/proc/{pid}/status"):
            if line.startswith(key + ":"):
                return int(line.split()[1]) // 1024
    except OSError:
        return None
    return None


def _multipart(fields: dict, name: str, data: bytes):
    b = "----bench" + uuid.uuid4().hex
    out = []
    for k, v in fields.items():
        out += [f"--{b}", f'Content-Disposition: form-data; name="{k}"', "", v]
    head = "\r\n".join(out + [f"--{b}", f'Content-Disposition: form-data; name="file"; filename="{name}"',
                              "Content-Type: application/octet-stream", "", ""]).encode()
    return head + data + f"\r\n--{b}--\r\n".encode(), f"multipart/form-data; boundary={b}"


def _post(port, path, fields, name, data, timeout=600):
    body, ctype = _multipart(fields, name, data)
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=timeout)
    try:
        c.request("POST", path, body=body, headers={"Content-Type": ctype})
        r = c.getresponse()
        got = r.read()
        return r.status, got
    finally:
        c.close()


class _Server:
    def __init__(self, port: int, env: dict | None = None):
        self.port = port
        self.work = tempfile.mkdtemp(prefix="wandell-bench-")
        env = dict(os.environ, WANDELL_HOST="127.0.0.1", WANDELL_PORT=str(port),
                   WANDELL_DATA_DIR=os.path.join(self.work, "data"), TMPDIR=self.work, **(env or {}))
        self.p = subprocess.Popen([sys.executable, "-m", "service"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                                  stderr=subprocess.DEVNULL, start_new_session=True)
        t0 = time.time()
        while time.time() - t0 < 120:
            try:
                c = http.client.HTTPConnection("127.0.0.1", port, timeout=5)
                c.request("GET", "/health")
                if c.getresponse().status == 200:
                    return
            except OSError:
                time.sleep(0.3)
        raise RuntimeError("the server did not start")

    def stop(self):
        os.killpg(self.p.pid, signal.SIGTERM)
        try:
            self.p.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(self.p.pid, signal.SIGKILL)
            self.p.wait()
        shutil.rmtree(self.work, ignore_errors=True)

    def peak_rise(self, fn):
        pid = self.p.pid
        base = _status(pid, "VmRSS")
        peak = [base]
        with open(f"/proc/{pid}/clear_refs", "w") as f:
            f.write("5")
        stop = threading.Event()

        def sample():
            while not stop.is_set():
                peak[0] = max(peak[0], _status(pid, "VmRSS") or 0)
                time.sleep(0.05)
        t = threading.Thread(target=sample, daemon=True)
        t.start()
        try:
            res = fn()
        finally:
            stop.set()
            t.join()
        peak[0] = max(peak[0], _status(pid, "VmHWM") or 0)
        return res, peak[0] - base


def _linear_tiff(mp: float, compress: bool = True) -> tuple[bytes, float]:
    import tifffile

    h = int(round((mp * 1e6 * 3 / 4) ** 0.5))
    w = int(round(mp * 1e6 / h))
    rng = np.random.default_rng(0)
    blocks = rng.integers(2000, 40000, (h // 64 + 1, w // 64 + 1, 3)).astype(np.uint16)
    img = np.kron(blocks, np.ones((64, 64, 1), np.uint16))[:h, :w]
    buf = io.BytesIO()
    if compress:
        tifffile.imwrite(buf, img, photometric="rgb", compression="zlib", predictor=True)
    else:
        tifffile.imwrite(buf, img, photometric="rgb")
    return buf.getvalue(), h * w / 1e6


def _linear_dng(mp: float, float_samples: bool, compression: str = "zlib") -> tuple[bytes, float]:
    import tifffile

    h = int(round((mp * 1e6 * 3 / 4) ** 0.5))
    w = int(round(mp * 1e6 / h))
    ramp = np.linspace(0.05, 0.6, w, dtype=np.float32)[None, :, None] * np.array([0.8, 1.0, 0.6], np.float32)
    img = np.broadcast_to(ramp, (h, w, 3))
    img = np.ascontiguousarray(img if float_samples else (img * 65535).astype(np.uint16))

    def rat(vals):
        return [v for x in np.ravel(vals) for v in (int(round(x * 10000)), 10000)]
    cm = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    tags = [(271, "s", 0, "Acme", True), (272, "s", 0, "LinCam", True), (50706, "B", 4, (1, 4, 0, 0), True),
            (50707, "B", 4, (1, 1, 0, 0), True), (50708, "s", 0, "Acme LinCam", True),
            (50721, "2i", 9, rat(cm), True), (50778, "H", 1, 21, True), (50728, "2I", 3, rat((0.5, 1, 0.6)), True),
            (50713, "H", 2, (1, 1), True), (50714, "I", 1, 0, True),
            (50717, "I", 1, 1 if float_samples else 65535, True)]
    buf = io.BytesIO()
    tifffile.imwrite(buf, img, photometric=34892, subfiletype=0, compression=compression, tile=(256, 256),
                     planarconfig="contig", metadata=None, extratags=tags)
    return buf.getvalue(), h * w / 1e6


def _cfa_dng(mp: float) -> tuple[bytes, float]:
    from testing.dngwriter import mosaic, write_dng

    h = int(round((mp * 1e6 * 3 / 4) ** 0.5)) // 2 * 2
    w = int(round(mp * 1e6 / h)) // 2 * 2
    rng = np.random.default_rng(1)
    blocks = rng.uniform(0.05, 0.6, (h // 64 + 1, w // 64 + 1, 3))
    rgb = np.kron(blocks, np.ones((64, 64, 1)))[:h, :w]
    buf = io.BytesIO()
    write_dng(buf, (mosaic(rgb) * 60000).astype(np.uint16), white_level=65535, as_shot_neutral=(0.5, 1.0, 0.6))
    return buf.getvalue(), h * w / 1e6


def memory(port: int, mp: float, only: str | None = None, endpoint: str | None = None,
           wb_format: str = "tiff") -> None:
    kinds = {"linear 16-bit TIFF (deflate)": ("a.tif", lambda: _linear_tiff(mp)),
             "CFA DNG (16-bit Bayer)": ("a.dng", lambda: _cfa_dng(mp)),
             "LinearRaw DNG, 16-bit, deflate tiles": ("a.dng", lambda: _linear_dng(mp, False)),
             "LinearRaw DNG, float32, deflate tiles": ("a.dng", lambda: _linear_dng(mp, True)),
             "LinearRaw DNG, 16-bit, deflate-32946 tiles": ("a.dng", lambda: _linear_dng(mp, False, "deflate"))}
    endpoints = (("/v1/analyze", {}), ("/v1/white-balance", {"format": wb_format}), ("/v1/surfaces", {"grid": "4x4"}))
    kinds = {k: v for k, v in kinds.items() if only is None or only.lower() in k.lower()}
    endpoints = tuple(e for e in endpoints if endpoint is None or e[0] == endpoint)
    warm = _cfa_dng(0.05)[0]
    for kind, (name, make) in kinds.items():
        data, mpx = make()
        for path, fields in endpoints:
            srv = _Server(port)
            try:
                _post(port, "/v1/analyze", {"method": "gray-world"}, "warm.dng", warm)
                t0 = time.perf_counter()
                (st, body), rise = srv.peak_rise(lambda: _post(port, path, fields, name, data))
                took = time.perf_counter() - t0
            finally:
                srv.stop()
            what = "" if st == 200 else f" ({json.loads(body).get('error') if body[:1] == b'{' else body[:60]})"
            where = f"{path} {fields['format']}" if "format" in fields else path
            print(f"{kind:40s} {where:23s} {mpx:5.1f} MP ({len(data) / 1e6:6.1f} MB): HTTP {st}{what}, "
                  f"RSS +{rise:5d} MiB = {rise / mpx:5.1f} MiB/MP, {took:5.1f} s", flush=True)


def glibc_default_arenas() -> int:
    """glibc's own arena limit (8 per CPU on 64-bit): as ``MALLOC_ARENA_MAX`` it gives a
    server glibc's default behaviour, which the service's cap (``service.workers``) then leaves alone."""
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    return 8 * max(1, cpus)


def anon_after_requests(port: int, data: bytes, n: int, slots: int, env: dict, at_once: bool) -> dict:
    """On a fresh server (``WANDELL_MAX_CONCURRENT_WORK=slots`` and ``env``): its ``RssAnon`` (MiB)
    at start, after the first request and after ``n`` requests to ``/v1/white-balance`` (TIFF),
    made one after another (``at_once`` false; also the median seconds a request took) or all sent
    at once; ``statuses`` the answers' HTTP statuses."""
    import concurrent.futures

    srv = _Server(port, dict(env, WANDELL_MAX_CONCURRENT_WORK=str(slots)))
    pid = srv.p.pid
    out = {"start": _status(pid, "RssAnon"), "statuses": set()}
    try:
        def one():
            t0 = time.perf_counter()
            st, _ = _post(port, "/v1/white-balance", {"format": "tiff"}, "a.tif", data)
            out["statuses"].add(st)
            return time.perf_counter() - t0
        if at_once:
            with concurrent.futures.ThreadPoolExecutor(n) as ex:
                list(ex.map(lambda _: one(), range(n)))
        else:
            took = []
            for i in range(n):
                took.append(one())
                if i == 0:
                    time.sleep(0.2)
                    out["first"] = _status(pid, "RssAnon")
            out["seconds"] = float(np.median(took))
        time.sleep(0.5)
        out["after"] = _status(pid, "RssAnon")
        out["peak"] = _status(pid, "VmHWM")
    finally:
        srv.stop()
    return out


def arenas(port: int, mp: float, n: int, slots: list[int], repeat: int) -> None:
    """Print the ``--arenas`` table: RssAnon after ``n`` requests, glibc's default arenas
    against the service's cap, medians of ``repeat`` fresh servers per figure."""
    from service.workers import MALLOC_ARENAS

    data, mpx = _linear_tiff(mp, compress=False)
    default = {"MALLOC_ARENA_MAX": str(glibc_default_arenas())}
    print(f"{mpx:.1f} MP uncompressed 16-bit TIFF ({len(data) / 1e6:.0f} MB) to /v1/white-balance (TIFF); "
          f"RssAnon in MiB, medians of {repeat} fresh servers; glibc default = MALLOC_ARENA_MAX="
          f"{default['MALLOC_ARENA_MAX']} (8 per CPU), capped = the service's {MALLOC_ARENAS}", flush=True)
    for k in slots:
        for at_once in (False, True):
            how = f"{n} sent at once" if at_once else f"{n} one after another"
            figs = {"glibc default": [], "capped": []}
            for _ in range(repeat):       # the two in turn, so a drift of the shared machine falls on both
                for name, env in (("glibc default", default), ("capped", {})):
                    figs[name].append(anon_after_requests(port, data, n, k, env, at_once))
            for name, runs in figs.items():
                after = np.median([r["after"] for r in runs])
                first = np.median([r["first"] for r in runs]) if not at_once else None
                start = np.median([r["start"] for r in runs])
                sts = set().union(*(r["statuses"] for r in runs))
                extra = (f", after the 1st {first:4.0f} (+{after - first:4.0f} since), {np.median([r['seconds'] for r in runs]):.2f} s a request"
                         if first is not None else "")
                print(f"slots {k}, {how:20s} {name:13s}: start {start:4.0f}, after all {after:4.0f} "
                      f"(each run {', '.join(str(r['after']) for r in runs)}){extra}, peak RSS "
                      f"{np.median([r['peak'] for r in runs]):4.0f}; HTTP {sorted(sts)}", flush=True)


def light_map() -> None:
    from recovery import estimate_illuminant
    from recovery.cameras import generic_camera
    from recovery.regions import region_count

    cam = generic_camera()
    rng = np.random.default_rng(1)
    for h, w in ((2000, 64), (4000, 64), (10000, 64), (25000, 32)):
        img = rng.integers(1000, 50000, (h, w, 3)).astype(np.float64) / 65535
        size = max(8, min(h, w) // 4)
        n = region_count((h, w), size, 0.5)
        t0 = time.perf_counter()
        est = estimate_illuminant(img, cam, "maloney-wandell", spatial=True, max_regions=None)
        took = time.perf_counter() - t0
        print(f"light map {h}x{w}, region side {size}: {n:6d} regions "
              f"({est.diagnostics.get('regions_used')} used, {est.diagnostics.get('overlap_equations')} overlap "
              f"equations): {took:5.1f} s = {1000 * took / n:.2f} s per 1,000 regions", flush=True)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", type=int, default=8660)
    ap.add_argument("--mp", type=float, default=10.0, help="megapixels of the memory cases (default 10)")
    ap.add_argument("--skip-memory", action="store_true")
    ap.add_argument("--skip-map", action="store_true")
    ap.add_argument("--only", help="only the input kinds whose name contains this (e.g. LinearRaw)")
    ap.add_argument("--endpoint", help="only this endpoint (e.g. /v1/white-balance)")
    ap.add_argument("--wb-format", default="tiff", help="/v1/white-balance's format (default tiff)")
    ap.add_argument("--arenas", action="store_true",
                    help="only the memory after many requests, glibc's default malloc arenas against the cap")
    ap.add_argument("--requests", type=int, default=16, help="--arenas: requests per server (default 16)")
    ap.add_argument("--slots", default="1,2", help="--arenas: WANDELL_MAX_CONCURRENT_WORK values (default 1,2)")
    ap.add_argument("--repeat", type=int, default=3, help="--arenas: fresh servers per figure (default 3)")
    a = ap.parse_args(argv)
    if a.arenas:
        arenas(a.port, a.mp, a.requests, [int(x) for x in a.slots.split(",")], a.repeat)
        return
    if not a.skip_map:
        light_map()
    if not a.skip_memory:
        memory(a.port, a.mp, a.only, a.endpoint, a.wb_format)


if __name__ == "__main__":
    main()
