"""Write ``models/data/colour_cache.npz``: what the CLI and the service take
from colour-science on every image, computed by colour-science now (issue 19:
start-up without importing it). ``tests/test_colour_cache.py`` checks the
shipped file against colour-science entry by entry.

    python -m benchmarks.build_colour_cache [RAW ...]

Besides the defaults of :func:`models._colour.build` and what ``recovery``
and ``service`` call on every image (:func:`_record_above_models`), every call the CLI's
``analyze`` and ``white-balance`` (TIFF, PNG, JPEG) make on each RAW is
recorded (default: the real CinemaDNG of ``shared/data/raw``), so the
arguments are exactly those of the hot path.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import tempfile

from models import _colour

DEFAULT_RAWS = [os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "raw", "Blackmagic.dng"),
                "/work/shared/data/raw/Blackmagic.dng"]


def _run_cli(raws):
    from service import cli

    with tempfile.TemporaryDirectory() as tmp, contextlib.redirect_stdout(io.StringIO()):
        for raw in raws:
            assert cli.main(["analyze", raw]) == 0, raw
            for ext in ("tif", "png", "jpg"):
                assert cli.main(["white-balance", raw, os.path.join(tmp, f"out.{ext}"), "--quiet"]) == 0, raw


def _record_above_models() -> None:
    """What the packages above :mod:`models` call on every image: the light
    posterior's default candidates and both loci of its plausible spectrum
    (Planckian: 480 blackbodies), and the service's display-encoding tables.
    (Moved here from ``models._colour``, which imports neither ``recovery``
    nor ``service``: issue 29.)"""
    from models import DEFAULT_WAVELENGTHS
    from recovery.bayes import _locus
    from recovery.illuminant_prior import default_candidates
    from service import correction

    default_candidates()
    _locus.cache_clear()
    for kind in ("daylight", "planckian"):
        _locus(kind, tuple(DEFAULT_WAVELENGTHS.tolist()))
    for bits in (8, 16):
        for curve in (None, "libraw"):
            correction._encoding_lut("sRGB", bits, curve)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    raws = argv or [next((p for p in DEFAULT_RAWS if os.path.exists(p)), DEFAULT_RAWS[-1])]
    rec = _colour.build(extra=lambda: (_record_above_models(), _run_cli(raws)))
    print(f"{_colour.CACHE_FILE}: {len(rec)} entries, {_colour.CACHE_FILE.stat().st_size} bytes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
