"""The request options, declared once (issue 18).

:mod:`service.schemas.fields` declares every option as plain data (type,
default, description, accepted values, examples, check), grouped by concern
(estimation, rendering and output, regions, the preview, batches);
:mod:`service.schemas.options` builds one pydantic model per concern from
them. The REST form fields and query parameters (:mod:`service.schemas.forms`), the batch options
(:class:`service.jobs.BatchOptions` is
:class:`~service.schemas.options.BatchOptions`), the CLI flags
(:mod:`service.schemas.cli`, from the declarations: ``wandell --help``
loads no pydantic) and the README's options table
(:func:`~service.schemas.fields.options_table`) are derived from them, so
``/docs``, ``wandell --help`` and the README agree by construction.

The models are loaded on first use (PEP 562), so importing
``service.schemas.fields`` stays light.
"""

from __future__ import annotations

_MODELS = ("AnalyzeEstimation", "BatchOptions", "Estimation", "Input", "Neutral", "Preview", "Regions", "Rendering",
           "Sampling", "SpectralRendering", "WhiteBalanceRendering")

__all__ = [*_MODELS, "options_table"]


def __getattr__(name: str):
    if name in _MODELS:
        from . import options

        return getattr(options, name)
    if name == "options_table":
        from .fields import options_table

        return options_table
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
