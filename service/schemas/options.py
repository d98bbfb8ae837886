"""One typed options model per concern, each field declared once.

A field is ``name: Annotated[type, Opt(...)] = Field(default, description=...)``:
:class:`Opt` carries what pydantic's ``Field`` does not: the accepted values
(``choices``; a request may narrow them, e.g. ``/v1/preview``'s 8-bit
formats), the examples ``/docs`` shows in the description (never as values
Swagger UI would send, :mod:`service.openapi_docs`), the type and default
the value has on the wire (a form field or a CLI flag: ``exposure`` is the
text ``auto`` or a number there, ``None`` or EV here) and the check. The
checks are :mod:`service.options`' functions: a bad value is a
:class:`~service.errors.ServiceError` (422 ``invalid_parameter`` naming
what is accepted), raised as is through pydantic (which wraps only
``ValueError`` and ``AssertionError``), so the REST answer stays
``{"error", "detail"}`` and the CLI's ``error: invalid_parameter: ...``.

>>> Estimation(method="gray-world").estimate_kwargs()
{'white_level': 1.0, 'spatial': False}
>>> Estimation(method="magic")
Traceback (most recent call last):
...
service.errors.ServiceError: method 'magic' unknown; accepted: ['auto', 'learned', 'bayes', 'maloney-wandell', 'gray-world', 'white-patch', 'shades-of-gray', 'gray-edge']
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Annotated, Any, Callable

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from recovery.methods import METHOD_NAMES, QUALITY_NAMES

from .. import options as checks
from ..errors import ServiceError
from ..options import FORMATS, IMAGE_FORMATS, LIGHT_MODELS, OUTPUTS, SURFACE_MODELS

__all__ = ["Opt", "OptionModel", "Estimation", "AnalyzeEstimation", "Rendering", "WhiteBalanceRendering",
           "Neutral", "Regions", "Preview", "BatchOptions", "LIGHTING", "option_fields", "options_table"]

#: Lighting modes of a batch.
LIGHTING = ("per-image", "shared")
_UNSET = object()


@dataclass(frozen=True)
class Opt:
    """What a field is besides its type, default and description.

    ``choices``: the accepted values (listed in ``/docs``, ``--help`` and the
    README); ``examples``: shown in the description; ``wire``/``wire_default``:
    the type and default of the form field and CLI flag when they differ from
    the model's; ``check(value, name, choices)``: validates (and may convert)
    a given value, raising :class:`~service.errors.ServiceError`; without one,
    a value outside ``choices`` is refused by name; ``cli``: the field is a
    CLI flag; ``metavar``: its placeholder there; ``summary``: the README
    table's text when the description's first clause is not short."""

    choices: tuple | None = None
    examples: tuple = ()
    wire: Any = None
    wire_default: Any = _UNSET
    check: Callable | None = None
    cli: bool = True
    metavar: str | None = None
    summary: str | None = None


def _choice(value, name: str, choices) -> Any:
    if value is not None and choices and value not in choices:
        raise ServiceError(422, "invalid_parameter", f"{name} {value!r} unknown; accepted: {list(choices)}")
    return value


class OptionModel(BaseModel):
    """Base of the option models: every field runs its :class:`Opt` check
    on a given value (a request may narrow a field's choices through the
    validation context ``{"choices": {name: (...)}}``, or leave a check for
    later with ``{"lazy": (name, ...)}`` and :meth:`check`)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    @field_validator("*", mode="before")
    @classmethod
    def _check(cls, value, info: ValidationInfo):
        ctx = info.context or {}
        if info.field_name in ctx.get("lazy", ()):
            return value
        opt = opt_of(cls, info.field_name)
        choices = (ctx.get("choices") or {}).get(info.field_name, opt.choices)
        return (opt.check or _choice)(value, info.field_name, choices)

    def check(self, name: str, choices=None) -> Any:
        """Run field ``name``'s check now (one a request validated lazily,
        e.g. ``/v1/preview``'s target, which matters only for ``wb=corrected``)."""
        opt = opt_of(type(self), name)
        return (opt.check or _choice)(getattr(self, name), name, choices or opt.choices)

    def as_dict(self) -> dict:
        """The options as plain data (what batches store)."""
        return self.model_dump()


def opt_of(model, name: str) -> Opt:
    """The :class:`Opt` of ``model``'s field ``name`` (an empty one when it has none)."""
    return next((m for m in model.model_fields[name].metadata if isinstance(m, Opt)), Opt())


def option_fields(model) -> dict:
    """``name -> (FieldInfo, Opt)`` of a model's fields, in declaration order."""
    return {n: (f, opt_of(model, n)) for n, f in model.model_fields.items()}


# --------------------------------------------------------------------------- checks
def _dim(value, name, choices):
    checks.check_dim(value, name)
    return None if value is None or value == "" else str(value)


def _region_size(value, name, choices):
    checks.check_region_size(value)
    return value


def _spatial(value, name, choices):
    checks.check_spatial(value)
    return value


