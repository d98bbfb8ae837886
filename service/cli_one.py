"""The commands that read one file and print what the service would answer for it: ``wandell analyze``
(the light, as ``POST /v1/analyze``) and ``wandell surfaces`` (reflectances, as ``POST /v1/surfaces``)."""

from __future__ import annotations

import json
import sys

from . import jobs
from .cli import _options, _settings, term_safe
from .cli_paths import input_file
from .errors import service_error
from .schemas.fields import ESTIMATION, REGIONS

__all__ = ["cmd_analyze", "cmd_surfaces"]


def _analysed(args, opts, settings, then=None):
    """The file of ``args`` decoded and its light estimated (``then(decoded, run)`` after, if given), or
    ``None`` with ``error: CODE: DETAIL`` on stderr when the file or an option is bad (exit status 1)."""
    from . import pipeline

    try:
        decoded, run = pipeline.analyze_file(args.file, settings, camera=opts.camera, method=opts.method,
                                             options=opts.estimate_kwargs())
        return then(decoded, run) if then else (decoded, run)
    except Exception as e:  # noqa: BLE001 - a bad file or option: say what, exit 1
        err = service_error(e)
        if err is None:
            raise
        print(f"error: {err.code}: {term_safe(err.detail)}", file=sys.stderr)
        return None


def cmd_analyze(args) -> int:
    from . import pipeline
    from .jsonsafe import clean

    input_file(args.file)
    opts = _options(args)
    got = _analysed(args, opts, _settings())
    if got is None:
        return 1
    decoded, run = got
    print(json.dumps(clean(pipeline.analysis_json(run, decoded)), indent=1))
    return 0


def cmd_surfaces(args) -> int:
    """Reflectances at points, rectangles or a grid of one file, as ``POST
    /v1/surfaces`` answers them (the same answer, limits and errors), JSON or
    CSV on stdout."""
    from .jsonsafe import clean
    from .schemas.options import Regions
    from .surfaces import regions_of, surfaces_answer, surfaces_csv

    input_file(args.file)
    opts = jobs.batch_options(**{n: getattr(args, n, None) for n in ESTIMATION})   # --format is the answer's
    regions = Regions(**{n: getattr(args, n) for n in REGIONS if getattr(args, n, None) is not None})
    settings = _settings()
    where = regions_of(regions, settings.max_surface_regions)        # a usage error before the file is decoded
    res = _analysed(args, opts, settings,
                    lambda decoded, run: surfaces_answer(decoded, run, regions, where, opts.estimate_kwargs()))
    if res is None:
        return 1
    if regions.format == "csv":
        sys.stdout.write(surfaces_csv(res))
    else:
        print(json.dumps(clean(res), indent=1))
    return 0
