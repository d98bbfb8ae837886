"""Concurrent white-balance load on a real server over loopback (issue 6).

``python -m benchmarks.load [--n 50] [--height 512 --width 768] [--url URL [--pid PID]]``

Writes ``n`` DNGs with :mod:`testing.dngwriter`, one per light (different
CIE, fluorescent, LED and high-pressure lights, so that every file has its
own true light), starts the service with uvicorn on a free loopback port
(or targets ``--url``, e.g. a server started by hand), and:

1. sends each file once, one at a time, with ``response=json``: the
   *reference* estimate of each file (and the warm-up of imports, colour
   data and caches);
2. sends all ``n`` ``POST /v1/white-balance`` requests at once (httpx
   async, one connection each) for the corrected 16-bit TIFF, and reports
   throughput (requests/s over the burst), latency p50/p90/p99/max and the
   server's peak resident memory (``VmHWM`` of its process, reset through
   ``/proc/<pid>/clear_refs`` before the burst; ``--pid`` with ``--url``);
3. checks that nothing failed and nothing leaked between requests: every
   answer is a 200; its ``X-Illuminant`` estimate equals that file's own
   reference estimate (relative 1e-6: the same deterministic computation
   on the same bytes, only the interleaving of requests differs) and lies
   within ``--max-angle`` degrees of the file's true light; the body decodes
   to an ``H x W x 3`` 16-bit image of that file's size.

Exit status 0 only if every check passed. Only loopback addresses are
accepted for ``--url``.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass, field
from urllib.parse import urlparse

import numpy as np

from recovery import angular_error

__all__ = ["LoadReport", "make_inputs", "run_load", "status_kb", "reset_peak", "main"]

#: Lights left out: under HP1 (low-pressure-sodium-like, nearly
#: monochromatic) the estimate is off by 17 degrees on these scenes,
#: measured; the load test checks plumbing, not that hard case.
EXCLUDED_LIGHTS = ("HP1",)


@dataclass
class LoadReport:
    """What one load run measured and what went wrong."""

    n: int = 0
    ok: int = 0
    wall_s: float = 0.0
    latencies_s: list = field(default_factory=list)
    peak_rss_mb: float | None = None
    rss_before_mb: float | None = None
    angles_deg: list = field(default_factory=list)
    failures: list = field(default_factory=list)
    image_mb: float = 0.0

    @property
    def throughput(self) -> float:
        return self.n / self.wall_s if self.wall_s > 0 else 0.0

    def percentile_ms(self, q: float) -> float:
        return 1e3 * float(np.percentile(self.latencies_s, q)) if self.latencies_s else float("nan")

    def summary(self) -> str:
        lat = self.latencies_s or [float("nan")]
        lines = [
            f"{self.n} concurrent POST /v1/white-balance, {self.ok} ok, {len(self.failures)} failed; "
            f"burst {self.wall_s:.2f} s -> {self.throughput:.2f} requests/s",
            f"latency ms: p50 {self.percentile_ms(50):.0f}, p90 {self.percentile_ms(90):.0f}, "
            f"p99 {self.percentile_ms(99):.0f}, max {1e3 * max(lat):.0f}",
        ]
        if self.peak_rss_mb is not None:
            lines.append(f"server RSS before the burst {self.rss_before_mb:.0f} MB, peak during it "
                         f"{self.peak_rss_mb:.0f} MB (decoded 16-bit image {self.image_mb:.1f} MB each)")
        if self.angles_deg:
            a = np.asarray(self.angles_deg)
            lines.append(f"estimate vs each file's true light: median {np.median(a):.2f} deg, max {a.max():.2f} deg")
        lines.extend(f"FAIL {f}" for f in self.failures[:20])
        return "\n".join(lines)


@dataclass
class _Input:
    name: str
    light: str
    data: bytes
    light_rgb: np.ndarray
    height: int
    width: int


def make_inputs(n: int, height: int, width: int, camera: str = "Nikon 5100 (NPL)") -> list[_Input]:
    """``n`` DNGs of a ColorChecker scene, each under a different light
    (:func:`models.illuminant_names` in order, without
    :data:`EXCLUDED_LIGHTS`, cycling when ``n`` is larger)."""
    import models

    from testing.dngwriter import scene_dng

    lights = [x for x in models.illuminant_names() if x not in EXCLUDED_LIGHTS]
    out = []
    for i in range(n):
        light = lights[i % len(lights)]
        buf = io.BytesIO()
        t = scene_dng(buf, camera, light, height, width, seed=100 + i)
        out.append(_Input(f"load-{i:03d}.dng", light, buf.getvalue(), np.asarray(t.light_rgb, float), height, width))
    return out


def status_kb(pid: int, name: str) -> int:
    """A ``/proc/PID/status`` figure in kB (``VmRSS``, ``VmHWM``), 0 if absent."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(name + ":"):
                return int(line.split()[1])
    return 0


