"""Issue 29, item 7: the house has no back doors. ``models`` (spectral data)
is the ground floor, ``recovery`` (the numerical core) stands on it and
``service`` (HTTP, CLI, batches) on both: imports point down only, so no
import cycle can cross packages. ``benchmarks`` and ``testing`` are outside
the product and never imported by it. The imports are read from the source
(every ``import``, at module level or inside a function, and every
``importlib.import_module("...")`` with a literal name), so a lazy import
inside a function counts as much as one at the top."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: package -> the project packages it may import (besides itself).
ALLOWED = {"models": set(), "recovery": {"models"}, "service": {"models", "recovery"}}
PROJECT = {"models", "recovery", "service", "benchmarks", "testing", "tests"}
#: Issue 29, item 7: no service module above this many lines.
MAX_SERVICE_LINES = 850


def _imports(path: Path):
    """(line, absolute module name) of every import in ``path``."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    pkg = path.relative_to(ROOT).parts[:-1]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level:               # relative: resolve against the file's package
                base = list(pkg[:len(pkg) - node.level + 1])
                yield node.lineno, ".".join(base + ([node.module] if node.module else []))
            elif node.module:
                yield node.lineno, node.module
        elif (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)
              and isinstance(node.args[0].value, str)
              and getattr(node.func, "attr", getattr(node.func, "id", None)) in ("import_module", "__import__")):
            yield node.lineno, node.args[0].value


def _violations():
    bad = []
    for pkg, allowed in ALLOWED.items():
        for f in sorted((ROOT / pkg).rglob("*.py")):
            for line, mod in _imports(f):
                top = mod.split(".")[0]
                if top in PROJECT and top != pkg and top not in allowed:
                    bad.append(f"{f.relative_to(ROOT)}:{line} imports {mod}")
    return bad


def test_imports_point_down_only():
    assert _violations() == []


def test_the_scan_sees_lazy_and_relative_imports(tmp_path, monkeypatch):
    """The scan is not blind: an upward import inside a function, a relative
    one that climbs out of the package and an ``import_module`` are found."""
    fake = tmp_path / "models" / "sub"
    fake.mkdir(parents=True)
    (fake / "x.py").write_text("def f():\n    from recovery import api\n"
                               "from ...service import app\n"
                               "import importlib\nimportlib.import_module('service.pipeline')\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    found = [m for _, m in _imports(fake / "x.py")]
    assert "recovery" in found and "service" in found and "service.pipeline" in found
    assert len(_violations()) == 3


@pytest.mark.parametrize("pkg,forbidden", [("models", ("recovery", "service")), ("recovery", ("service",))])
def test_importing_a_package_loads_nothing_above_it(pkg, forbidden):
    """At run time too: a fresh interpreter importing ``pkg`` and every
    module of it has none of the packages above it in ``sys.modules``."""
    mods = sorted(".".join(p.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
                  for p in (ROOT / pkg).rglob("*.py"))
    code = ("import importlib, sys\n"
            f"for m in {mods!r}:\n    importlib.import_module(m)\n"
            f"print(sorted({{k.split('.')[0] for k in sys.modules}} & {set(forbidden)!r}))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]", out.stdout


def test_no_service_module_is_over_the_limit():
    long = {str(f.relative_to(ROOT)): n for f in (ROOT / "service").rglob("*.py")
            if (n := len(f.read_text(encoding="utf-8").splitlines())) > MAX_SERVICE_LINES}
    assert long == {}, f"split these by concern (at most {MAX_SERVICE_LINES} lines): {long}"
