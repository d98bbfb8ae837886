"""Issue 17's own reproductions (``shared/repro/round2``) of part A, run as
their README says: the four request scripts against ``python -m service``
started the way users start it (``WANDELL_HOST/PORT/DATA_DIR``), the two
memory scripts starting servers of their own from this checkout. Each exits
0 ("FIXED") once its problem is gone, 1 while it is present."""

from __future__ import annotations

import socket
import subprocess
from pathlib import Path

from .conftest import SHARED, running_server, unavailable

ROOT = Path(__file__).resolve().parents[1]
REQUEST_SCRIPTS = ("nonascii_metadata_tiff", "xmp_filename", "target_names", "json_fields")
OWN_SERVER_SCRIPTS = ("mem_wide_csv", "mem_packbits_tiff")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_round2_reproductions_of_part_a_are_fixed(tmp_path):
    repro = SHARED / "repro" / "round2"
    if not (repro / "README.md").is_file():
        unavailable(f"{repro} is absent (the shared folder with the issue-17 reproductions)")
    py = ROOT / ".venv" / "bin" / "python"      # what the scripts start their own servers with
    if not py.exists():
        unavailable(f"{py} is absent: the scripts run from a checkout with its .venv (the README's set-up)")
    # the memory scripts run meanwhile, each on its own free port with its own servers
    own = {name: subprocess.Popen([str(py), str(repro / f"{name}.py"), str(_free_port())], cwd=ROOT,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
           for name in OWN_SERVER_SCRIPTS}
    results = {}
    try:
        with running_server({"data_dir": tmp_path / "data"}) as (base, _, _log):
            port = base.rsplit(":", 1)[1]
            for name in REQUEST_SCRIPTS:
                r = subprocess.run([str(py), str(repro / f"{name}.py"), port], cwd=ROOT, capture_output=True,
                                   text=True, timeout=300)
                results[name] = (r.returncode, (r.stdout + r.stderr).strip()[-600:])
        for name, p in own.items():
            out, _ = p.communicate(timeout=600)
            results[name] = (p.returncode, out.strip()[-600:])
    finally:
        for p in own.values():
            if p.poll() is None:
                p.kill()
                p.wait()
    print("\n".join(f"{k}: exit {c}: {t}" for k, (c, t) in results.items()))
    assert {k: c for k, (c, _) in results.items()} == dict.fromkeys(REQUEST_SCRIPTS + OWN_SERVER_SCRIPTS, 0), results
