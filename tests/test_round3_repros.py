"""Issue 28's own reproductions (``shared/repro/round3``) of part B (every
request's cost bounded, answers right or clearly refused), run as their
README says: ``singular_color_matrix`` and ``head_405`` against
``python -m service`` started the way users start it
(``WANDELL_HOST/PORT/DATA_DIR``), the five others starting servers of their
own from this checkout on free ports. Each exits 0 ("FIXED") once its
problem is gone, 1 while it is present, 2 when it cannot tell.

They run side by side to keep the suite's time down (about 2 minutes in
all instead of 5): ``stalled_readers_tmpdir`` (90 s of waiting) beside the
rest; the two memory scripts together when the machine has the memory they
need (3.5 and 2.5 GB free, their README), else one after the other; the
slow-upload script, whose criterion is a latency, after them.
"""

from __future__ import annotations

import socket
import subprocess
import time
from pathlib import Path

from .conftest import SHARED, running_server, unavailable

ROOT = Path(__file__).resolve().parents[1]
REQUEST_SCRIPTS = ("singular_color_matrix", "head_405")
OWN_SERVER_SCRIPTS = ("light_map_blowup", "mem_surfaces_tiff", "mem_linear_raw_dng", "slow_uploads_fd_exhaustion",
                      "stalled_readers_tmpdir")
#: free memory (GB) each memory script needs, from the reproductions' README
NEEDS_GB = {"mem_surfaces_tiff": 3.5, "mem_linear_raw_dng": 2.5}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _available_gb() -> float:
    try:
        for line in open("/proc/meminfo"):
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 1e6
    except OSError:
        pass
    return 0.0


def test_round3_reproductions_of_part_b_are_fixed(tmp_path):
    repro = SHARED / "repro" / "round3"
    if not (repro / "README.md").is_file():
        unavailable(f"{repro} is absent (the shared folder with the issue-28 reproductions)")
    py = ROOT / ".venv" / "bin" / "python"      # what the scripts start their own servers with
    if not py.exists():
        unavailable(f"{py} is absent: the scripts run from a checkout with its .venv (the README's set-up)")

    def start(name):
        return subprocess.Popen([str(py), str(repro / f"{name}.py"), str(_free_port())], cwd=ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    results, running = {}, {}

    def finish(name, timeout=600):
        p = running.pop(name)
        out, _ = p.communicate(timeout=timeout)
        results[name] = (p.returncode, out.strip()[-600:])

    t0 = time.monotonic()
    try:
        running["stalled_readers_tmpdir"] = start("stalled_readers_tmpdir")
        running["light_map_blowup"] = start("light_map_blowup")
        with running_server({"data_dir": tmp_path / "data"}) as (base, _, _log):
            port = base.rsplit(":", 1)[1]
            for name in REQUEST_SCRIPTS:
                r = subprocess.run([str(py), str(repro / f"{name}.py"), port], cwd=ROOT, capture_output=True,
                                   text=True, timeout=300)
                results[name] = (r.returncode, (r.stdout + r.stderr).strip()[-600:])
        finish("light_map_blowup")
        together = _available_gb() >= sum(NEEDS_GB.values()) + 1.0
        for name in NEEDS_GB:
            running[name] = start(name)
            if not together:
                finish(name)
        for name in [n for n in NEEDS_GB if n in running]:
            finish(name)
        running["slow_uploads_fd_exhaustion"] = start("slow_uploads_fd_exhaustion")
        finish("slow_uploads_fd_exhaustion")
        finish("stalled_readers_tmpdir")
    finally:
        for p in running.values():
            if p.poll() is None:
                p.kill()
                p.wait()
    print(f"{time.monotonic() - t0:.0f} s in all\n" + "\n".join(f"{k}: exit {c}: {t}" for k, (c, t) in results.items()))
    assert {k: c for k, (c, _) in results.items()} == dict.fromkeys(REQUEST_SCRIPTS + OWN_SERVER_SCRIPTS, 0), results
