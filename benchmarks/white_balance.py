"""White-balance speed and memory benchmark (issues 3 and 19).

``python -m benchmarks.white_balance [--height 4000 --width 6000] [--repeat 5] [--cli-repeat 5]``

Writes a 24-megapixel DNG with the fixture code (:mod:`testing.dngwriter`),
starts the real service (uvicorn, as the README starts it) on a free
loopback port, and measures side by side in one run, the repeats
interleaved (one of each in turn) and the medians quoted, so the ratios hold
on a machine whose speed drifts:

* rawpy's own default ``postprocess()`` of the file (imread +
  postprocess) in a warm worker process: the reference of every ratio,
* the full ``POST /v1/white-balance`` request over HTTP (upload, decode,
  estimate, demosaic, correct, encode, download), made by curl as a user
  would (httpx's own reading of a 144 MB answer takes longer than the
  server's sending it), for a 16-bit TIFF, an 8-bit PNG and a JPEG, with the server's own steps (``timings_ms`` of the
  ``X-Illuminant`` header) and what is left: moving the upload and the
  answer through HTTP,
* the estimate alone: ``POST /v1/analyze`` over HTTP, and the estimation
  step inside the server (half-size decode + estimate),
* whole commands, started fresh each time, each writing a new file (the
  last round's output removed before, outside the timing): ``wandell
  white-balance FILE OUT.{tif,png,jpg}`` against a script that runs rawpy
  ``postprocess()`` and writes the same format (tifffile for the 16-bit TIFF, with
  ``output_bps=16``; OpenCV's ``imwrite`` with its defaults for PNG, quality
  95 for JPEG, as the service writes), and ``wandell analyze`` of the real
  CinemaDNG (``--real``, the shared ``Blackmagic.dng``) when it is there.

``--before TREE`` (another checkout, e.g. ``git worktree add /tmp/before
HEAD~3``) measures that tree's server and CLI too, in the same run,
interleaved with this tree's: rows marked ``before``, and the ratios
after/before.

Whole commands run with Python's bytecode written (``PYTHONDONTWRITEBYTECODE``
removed from their environment), as an installed ``wandell`` runs: pip
compiles it at install; without it every run of the CLI compiles the
project's 60-odd modules again (about 50 ms of ``wandell analyze``).

Peak memory of a request is the server's resident-set high-water mark
(``VmHWM``, reset through ``/proc/<pid>/clear_refs``) above its resident size
just before the step, against the decoded 16-bit image (H x W x 3 x 2
bytes); of a whole command, its maximum resident set (``ru_maxrss``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
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

#: The script the CLI is compared with: rawpy's postprocess(), then the same
#: format written by the usual tools.
_RAWPY_SCRIPT = r"""
import sys, rawpy
src, out = sys.argv[1], sys.argv[2]
fmt = out.rsplit(".", 1)[-1]
with rawpy.imread(src) as raw:
    rgb = raw.postprocess(output_bps=16) if fmt == "tif" else raw.postprocess()
if fmt == "tif":
    import tifffile
    tifffile.imwrite(out, rgb, photometric="rgb")
else:
    import cv2
    cv2.imwrite(out, rgb[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95] if fmt == "jpg" else [])
"""

#: the real CinemaDNG of the issues (4128 x 2176), for ``wandell analyze``
REAL_DNG = os.path.join(os.environ.get("WANDELL_SHARED_DIR") or os.path.join(
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "shared"),
    "data", "raw", "Blackmagic.dng")


#: Runs whole commands for the bench (started before the bench holds any
#: image, so a command's peak resident size is its own: Linux carries a
#: forked child's resident size over ``exec`` into ``ru_maxrss``).
_LAUNCHER = r"""
import json, os, subprocess, sys, time
for line in sys.stdin:
    argv = json.loads(line)
    t0 = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    err = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    code = os.waitstatus_to_exitcode(status)
    print(json.dumps({"wall": wall, "peak_mb": usage.ru_maxrss / 1024, "code": code,
                      "err": err.decode(errors="replace")[-2000:]}), flush=True)