def _target(value, name, choices):
    return checks.check_target(value)


def _output(value, name, choices):
    return checks.check_output(value, choices or OUTPUTS)


def _format(value, name, choices):
    checks.choose_format(value, choices or tuple(FORMATS))
    return value


def _exposure(value, name, choices):
    return checks.parse_exposure(value)


def _neutral(value, name, choices):
    return checks.parse_neutral(value)


def _json_list(width):
    def parse(value, name, choices):
        return checks.parse_json_list(value, name, width) if isinstance(value, str) or value is None else value
    return parse


def _grid(value, name, choices):
    return checks.parse_grid(value) if isinstance(value, str) or value is None else tuple(value)


def _must_be(text: str):
    def check(value, name, choices):
        if value not in choices:
            raise ServiceError(422, "invalid_parameter", text.format(name=name, value=value))
        return value
    return check


# --------------------------------------------------------------------------- estimation
class Estimation(OptionModel):
    """How the light is estimated (:func:`recovery.estimate_illuminant`):
    every endpoint that estimates, batches and the CLI."""

    camera: Annotated[str | None, Opt(examples=("matrix", "generic", "Nikon 5100 (NPL)"))] = Field(
        None, description="measured camera name (see GET /v1/cameras), 'matrix' (the file's colour matrix) or "
                          "'generic'; default: from the file")
    method: Annotated[str, Opt(choices=METHOD_NAMES, examples=("auto", "maloney-wandell"))] = Field(
        "auto", description="the estimator: auto (the learnt estimator, the light posterior as its fallback), "
                            "learned, bayes (the light posterior), maloney-wandell (the literal subspace method) "
                            "or a classical peer; GET /v1/models describes each")
    quality: Annotated[str | None, Opt(choices=QUALITY_NAMES, examples=("balanced",))] = Field(
        None, description="speed/accuracy preset (the measured trade-off); default: neither")
    surface_dim: Annotated[str | None, Opt(examples=("2", "auto"), check=_dim)] = Field(
        None, description="surface model terms D(S): 1..C-1, or auto (BIC)")
    light_dim: Annotated[str | None, Opt(examples=("3", "auto"), check=_dim)] = Field(
        None, description="light model terms D(E): 1..D(S)+1, or auto (BIC)")
    region_size: Annotated[int | None, Opt(examples=(64,), check=_region_size)] = Field(
        None, description="region side in pixels for a light map, 8..100000 (default: a quarter of the shorter "
                          "side)")
    surface_model: Annotated[str | None, Opt(choices=SURFACE_MODELS, examples=("pca",))] = Field(
        None, description="surface reflectance basis")
    light_model: Annotated[str | None, Opt(choices=LIGHT_MODELS, examples=("daylight",))] = Field(
        None, description="light spectrum basis")

    def estimate_kwargs(self) -> dict:
        """Keyword options of :func:`recovery.estimate_illuminant`: one light
        (``spatial=False``) unless the model has ``spatial``."""
        return checks.estimate_options(self.method, self.surface_dim, self.light_dim, self.region_size,
                                       getattr(self, "spatial", False), self.surface_model, self.light_model,
                                       self.quality)


class AnalyzeEstimation(Estimation):
    """``/v1/analyze`` also decides between one light and a light map."""

    spatial: Annotated[str | None, Opt(choices=("auto", "true", "false"), examples=("auto",), check=_spatial,
                                       cli=False)] = Field(
        None, description="auto (decide from the image), true (a light map) or false (one light)")


# --------------------------------------------------------------------------- rendering and output
class Rendering(OptionModel):
    """How the corrected image is rendered and written."""

    target: Annotated[str, Opt(examples=("D65", "estimate", "D5000"), check=_target)] = Field(
        "D65", description="light to render under: a CIE illuminant name, D<cct> (4000..25000 K) or BB<K> "
                           "(1000..25000 K), or estimate (as seen)")
    output: Annotated[str, Opt(choices=OUTPUTS, examples=("sRGB",), check=_output)] = Field(
        "sRGB", description="output space or display")
    format: Annotated[str, Opt(choices=IMAGE_FORMATS, examples=("tiff", "png16"), check=_format)] = Field(
        "tiff", description="tiff (16-bit), png (8-bit), png16, jpeg")
    exposure: Annotated[float | None, Opt(wire=str, wire_default="auto", examples=("auto", "1.5"),
                                          check=_exposure, metavar="EV|auto",
                                          summary="EV over LibRaw's auto-brightness base, or auto (that rule)")] = Field(
        None, description=checks.EXPOSURE_HELP)


class WhiteBalanceRendering(Rendering):
    """``/v1/white-balance`` also answers a Camera Raw sidecar or JSON, and
    renders the file's own white for comparison."""

    white: Annotated[str, Opt(choices=("estimate", "as-shot"), examples=("estimate",),
                              check=_must_be("{name} must be estimate or as-shot, not {value!r}"))] = Field(
        "estimate", description="estimate (this service's light, or neutral) or as-shot (the camera's own white, "
                                "rendered the same way, to compare)")
    response: Annotated[str, Opt(choices=("image", "json"), examples=("image",),
                                 check=_must_be("{name} must be image or json"))] = Field(
        "image", description="image, or json for the estimate and correction matrix only")


