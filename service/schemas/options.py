"""The options models, one per concern, built from the declarations of
:mod:`service.schemas.fields` (each field's type, default, description,
accepted values, examples and check, declared once there).

Every field runs its check on a given value (a request may narrow a field's
choices through the validation context ``{"choices": {name: (...)}}``, or
leave a check for later with ``{"lazy": (name, ...)}`` and
:meth:`OptionModel.check`); the :class:`~service.fields.Opt` of a field is
in its ``Annotated`` metadata (:func:`opt_of`), so the form fields
(:mod:`service.schemas.forms`) are derived from the models.

>>> Estimation(method="gray-world").estimate_kwargs()
{'white_level': 1.0, 'spatial': 'auto'}
>>> Estimation(method="magic")
Traceback (most recent call last):
...
service.errors.ServiceError: method 'magic' unknown; accepted: ['auto', 'learned', 'bayes', 'maloney-wandell', 'gray-world', 'white-patch', 'shades-of-gray', 'gray-edge']
"""

from __future__ import annotations

import json
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, create_model, field_validator

from .. import options as checks
from ..options import FORMATS
from .fields import (BATCH, ESTIMATION, INPUT, LIGHTING, NEUTRAL, PREVIEW, PREVIEW_MAX_SIDE, PREVIEW_SIDE_RANGE, REGIONS,
                     RENDERING, SPATIAL, SPECTRAL, WHITE_BALANCE, Opt, options_table, run_check)

__all__ = ["OptionModel", "Input", "Estimation", "AnalyzeEstimation", "Rendering", "WhiteBalanceRendering", "Neutral",
           "Regions", "Preview", "BatchOptions", "Sampling", "SpectralRendering", "LIGHTING", "PREVIEW_MAX_SIDE", "PREVIEW_SIDE_RANGE", "opt_of",
           "option_fields", "options_table"]


class OptionModel(BaseModel):
    """Base of the option models: a given value runs its field's check."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    @field_validator("*", mode="before")
    @classmethod
    def _check(cls, value, info: ValidationInfo):
        ctx = info.context or {}
        if info.field_name in ctx.get("lazy", ()):
            return value
        choices = (ctx.get("choices") or {}).get(info.field_name)
        return run_check(opt_of(cls, info.field_name), value, info.field_name, choices)

    def check(self, name: str, choices=None) -> Any:
        """Run field ``name``'s check now (one a request validated lazily,
        e.g. ``/v1/preview``'s target, which matters only for ``wb=corrected``)."""
        return run_check(opt_of(type(self), name), getattr(self, name), name, choices)

    def as_dict(self) -> dict:
        """The options as plain data (what batches store)."""
        return self.model_dump()


def opt_of(model, name: str) -> Opt:
    """The :class:`~service.schemas.fields.Opt` of ``model``'s field ``name``."""
    return next(m for m in model.model_fields[name].metadata if isinstance(m, Opt))


def option_fields(model) -> dict:
    """``name -> Opt`` of a model's fields, in declaration order."""
    return {n: opt_of(model, n) for n in model.model_fields}


def _model(name: str, base, doc: str, *groups):
    fields = {n: (Annotated[o.type, o], Field(o.default, description=o.description))
              for g in groups for n, o in g.items()}
    return create_model(name, __base__=base, __module__=__name__, __doc__=doc, **fields)


class _Estimating(OptionModel):
    def estimate_kwargs(self) -> dict:
        """Keyword options of :func:`recovery.estimate_illuminant`: one light
        or a light map decided from the image (``spatial="auto"``) unless the
        model has ``spatial``."""
        return checks.estimate_options(self.method, self.surface_dim, self.light_dim, self.region_size,
                                       getattr(self, "spatial", "auto"), self.surface_model, self.light_model,
                                       self.quality)


class _Batch(_Estimating):
    @property
    def extension(self) -> str:
        return FORMATS[self.format].extension

    def to_json(self) -> str:
        return json.dumps(self.as_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str):
        """Stored options (validated when they were stored: not checked again)."""
        return cls.model_construct(**json.loads(text))


Input = _model("Input", OptionModel, "What is done with a display-referred upload (service.decode.icc).", INPUT)
Estimation = _model("Estimation", _Estimating, "How the light is estimated (every endpoint that estimates, batches, "
                    "the CLI).", ESTIMATION)
AnalyzeEstimation = _model("AnalyzeEstimation", Estimation, "``/v1/analyze``, ``/v1/white-balance``, "
                           "``/v1/surfaces`` and ``/v1/preview``: the estimation options and one light or a light "
                           "map.", SPATIAL)
Rendering = _model("Rendering", OptionModel, "How the corrected image is rendered and written.", RENDERING)
WhiteBalanceRendering = _model("WhiteBalanceRendering", Rendering, "``/v1/white-balance``: also the white "
                               "rendered and the kind of answer.", WHITE_BALANCE)
Neutral = _model("Neutral", OptionModel, "A surface the user says is white.", NEUTRAL)
Regions = _model("Regions", OptionModel, "Where ``/v1/surfaces`` recovers reflectances, and how it answers.",
                 REGIONS)
Preview = _model("Preview", OptionModel, "What ``/v1/preview`` shows.", PREVIEW)
BatchOptions = _model("BatchOptions", _Batch, "The options of a batch (``POST /v1/batches``, ``wandell "
                      "batch``): estimation, rendering and the lighting mode; stored with the batch and beside "
                      "each output (``to_json``).", ESTIMATION, RENDERING, BATCH)
SpectralRendering = _model("SpectralRendering", OptionModel, "``/v1/render``: the wavelength sampling, the light "
                           "and the output of spectral data.", SPECTRAL)
Sampling = _model("Sampling", OptionModel, "``GET /v1/sampling``: a sampling rule, its order and the light it is "
                  "made for (the fields of :data:`SPECTRAL` that name a rule).",
                  {k: SPECTRAL[k] for k in ("strategy", "n", "channel", "degrees", "illuminant")})