"""


class Launcher:
    """A small process that times whole commands: wall seconds and peak
    resident MB (``ru_maxrss``) of each, bytecode written (module docstring)."""

    def __init__(self):
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        self.proc = subprocess.Popen([sys.executable, "-S", "-c", _LAUNCHER], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env)

    def run(self, argv: list[str]) -> tuple[float, float]:
        self.proc.stdin.write(json.dumps(argv) + "\n")
        self.proc.stdin.flush()
        r = json.loads(self.proc.stdout.readline())
        if r["code"] != 0:
            raise RuntimeError(f"{argv} exited {r['code']}: {r['err']}")
        return r["wall"], r["peak_mb"]

    def close(self):
        self.proc.stdin.close()
        self.proc.wait()


def _median(xs):
    return statistics.median(xs) if xs else float("nan")


def bench_arguments(doc: str, argv=None, repeat: int = 3, **extra) -> argparse.Namespace:
    """The options the 24-megapixel benches share (size, repeats, camera, light)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0])
    ap.add_argument("--height", type=int, default=4000)
    ap.add_argument("--width", type=int, default=6000)
    ap.add_argument("--repeat", type=int, default=repeat)
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


def _round_order(keys: list, i: int) -> list:
    """The steps of round ``i``: in odd rounds each ``before X`` runs ahead of
    its ``X``. Whichever writes a 144 MB TIFF first in a round pays for
    memory the system had just taken back (in this VM 1.3-1.5 s of TIFF
    writing against 0.04-0.1 s for the one after it): alternating shares that
    between the two trees instead of charging it to one."""
    if i % 2 == 0:
        return keys
    out = list(keys)
    for k in keys:
        b = f"before {k}"
        if b in out:
            a, c = out.index(k), out.index(b)
            out[a], out[c] = out[c], out[a]
    return out


def _start_tree_server(tree: str):
    """The service of another checkout under uvicorn (``--before``)."""
    from .load import start_server

    return start_server(tree=tree)