# --------------------------------------------------------------------------- regions
class Neutral(OptionModel):
    """A surface the user says is white."""

    neutral: Annotated[list[int] | None, Opt(wire=str | None, wire_default=None,
                                             examples=("[1200, 2040]", "[100, 200, 140, 260]"),
                                             check=_neutral,
                                             summary="a surface to use as white: JSON [row, col] or [r0, c0, "
                                                     "r1, c1] in full-resolution pixels")] = Field(
        None, description=checks.NEUTRAL_HELP)


class Regions(OptionModel):
    """Where ``/v1/surfaces`` recovers reflectances, and how it answers."""

    points: Annotated[list | None, Opt(wire=str | None, wire_default=None, examples=("[[100, 200], [300, 400]]",),
                                       check=_json_list(2))] = Field(
        None, description="JSON [[row, col], ...] in full-resolution pixels")
    rects: Annotated[list | None, Opt(wire=str | None, wire_default=None, examples=("[[0, 0, 50, 80]]",),
                                      check=_json_list(4))] = Field(
        None, description="JSON [[r0, c0, r1, c1], ...] (end exclusive)")
    grid: Annotated[tuple[int, int] | None, Opt(wire=str | None, wire_default=None, examples=("8x6",),
                                                check=_grid)] = Field(
        None, description="a coarse grid, rows x columns")
    format: Annotated[str, Opt(choices=("json", "csv"), check=_must_be("{name} must be json or csv"))] = Field(
        "json", description="json or csv")


# --------------------------------------------------------------------------- preview
#: Longest side of a preview, default and accepted range (pixels).
PREVIEW_MAX_SIDE = 1024
PREVIEW_SIDE_RANGE = (16, 4096)


def _max_side(value, name, choices):
    lo, hi = PREVIEW_SIDE_RANGE
    if not lo <= value <= hi:
        raise ServiceError(422, "invalid_parameter", f"max_side must be in {lo}..{hi} pixels, not {value}")
    return value


class Preview(OptionModel):
    """What ``/v1/preview`` shows."""

    wb: Annotated[str, Opt(choices=("camera", "corrected"), examples=("corrected",),
                           check=_must_be("{name} must be camera or corrected, not {value!r}"))] = Field(
        "camera", description="camera: the file's own as-shot white balance as LibRaw renders it (the original); "
                              "corrected: this service's correction, the same matrix as /v1/white-balance")
    max_side: Annotated[int, Opt(examples=(PREVIEW_MAX_SIDE,), check=_max_side)] = Field(
        PREVIEW_MAX_SIDE, description=f"longest side of the preview, {PREVIEW_SIDE_RANGE[0]}.."
                                      f"{PREVIEW_SIDE_RANGE[1]} pixels")


# --------------------------------------------------------------------------- batches
class BatchOptions(Estimation, Rendering):
    """The options of a batch (``POST /v1/batches``, ``wandell batch``):
    estimation, rendering and the lighting mode; stored with the batch and
    beside each output (:meth:`to_json`)."""

    lighting: Annotated[str, Opt(choices=LIGHTING, examples=("per-image",))] = Field(
        "per-image", description="per-image, or shared: one light estimated from all the images together")

    @property
    def extension(self) -> str:
        return FORMATS[self.format].extension

    def to_json(self) -> str:
        return json.dumps(self.as_dict(), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "BatchOptions":
        """Stored options (validated when they were stored: not checked again)."""
        return cls.model_construct(**json.loads(text))


# --------------------------------------------------------------------------- the README's table
#: The concerns in the README's options table, in order.
CONCERNS = (("estimation", AnalyzeEstimation), ("rendering", WhiteBalanceRendering), ("regions", Neutral),
            ("regions", Regions), ("preview", Preview), ("batches", BatchOptions))


def _cell(value) -> str:
    return "" if value is None else f"`{value}`"


def options_table() -> str:
    """The README's options table (markdown), from the models: option,
    concern, default, accepted values. ``tests/test_options_agree.py``
    checks that the README holds it as written here."""
    rows = ["| option | concern | default | accepted |", "|---|---|---|---|"]
    seen = set()
    for concern, model in CONCERNS:
        for name, (f, opt) in option_fields(model).items():
            label = name if not (model is Regions and name == "format") else "format (surfaces)"
            if label in seen:
                continue
            seen.add(label)
            default = f.default if opt.wire_default is _UNSET else opt.wire_default
            accepted = (", ".join(f"`{c}`" for c in opt.choices) if opt.choices
                        else (opt.summary or f.description.split(";")[0]).replace("|", "/").replace("<", "&lt;"))
            rows.append(f"| `{label}` | {concern} | {_cell(default)} | {accepted} |")
    return "\n".join(rows)