def reset_peak(pid: int) -> bool:
    """Reset the process's peak RSS (``VmHWM``); False where not allowed."""
    try:
        with open(f"/proc/{pid}/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


async def _burst(base: str, inputs, timeout: float, fields: dict):
    import httpx

    limits = httpx.Limits(max_connections=len(inputs), max_keepalive_connections=len(inputs))
    async with httpx.AsyncClient(base_url=base, timeout=timeout, limits=limits) as client:
        async def one(inp):
            t0 = time.perf_counter()
            try:
                r = await client.post("/v1/white-balance", data=fields,
                                      files={"file": (inp.name, inp.data, "image/x-adobe-dng")})
            except Exception as e:  # timeout, connection refused or reset
                return inp, None, time.perf_counter() - t0, f"{type(e).__name__}: {e}"
            return inp, r, time.perf_counter() - t0, None

        t0 = time.perf_counter()
        results = await asyncio.gather(*(one(inp) for inp in inputs))
        return results, time.perf_counter() - t0


def _check_image(inp: _Input, r) -> str | None:
    import tifffile

    try:
        img = tifffile.imread(io.BytesIO(r.content))
    except Exception as e:
        return f"{inp.name}: body is not a TIFF ({type(e).__name__}: {e})"
    if img.shape != (inp.height, inp.width, 3) or img.dtype != np.uint16:
        return f"{inp.name}: image {img.shape} {img.dtype}, expected ({inp.height}, {inp.width}, 3) uint16"
    return None


#: The estimator the load run asks for: the light posterior, within 0.6
#: degrees of the true light on these synthetic ColorChecker scenes for every
#: light used (measured), so an answer more than ``max_angle`` from its own
#: file's light can only be another request's. (The learnt default is built
#: for real photographs and is 2-5 degrees off on some of these charts.)
METHOD = "bayes"


def run_load(base: str, inputs, *, pid: int | None = None, timeout: float = 600.0,
             max_angle: float = 3.0, method: str = METHOD) -> LoadReport:
    """Reference pass, concurrent burst and checks against a server at
    ``base`` (see the module docstring). ``pid``: the server's process, for
    its peak memory; ``method``: the estimator asked for (:data:`METHOD`)."""
    import httpx

    rep = LoadReport(n=len(inputs), image_mb=inputs[0].height * inputs[0].width * 6 / 2**20 if inputs else 0.0)
    reference = {}
    with httpx.Client(base_url=base, timeout=timeout) as client:
        for inp in inputs:
            r = client.post("/v1/white-balance", data={"response": "json", "method": method},
                            files={"file": (inp.name, inp.data, "image/x-adobe-dng")})
            if r.status_code != 200:
                rep.failures.append(f"{inp.name} ({inp.light}) reference request: {r.status_code} {r.text[:200]}")
                continue
            reference[inp.name] = np.asarray(r.json()["illuminant"]["camera_rgb"], float)
    if pid is not None:
        rep.rss_before_mb = status_kb(pid, "VmRSS") / 1024
        if not reset_peak(pid):
            pid = None
    results, rep.wall_s = asyncio.run(_burst(base, inputs, timeout, {"format": "tiff", "method": method}))
    if pid is not None:
        rep.peak_rss_mb = status_kb(pid, "VmHWM") / 1024
    for inp, r, dt, err in results:
        rep.latencies_s.append(dt)
        where = f"{inp.name} ({inp.light})"
        if err is not None:
            rep.failures.append(f"{where}: {err}")
            continue
        if r.status_code != 200:
            rep.failures.append(f"{where}: {r.status_code} {r.text[:200]}")
            continue
        try:
            est = np.asarray(json.loads(r.headers["x-illuminant"])["illuminant"]["camera_rgb"], float)
        except (KeyError, ValueError, TypeError) as e:
            rep.failures.append(f"{where}: X-Illuminant unreadable ({type(e).__name__}: {e})")
            continue
        ref = reference.get(inp.name)
        if ref is not None and not np.allclose(est, ref, rtol=1e-6, atol=0):
            rep.failures.append(f"{where}: estimate {est.tolist()} differs from this file's own reference "
                                f"{ref.tolist()} (leak between requests?)")
            continue
        angle = float(angular_error(est, inp.light_rgb))
        rep.angles_deg.append(angle)
        if not angle <= max_angle:
            rep.failures.append(f"{where}: estimate {angle:.2f} deg from the file's true light (> {max_angle})")
            continue
        problem = _check_image(inp, r)
        if problem:
            rep.failures.append(problem)
            continue
        rep.ok += 1
    return rep


def _free_port() -> int:
    """A free loopback port: the first free one of ``WANDELL_BENCH_PORTS``
    (``LOW-HIGH``) when it is set (a shared machine's allotment), else the
    system's choice."""
    span = os.environ.get("WANDELL_BENCH_PORTS")
    if span:
        low, high = (int(v) for v in span.split("-"))
        for port in range(low, high + 1):
            with socket.socket() as s:
                try:
                    s.bind(("127.0.0.1", port))
                except OSError:
                    continue
                return port
        raise RuntimeError(f"no free port in WANDELL_BENCH_PORTS={span}")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(port: int | None = None, env: dict | None = None, tree: str | None = None):
    """The service under uvicorn on 127.0.0.1 (as the README starts it):
    ``(process, base URL)`` once ``/health`` answers. ``tree``: another
    checkout's service instead (its folder first on the path and the
    working directory, the current folder left off the path, ``-P``)."""
    import httpx

    port = port or _free_port()
    env = {**os.environ, **(env or {}), **({"PYTHONPATH": tree} if tree else {})}
    proc = subprocess.Popen([sys.executable, *(["-P"] if tree else []), "-m", "uvicorn", "service.app:app",
                             "--host", "127.0.0.1", "--port", str(port), "--log-level", "warning"],
                            env=env, cwd=tree)
    what = f"the server of {tree}" if tree else "the server"
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"{what} exited with status {proc.returncode}")
        try:
            if httpx.get(base + "/health", timeout=2).status_code == 200:
                return proc, base
        except httpx.TransportError:
            time.sleep(0.2)
    proc.terminate()
    raise RuntimeError(f"{what} did not answer /health within 120 s")


