"""The request options, declared once (issue 18).

:mod:`service.schemas.options` holds one pydantic model per concern
(estimation, rendering and output, regions, the preview, batches): each
field's type, default, description, accepted values, examples and check.
The REST form fields (:mod:`service.schemas.forms`), the batch options
(:class:`service.jobs.BatchOptions` is :class:`~service.schemas.options.BatchOptions`),
the CLI flags (:mod:`service.schemas.cli`) and the README's options table
(:func:`~service.schemas.options.options_table`) are derived from them, so
``/docs``, ``wandell --help`` and the README agree by construction.

Importing this package loads pydantic but no numerical library (the CLI's
``--help`` stays light); the checks import what they need when they run.
"""

from .options import (AnalyzeEstimation, BatchOptions, Estimation, Neutral, Preview, Regions, Rendering,
                      WhiteBalanceRendering, options_table)

__all__ = ["Estimation", "AnalyzeEstimation", "Rendering", "WhiteBalanceRendering", "Neutral", "Regions",
           "Preview", "BatchOptions", "options_table"]
