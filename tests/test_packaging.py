"""Every data file the product reads is in its installed package.

The README installs the project editable (``pip install -e .``), where the
source tree is the package, so a data file missing from
``[tool.setuptools.package-data]`` goes unnoticed until someone installs a
wheel: ``recovery/data/learned_confidence.json`` (the confidence's law) and
``models/data/surface_band_scale.json`` (the surface bands' calibration)
were left out of it until 2026-12-06 (only ``*.npz`` was listed). This
checks the globs against every file under the packages' ``data/`` folders,
static files and schemas (fast, no build).
"""

from __future__ import annotations

import fnmatch
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_shipped_data_file_is_package_data():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-data"]
    missing = []
    for pkg, sub in (("recovery", "data"), ("models", "data"), ("service", "static"), ("service", "icc"),
                     ("service", "schemas")):
        for f in sorted((ROOT / pkg / sub).iterdir()):
            if f.is_dir() or f.suffix in (".py", ".pyc") or f.name.startswith("."):
                continue
            rel = f"{sub}/{f.name}"
            if not any(fnmatch.fnmatch(rel, g) for g in cfg.get(pkg, [])):
                missing.append(f"{pkg}/{rel}")
    assert not missing, f"not in [tool.setuptools.package-data]: {missing}"