def main(argv=None) -> None:
    args = bench_arguments(__doc__, argv, repeat=5,
                           cli_repeat=dict(type=int, default=5, help="runs of each whole command"),
                           formats=dict(default="tiff,png,jpeg", help="white-balance formats over HTTP"),
                           real=dict(default=REAL_DNG, help="the real CinemaDNG for wandell analyze"),
                           before=dict(default=None, help="another checkout measured in the same run "
                                                           "(its server and CLI, interleaved)"))

    import httpx

    from .load import reset_peak, status_kb, start_server

    formats = [f for f in args.formats.split(",") if f]
    cli = [sys.executable, "-m", "service.cli"]     # what the installed `wandell` runs, from this tree
    before = os.path.abspath(args.before) if args.before else None
    # the other tree's modules first: -P leaves the current folder (this tree) off sys.path
    cli_before = ["env", f"PYTHONPATH={before}", sys.executable, "-P", "-m", "service.cli"] if before else None
    print(f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} {os.getloadavg()[2]:.2f} "
          f"on {os.cpu_count()} CPUs")
    launcher = Launcher()
    with tempfile.TemporaryDirectory() as tmp:
        path = write_bench_dng(tmp, args)
        decoded_mb = args.height * args.width * 3 * 2 / 2**20

        worker = subprocess.Popen([sys.executable, "-c", _RAWPY_WORKER, path], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True)
        server, base = start_server()
        bserver = bbase = None
        if before:
            bserver, bbase = _start_tree_server(before)
        try:
            assert worker.stdout.readline().strip() == "ready"
            client = httpx.Client(timeout=600)

            def post(endpoint, fields, url=None):
                with open(path, "rb") as fh:
                    r = client.post((url or base) + endpoint, files={"file": ("bench.dng", fh, "image/x-adobe-dng")},
                                    data=fields)
                assert r.status_code == 200, r.text[:500]
                return r

            def measure(pid, fn):
                before = status_kb(pid, "VmRSS")
                reset_peak(pid)
                t0 = time.perf_counter()
                out = fn()
                return time.perf_counter() - t0, (status_kb(pid, "VmHWM") - before) / 1024, out

            def rawpy_once():
                worker.stdin.write("go\n")
                worker.stdin.flush()
                return float(worker.stdout.readline())

            def post_curl(endpoint, fields, url=None):
                """The request as curl makes it (the answer to /dev/null):
                a Python client's own reading of a 144 MB answer costs more
                than the server's sending it. ``{"headers", "bytes"}``."""
                argv = ["curl", "-s", "-S", "-o", "/dev/null", "-D", "-", "-w", "\n%{http_code} %{size_download}",
                        "-H", "Expect:", "-F", f"file=@{path};type=image/x-adobe-dng;filename=bench.dng"]
                for k, v in fields.items():
                    argv += ["-F", f"{k}={v}"]
                r = subprocess.run(argv + [(url or base) + endpoint], capture_output=True, text=True, check=True)
                head, _, tail = r.stdout.rpartition("\n")
                code, size = tail.split()
                assert code == "200", r.stdout[:500]
                headers = {}
                for line in head.splitlines():
                    name, sep, value = line.partition(":")
                    if sep:
                        headers[name.strip().lower()] = value.strip()
                return {"headers": headers, "bytes": int(size)}

            wb = post_curl if shutil.which("curl") else (
                lambda e, f, u=None: (lambda r: {"headers": dict(r.headers), "bytes": len(r.content)})(post(e, f, u)))
            print("white-balance requests by", "curl" if shutil.which("curl") else "httpx (curl not found)")
            steps = {"rawpy": (worker.pid, rawpy_once)}
            for fmt in formats:
                steps[fmt] = (server.pid, lambda fmt=fmt: wb("/v1/white-balance", {"format": fmt}))
                if before:
                    steps[f"before {fmt}"] = (bserver.pid, lambda fmt=fmt: wb("/v1/white-balance", {"format": fmt},
                                                                               bbase))
            steps["analyze"] = (server.pid, lambda: post("/v1/analyze", {}))
            wb_keys = [k for k in steps if k not in ("rawpy", "analyze")]
            for fmt in formats:                        # warm-up: imports, data, caches
                post("/v1/white-balance", {"format": fmt})
                if before:
                    post("/v1/white-balance", {"format": fmt}, bbase)
            res = {k: {"t": [], "m": [], "out": []} for k in steps}
            for i in range(args.repeat):               # interleaved: one of each in turn
                for k in _round_order(list(steps), i):
                    pid, fn = steps[k]
                    t, m, out = measure(pid, fn)
                    res[k]["t"].append(t)
                    res[k]["m"].append(m)
                    assert k.split()[-1] != "tiff" or out["bytes"] > decoded_mb * 2**20
                    res[k]["out"].append(out)
            for fmt in wb_keys:
                inner = [json.loads(r["headers"]["x-illuminant"])["timings_ms"] for r in res[fmt]["out"]]
                res[fmt]["steps"] = {k: _median([t.get(k, 0.0) for t in inner]) for k in inner[0]}
                res[fmt]["bytes"] = res[fmt]["out"][-1]["bytes"]
                res[fmt]["http"] = _median([t - i["total"] / 1e3 for t, i in zip(res[fmt]["t"], inner)])
            inner = [r.json()["timings_ms"] for r in res["analyze"]["out"]]
            t_est = _median([(t["decode"] + t["estimate"]) / 1e3 for t in inner])
        finally:
            for s in (server, bserver):
                if s is not None:
                    s.terminate()
            worker.kill()
            for s in (server, bserver):
                if s is not None:
                    s.wait()

        # whole commands, started fresh, interleaved
        ext = {"tiff": "tif", "png": "png", "jpeg": "jpg"}
        cmds = {}
        for fmt in formats:
            out = os.path.join(tmp, f"cli.{ext[fmt]}")
            cmds[f"wandell white-balance .{ext[fmt]}"] = cli + ["white-balance", "-q", path, out]
            if before:
                cmds[f"before wandell white-balance .{ext[fmt]}"] = cli_before + [
                    "white-balance", "-q", path, os.path.join(tmp, f"before.{ext[fmt]}")]
            cmds[f"rawpy script .{ext[fmt]}"] = [sys.executable, "-c", _RAWPY_SCRIPT, path,
                                                 os.path.join(tmp, f"script.{ext[fmt]}")]
        real = os.path.abspath(args.real) if args.real and os.path.isfile(args.real) else None
        if real:
            cmds["wandell analyze (real CinemaDNG)"] = cli + ["analyze", real]
            if before:
                cmds["before wandell analyze (real CinemaDNG)"] = cli_before + ["analyze", real]
        if args.cli_repeat < 1:
            cmds = {}
        def fresh(argv_):
            # every command writes a new file: its output of the last round
            # removed first (outside the timing). Overwriting in place let the
            # script reuse the old file's pages while the CLI (a temporary file
            # renamed over the old one) needed 144 MB of new ones, which this VM
            # hands out at up to 2 s; a script writing to a new name paid the same
            out = argv_[-1]
            if out.endswith((".tif", ".png", ".jpg")) and os.path.exists(out):
                os.unlink(out)

        for argv_ in cmds.values():                    # warm-up: page cache, bytecode
            fresh(argv_)
            launcher.run(argv_)
        whole = {k: {"t": [], "m": []} for k in cmds}
        for i in range(args.cli_repeat):
            for k in _round_order(list(cmds), i):
                argv_ = cmds[k]
                fresh(argv_)
                t, m = launcher.run(argv_)
                whole[k]["t"].append(t)
                whole[k]["m"].append(m)
    launcher.close()

    t_raw = _median(res["rawpy"]["t"])
    print(f"\n{'step (24 MP DNG)':44s} {'median s':>9s} {'x rawpy':>8s} {'pairs':>6s} {'peak MB':>8s} "
          f"{'x image':>8s}")
    rows = [("rawpy postprocess() default", "rawpy")]
    names = {"tiff": "16-bit TIFF", "png": "8-bit PNG", "png16": "16-bit PNG", "jpeg": "JPEG"}
    rows += [(f"{'before ' if k.startswith('before') else ''}POST /v1/white-balance ({names.get(k.split()[-1], k)})", k)
             for k in wb_keys]
    rows += [("POST /v1/analyze over HTTP", "analyze")]
    for name, k in rows:
        t, mem = _median(res[k]["t"]), max(res[k]["m"])
        pairs = _median([a / b for a, b in zip(res[k]["t"], res["rawpy"]["t"])])
        print(f"{name:44s} {t:9.2f} {t / t_raw:8.2f} {pairs:6.2f} {mem:8.0f} {mem / decoded_mb:8.2f}")
    print(f"{'estimation in the server (decode+estimate)':44s} {t_est:9.2f} {t_est / t_raw:8.2f}")
    print("(x rawpy: ratio of the medians; pairs: median of the ratios to the rawpy run just before, "
          "which holds better when the machine's load drifts)")
    print(f"\ndecoded 16-bit image: {decoded_mb:.0f} MB; targets (issue 19): white-balance TIFF and PNG <= 0.80 x "
          "rawpy, JPEG <= 0.50 x rawpy; peak no higher than before")
    print("\nwhere a white-balance request's time goes (median ms; http = the request's wall time minus the "
          "server's total: upload and answer on the wire):")
    for fmt in wb_keys:
        st = dict(res[fmt]["steps"])
        st.pop("total", None)
        parts = "  ".join(f"{k} {v:.0f}" for k, v in st.items())
        print(f"  {fmt:13s} {parts}  http {res[fmt]['http'] * 1e3:.0f}  ({res[fmt]['bytes'] / 1e6:.1f} MB answer)")

    print(f"\n{'whole command (fresh process)':44s} {'median s':>9s} {'min':>6s} {'max':>6s} {'peak MB':>8s}")
    for k, v in whole.items():
        print(f"{k:44s} {_median(v['t']):9.2f} {min(v['t']):6.2f} {max(v['t']):6.2f} {max(v['m']):8.0f}")
    print("\nCLI against the rawpy script (median of the pairwise ratios; target <= 1.00):")
    for fmt in formats if whole else ():
        a, b = whole[f"wandell white-balance .{ext[fmt]}"]["t"], whole[f"rawpy script .{ext[fmt]}"]["t"]
        line = f"  .{ext[fmt]:4s} {_median([x / y for x, y in zip(a, b)]):.2f}"
        if before:
            c = whole[f"before wandell white-balance .{ext[fmt]}"]["t"]
            line += f"   before: {_median([x / y for x, y in zip(c, b)]):.2f}"
        print(line)
    if before:
        print("\nthis tree against --before, same run (median of the pairwise ratios of the wall times):")
        for fmt in wb_keys:
            if not fmt.startswith("before"):
                r = _median([x / y for x, y in zip(res[fmt]["t"], res[f"before {fmt}"]["t"])])
                print(f"  POST /v1/white-balance {fmt:6s} {r:.2f}")
        for k in whole:
            if f"before {k}" in whole:
                r = _median([x / y for x, y in zip(whole[k]["t"], whole[f"before {k}"]["t"])])
                print(f"  {k:40s} {r:.2f}")
    if real and whole:
        print(f"\nwandell analyze of the real CinemaDNG: {_median(whole['wandell analyze (real CinemaDNG)']['t']):.2f} s "
              "(target <= 0.80 s)")
    print(f"load average at the end {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
