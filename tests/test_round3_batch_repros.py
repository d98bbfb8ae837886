"""Issue 28, part A: the round-3 reproductions of batch faults
(``shared/repro/round3``), run as their README says, each starting
``python -m service`` from this checkout on a free port (the Dask ones also a
real ``dask scheduler`` on 127.0.0.1:8590 and ``dask worker`` processes).
Each exits 0 ("FIXED") once its problem is gone, 1 while it is present, 2
when it could not tell (then this test fails too: the check did not run).

The scripts are run once, concurrently in four lanes (the two Dask scripts
share the scheduler's port, so they run one after the other; the timed ones
measure /health latency against limits of 1-3 s that the measured latencies,
0.0-0.1 s under this load, are far below); each script is then one test
case. About 4-5 minutes on the 2-core machine."""

from __future__ import annotations

import os
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest

from .conftest import SHARED, unavailable

ROOT = Path(__file__).resolve().parents[1]
REPRO = SHARED / "repro" / "round3"

#: Lanes run side by side; the scripts of one lane one after another. The
#: folder scan (200,000 files to create and remove) takes a lane of its own.
LANES = (
    ("dask_client_closed", "dask_fixed_capacity"),                  # both use the scheduler port 8590
    ("folder_scan_blocks_loop",),
    ("store_lock_blocks_loop", "shared_cancel_keeps_pool", "sigterm_fails_items", "worker_killed_breaks_pool"),
    ("store_lost_batches_gone", "folder_symlink_swap", "folder_nonutf8_name", "diskfull_item_stuck"),
)
SCRIPTS = tuple(s for lane in LANES for s in lane)
#: Scripts that mount a tmpfs (root only).
NEEDS_ROOT = {"diskfull_item_stuck"}
#: Scripts written against an API that has changed since, and why (strict: a
#: script fixed in the shared folder makes its case pass, and this must go).
#: scripts whose own last steps no longer fit the service (none: a plain DELETE only cancels again,
#: ``?remove=true`` removes, so ``diskfull_item_stuck``'s closing cancel keeps its batch)
STALE: dict = {}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _is_root() -> bool:
    return hasattr(os, "geteuid") and os.geteuid() == 0


@pytest.fixture(scope="module")
def outcomes():
    """Every script's (exit code, last lines, seconds), run once."""
    if not (REPRO / "README.md").is_file():
        unavailable(f"{REPRO} is absent (the shared folder with the issue-28 reproductions)")
    py = ROOT / ".venv" / "bin" / "python"      # what the scripts start their servers with
    if not py.exists():
        unavailable(f"{py} is absent: the scripts run from a checkout with its .venv (the README's set-up)")
    results: dict = {}

    def lane(names):
        for name in names:
            if name in NEEDS_ROOT and not _is_root():
                continue
            t0 = time.monotonic()
            try:
                r = subprocess.run([str(py), str(REPRO / f"{name}.py"), str(_free_port())], cwd=ROOT,
                                   capture_output=True, text=True, timeout=600)
                results[name] = (r.returncode, (r.stdout + r.stderr).strip()[-800:], time.monotonic() - t0)
            except subprocess.TimeoutExpired as e:   # the script stops its own servers only when it ends
                results[name] = (None, f"timed out after 600 s: {str(e.stdout)[-400:]}", time.monotonic() - t0)

    threads = [threading.Thread(target=lane, args=(names,)) for names in LANES]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    print("\n".join(f"{k}: exit {c} in {s:.0f} s: {t.splitlines()[-1] if t else ''}"
                    for k, (c, t, s) in results.items()))
    return results


@pytest.mark.parametrize("name", [pytest.param(s, marks=pytest.mark.xfail(strict=True, reason=STALE[s]))
                                  if s in STALE else s for s in SCRIPTS])
def test_round3_batch_reproduction_is_fixed(outcomes, name):
    if name in NEEDS_ROOT and not _is_root():
        pytest.skip(f"{name} mounts a tmpfs as the data directory: it needs root")
    code, text, seconds = outcomes[name]
    assert code == 0, f"{name}: exit {code} after {seconds:.0f} s: {text}"
    assert text.splitlines()[-1].startswith("FIXED:"), text
