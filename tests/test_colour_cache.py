"""The shipped colour-science cache (issue 19: ``wandell analyze`` without
importing colour-science): every entry is what colour-science gives now,
exactly, and the numpy Ohno (2013) is colour-science's."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from models import _colour
import service.correction  # noqa: F401 - registers service.pipeline._encoding_lut for recompute()

RAW = "/work/shared/data/raw/Blackmagic.dng"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _keys():
    _colour._index()
    return sorted(_colour._cache)


def test_cache_file_is_shipped():
    assert _colour.CACHE_FILE.exists(), "run python -m benchmarks.build_colour_cache"
    keys = _keys()
    assert _colour._OHNO_KEY in keys
    assert any(k.startswith("models.illuminants._illuminant(") for k in keys)


#: Entries that go through a matrix inverse (a display's RGB -> XYZ from its
#: primaries) are rounded by LAPACK, whose last bits depend on the BLAS kernel
#: the CPU selects and on the numpy build: the sRGB matrix came out 2.8e-17
#: from the cached one under numpy 2.4.6 (OpenBLAS) here. 1e-12 is a
#: thousand times above double rounding of such a chain and far below
#: anything the service reports.
ROUNDING = 1e-12


def _same(a, b, key):
    if isinstance(a, tuple):
        assert isinstance(b, tuple) and len(a) == len(b), key
        for x, y in zip(a, b):
            _same(x, y, key)
    elif isinstance(a, (str, list)):
        assert a == b, key
    else:
        b = np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, key
        if a.dtype.kind == "f":       # LAPACK's last bits depend on the BLAS kernel and numpy build
            np.testing.assert_allclose(a, b, rtol=ROUNDING, atol=ROUNDING, equal_nan=True, err_msg=key)
        else:
            assert np.array_equal(a, b), key


def test_every_entry_is_colour_science_now():
    """Regenerated from colour-science, each entry is the one in the file
    (to LAPACK's rounding, :data:`ROUNDING`; strings, lists and integers
    exactly): the cache cannot drift from the library (rebuild it with
    ``python -m benchmarks.build_colour_cache`` when colour-science changes)."""
    for key in _keys():
        _same(_colour.lookup(key), _colour.recompute(key), key)


def test_cached_values_are_copies():
    key = next(k for k in _keys() if k.startswith("models.illuminants._illuminant("))
    a = _colour.lookup(key)
    a[:] = -1
    assert np.all(_colour.lookup(key) > -1)


def test_ohno2013_is_colour_sciences():
    import colour

    rng = np.random.default_rng(19)
    cct = np.exp(rng.uniform(np.log(1200), np.log(60000), 300))
    duv = rng.uniform(-0.05, 0.05, 300)
    xy = np.concatenate([colour.temperature.CCT_to_xy_CIE_D(np.clip(cct, 4000, 25000)).reshape(-1, 2),
                         colour.UCS_uv_to_xy(colour.temperature.CCT_to_uv_Ohno2013(np.stack([cct, duv], 1)))])
    uv = _colour.xy_to_UCS_uv(xy)
    np.testing.assert_allclose(uv, colour.xy_to_UCS_uv(xy), rtol=1e-14, atol=0)
    ours = np.stack([_colour.uv_to_CCT_Ohno2013(u) for u in uv])
    theirs = np.stack([colour.temperature.uv_to_CCT_Ohno2013(u) for u in uv])
    np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(_colour.uv_to_CCT_Ohno2013(uv), theirs, rtol=1e-12, atol=1e-15)


@pytest.mark.skipif(not os.path.exists(RAW), reason="the real CinemaDNG is not here")
@pytest.mark.parametrize("cmd", [["analyze", RAW], ["white-balance", RAW, "OUT.tif", "--quiet"]])
def test_cli_imports_neither_colour_science_nor_pydantic_settings_nor_scipy_ndimage(cmd, tmp_path):
    cmd = [str(tmp_path / c) if c == "OUT.tif" else c for c in cmd]
    code = ("import sys\nfrom service.cli import main\nrc = main(%r)\n"
            "assert 'colour' not in sys.modules, 'colour-science was imported'\n"
            "assert 'pydantic_settings' not in sys.modules, 'pydantic-settings was imported'\n"
            "assert 'scipy.ndimage' not in sys.modules, 'scipy.ndimage was imported'\nsys.exit(rc)" % (cmd,))
    env = {k: v for k, v in os.environ.items() if not k.upper().startswith("WANDELL_")}
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr[-2000:]


def test_cli_default_limits_are_the_settings_defaults(monkeypatch):
    """The CLI's settings without any ``WANDELL_*`` variable (read without
    pydantic-settings, issue 19) are the service's embedded defaults; with
    one set, they are the service's settings."""
    from service import cli
    from service.settings import Settings, get_settings

    for k in list(os.environ):
        if k.upper().startswith("WANDELL_"):
            monkeypatch.delenv(k)
    fast = cli._settings()
    assert isinstance(fast, cli._DefaultLimits)
    full = Settings()
    for f in dataclasses_fields(fast):
        assert getattr(fast, f) == getattr(full, f), f
    monkeypatch.setenv("wandell_estimation_pixels", "5000")
    get_settings.cache_clear()
    try:
        assert cli._settings().estimation_pixels == 5000
    finally:
        get_settings.cache_clear()


def dataclasses_fields(obj):
    import dataclasses

    return [f.name for f in dataclasses.fields(obj)]
