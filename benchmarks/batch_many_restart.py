"""Many small batches made at once, and a restart in the middle (round 5 of
the batch probes, docs/reliability.md): every accepted batch must come back,
and each of its items end exactly once.

``python -m benchmarks.batch_many_restart [--batches 20] [--stop sigterm|kill9] [--after 3] [--during 0.5]``

Starts ``python -m service`` as users do (a fresh ``WANDELL_DATA_DIR``, 2 pool
workers), POSTs ``--batches`` batches of 1 to 3 small DNGs at once (httpx,
concurrently), stops the server (SIGTERM or SIGKILL to its process group)
``--after`` seconds after the answers, or ``--during`` seconds after the
POSTs started (while they are being answered), starts it again on the same
directory and waits for every accepted batch to settle. Prints the POSTs'
status codes, and: batches accepted, listed and lost; items done, failed,
stuck (pending/running after 600 s) and written twice (``writes.log``); lock
files left; batch folders not accepted (a POST cut by the stop). Exits 1 if a
batch was lost or an item failed, stuck or was written twice.
"""

from __future__ import annotations

import argparse
import asyncio
import glob
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _start(port: int, data: str, log: str) -> subprocess.Popen:
    import httpx

    env = dict(os.environ, WANDELL_HOST="127.0.0.1", WANDELL_PORT=str(port), WANDELL_DATA_DIR=data,
               WANDELL_BATCH_WORKERS="2")
    p = subprocess.Popen([sys.executable, "-m", "service"], cwd=ROOT, env=env, stdout=open(log, "a"),
                         stderr=subprocess.STDOUT, start_new_session=True)
    for _ in range(600):
        try:
            if httpx.get(f"http://127.0.0.1:{port}/health", timeout=2).status_code == 200:
                return p
        except httpx.HTTPError:
            time.sleep(0.1)
    raise SystemExit("the server did not start")


async def _posts(base: str, files: list[str], n: int, per: int, stop):
    import httpx

    async def one(c, i):
        names = files[(i * per) % len(files):][:per]
        fs = [("files", (os.path.basename(f), open(f, "rb").read(), "application/octet-stream")) for f in names]
        try:
            r = await c.post(f"{base}/v1/batches", files=fs, data={"format": "png"}, timeout=120)
            return r.status_code, (r.json().get("id") if r.status_code == 202 else None), len(names)
        except httpx.HTTPError as e:
            return type(e).__name__, None, len(names)

    async with httpx.AsyncClient() as c:
        got = await asyncio.gather(*[one(c, i) for i in range(n)], stop())
    return got[:n]


def main(argv=None) -> int:
    import httpx

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, default=20)
    ap.add_argument("--stop", choices=("sigterm", "kill9"), default="sigterm")
    ap.add_argument("--after", type=float, default=3.0, help="seconds after the answers")
    ap.add_argument("--keep", action="store_true", help="keep (and print) the work folder")
    ap.add_argument("--during", type=float, default=None, help="seconds after the POSTs started (overrides --after)")
    args = ap.parse_args(argv)
    from testing.dngwriter import scene_dng

    work = tempfile.mkdtemp(prefix="batch-many-")
    data, log = os.path.join(work, "data"), os.path.join(work, "server.log")
    files = []
    for i in range(20):
        files.append(os.path.join(work, f"s{i:02d}.dng"))
        scene_dng(files[-1], "Nikon 5100 (NPL)", "D65", 200, 300, seed=i)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    base = f"http://127.0.0.1:{port}"
    sig = signal.SIGKILL if args.stop == "kill9" else signal.SIGTERM
    p = _start(port, data, log)

    async def stop():
        if args.during is not None:
            await asyncio.sleep(args.during)
            os.killpg(p.pid, sig)

    try:
        got = asyncio.run(_posts(base, files, args.batches, 3, stop))
        codes = [g[0] for g in got]
        print("POST answers:", {str(k): codes.count(k) for k in set(codes)})
        if args.during is None:
            time.sleep(args.after)
            os.killpg(p.pid, sig)
        p.wait(60)
        p = _start(port, data, log)
        ids = {g[1]: g[2] for g in got if g[1]}
        docs, t_end = {}, time.time() + 600
        while len(docs) < len(ids) and time.time() < t_end:
            for b in set(ids) - set(docs):
                r = httpx.get(f"{base}/v1/batches/{b}", timeout=30)
                if r.status_code != 200:
                    docs[b] = r.status_code
                elif r.json()["settled"] and r.json()["status"] not in ("queued", "running"):
                    docs[b] = r.json()
            time.sleep(0.5)
        listed = {b["id"] for b in httpx.get(f"{base}/v1/batches", timeout=30).json()["batches"]}
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGTERM)
            p.wait(60)
    lost = sum(not isinstance(docs.get(b), dict) for b in ids if b in docs) + len(set(ids) - listed)
    done = sum(d["counts"]["done"] for d in docs.values() if isinstance(d, dict))
    failed = sum(d["counts"]["failed"] for d in docs.values() if isinstance(d, dict))
    stuck = sum(ids.values()) - done - failed - sum(d["counts"]["cancelled"] for d in docs.values()
                                                    if isinstance(d, dict))
    twice = 0
    for b in ids:
        wl = os.path.join(data, "batches", b, "writes.log")
        outs = [json.loads(line)["out"] for line in open(wl)] if os.path.exists(wl) else []
        twice += len(outs) - len(set(outs))
    locks = glob.glob(os.path.join(data, "batches", "*", "out", ".wandell", "*.lock"))
    folders = set(os.listdir(os.path.join(data, "batches"))) if os.path.isdir(os.path.join(data, "batches")) else set()
    print(f"batches accepted {len(ids)}, listed {len(listed & set(ids))}, lost {lost}; items done {done}/"
          f"{sum(ids.values())}, failed {failed}, stuck {stuck}, written twice {twice}; lock files left {len(locks)}; "
          f"batch folders not accepted {len(folders - set(ids))}")
    if args.keep:
        print("kept:", work)
    else:
        shutil.rmtree(work, ignore_errors=True)
    return 1 if lost or failed or stuck or twice else 0


if __name__ == "__main__":
    sys.exit(main())
