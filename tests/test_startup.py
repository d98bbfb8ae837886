"""What the commands print on start-up (issue 19, item 8): no colour-science
"Matplotlib related API features are not available" warning (Matplotlib is
not a dependency of the product, only of the bench extra), and
``python -m service --help`` / ``wandell-serve --help`` print their usage
instead of starting a server.

The installed product has no Matplotlib; these tests hide it from the child
process (``sys.modules["matplotlib"] = None``) so colour-science takes the
path that warns."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

from testing.dngwriter import scene_dng

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WARNING = "Matplotlib"


def _run_without_matplotlib(code: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    prog = "import sys; sys.modules['matplotlib'] = None\n" + code
    return subprocess.run([sys.executable, "-c", prog], capture_output=True, text=True, timeout=timeout,
                          cwd=ROOT)


def test_colour_itself_warns_without_matplotlib():
    """The check below is meaningful: colour-science does warn when it
    cannot import Matplotlib."""
    r = _run_without_matplotlib("import colour")
    assert r.returncode == 0, r.stderr
    assert WARNING in r.stderr


def _cli(args: list[str]) -> str:
    return ("import runpy; sys.argv = ['wandell'] + " + repr(args)
            + "\nrunpy.run_module('service.cli', run_name='__main__')")


def test_wandell_help_has_no_matplotlib_warning():
    r = _run_without_matplotlib(_cli(["--help"]))
    assert r.returncode == 0, r.stderr
    assert "usage: wandell" in r.stdout
    assert WARNING not in r.stderr and r.stderr == ""


def test_wandell_analyze_has_no_matplotlib_warning(tmp_path):
    dng = tmp_path / "a.dng"
    scene_dng(dng, "Nikon 5100 (NPL)", "D4000", 64, 96, seed=0, grid=(4, 6))
    r = _run_without_matplotlib(_cli(["analyze", str(dng)]))
    assert r.returncode == 0, r.stderr
    assert '"illuminant"' in r.stdout
    assert WARNING not in r.stderr, r.stderr


def test_the_app_imports_without_matplotlib_warning():
    """The server log: importing the ASGI app (and colour, as the first
    white balance does) prints nothing."""
    r = _run_without_matplotlib("import service.app, colour")
    assert r.returncode == 0, r.stderr
    assert WARNING not in r.stderr, r.stderr


def test_other_colour_warnings_are_not_hidden():
    """The filter is that one message: colour's other warnings still show."""
    r = _run_without_matplotlib("import service, colour\nfrom colour.utilities import usage_warning\n"
                                "usage_warning('something else')")
    assert "something else" in r.stderr and WARNING not in r.stderr


@pytest.mark.parametrize("argv", [[sys.executable, "-m", "service", "--help"], ["wandell-serve", "--help"]])
def test_serve_help_prints_usage_and_exits(argv):
    if argv[0] == "wandell-serve":
        exe = shutil.which("wandell-serve") or os.path.join(os.path.dirname(sys.executable), "wandell-serve")
        if not os.path.exists(exe):
            pytest.skip("wandell-serve is not installed in this environment")
        argv = [exe] + argv[1:]
    r = subprocess.run(argv, capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert "usage: wandell-serve" in r.stdout and "--port" in r.stdout
    assert "Uvicorn running" not in r.stderr


def test_serve_rejects_unknown_arguments():
    r = subprocess.run([sys.executable, "-m", "service", "--no-such-option"], capture_output=True, text=True,
                       timeout=60, cwd=ROOT)
    assert r.returncode == 2 and "unrecognized arguments" in r.stderr