def _loopback(url: str) -> bool:
    host = urlparse(url).hostname or ""
    return host == "localhost" or host == "::1" or host.startswith("127.")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=50, help="concurrent requests (one DNG and light each)")
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--width", type=int, default=768)
    ap.add_argument("--url", help="a running server on loopback, e.g. http://127.0.0.1:8000")
    ap.add_argument("--pid", type=int, help="with --url: the server's process id, for its peak memory")
    ap.add_argument("--timeout", type=float, default=600.0, help="seconds per request")
    ap.add_argument("--max-angle", type=float, default=3.0,
                    help="largest accepted angle (deg) between an estimate and its file's true light")
    args = ap.parse_args(argv)
    if args.url and not _loopback(args.url):
        ap.error("--url must be a loopback address (127.0.0.0/8, localhost or ::1)")

    t0 = time.perf_counter()
    inputs = make_inputs(args.n, args.height, args.width)
    print(f"wrote {len(inputs)} DNGs of {args.width}x{args.height} ({len(inputs[0].data) / 2**20:.1f} MB each, "
          f"lights {inputs[0].light} ... {inputs[-1].light}) in {time.perf_counter() - t0:.1f} s", flush=True)
    proc = None
    try:
        if args.url:
            base, pid = args.url.rstrip("/"), args.pid
        else:
            proc, base = start_server()
            pid = proc.pid
        rep = run_load(base, inputs, pid=pid, timeout=args.timeout, max_angle=args.max_angle)
    finally:
        if proc is not None:
            proc.terminate()
            try:
                proc.wait(10)
            except subprocess.TimeoutExpired:
                proc.kill()
    print(rep.summary())
    ok = not rep.failures and rep.ok == rep.n
    print("OK" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
