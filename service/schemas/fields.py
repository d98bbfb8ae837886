"""Every request option, declared once, as plain data (no pydantic here).

A field is an :class:`Opt`: its type, default, description, accepted values
(``choices``; a request may narrow them, e.g. ``/v1/preview``'s 8-bit
formats), the examples ``/docs`` shows in the description (never as values
Swagger UI would send, :mod:`service.openapi_docs`), the type and default
it has on the wire (a form field or a CLI flag: ``exposure`` is the text
``auto`` or a number there, ``None`` or EV in the model) and its check.
The fields are grouped by concern (:data:`ESTIMATION`, :data:`RENDERING`,
...); :mod:`service.schemas.options` builds the pydantic models from the
groups, :mod:`service.schemas.cli` the CLI flags (without loading pydantic:
``wandell --help`` stays light).

The checks are :mod:`service.options`' functions: a bad value is a
:class:`~service.errors.ServiceError` (422 ``invalid_parameter`` naming what
is accepted), raised as is through pydantic (which wraps only
``ValueError`` and ``AssertionError``), so the REST answer stays
``{"error", "detail"}`` and the CLI's ``error: invalid_parameter: ...``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

from recovery.methods import METHOD_NAMES, QUALITY_NAMES

from .. import options as checks
from ..errors import ServiceError
from ..options import BATCH_FORMATS, FORMATS, IMAGE_FORMATS, LIGHT_MODELS, OUTPUTS, SURFACE_MODELS
from ..white import WHITE_HELP, check_white

__all__ = ["Opt", "INPUT", "ESTIMATION", "SPATIAL", "RENDERING", "WHITE_BALANCE", "NEUTRAL", "REGIONS", "PREVIEW",
           "BATCH", "SIDECAR", "XMP_NAMES", "SPECTRAL", "LIGHTING", "CONCERNS", "PREVIEW_MAX_SIDE",
           "PREVIEW_SIDE_RANGE", "run_check"]

#: Lighting modes of a batch.
LIGHTING = ("per-image", "shared")
#: Longest side of a preview, default and accepted range (pixels).
PREVIEW_MAX_SIDE = 1024
PREVIEW_SIDE_RANGE = (16, 4096)
_UNSET = object()


@dataclass(frozen=True)
class Opt:
    """One option: ``type``, ``default`` and ``description`` (what the model
    field has); ``choices``: the accepted values (listed in ``/docs``,
    ``--help`` and the README); ``examples``: shown in the description;
    ``wire``/``wire_default``: the type and default of the form field and
    CLI flag when they differ from the model's; ``check(value, name,
    choices)``: validates (and may convert) a given value, raising
    :class:`~service.errors.ServiceError`; without one, a value outside
    ``choices`` is refused by name; ``cli``: the option is a CLI flag;
    ``metavar``: its placeholder there; ``summary``: the README table's text
    when the description's first clause is not short; ``const``: the flag's
    value when given without one (an optional value, argparse
    ``nargs="?"``). A ``bool`` option is a switch (``store_true``)."""

    type: Any
    default: Any
    description: str
    choices: tuple | None = None
    examples: tuple = ()
    wire: Any = None
    wire_default: Any = _UNSET
    check: Callable | None = None
    cli: bool = True
    metavar: str | None = None
    summary: str | None = None
    const: Any = _UNSET

    @property
    def wire_type(self):
        """The type of the form field and CLI flag."""
        return self.wire if self.wire is not None else self.type

    @property
    def given_default(self):
        """The default of the form field and CLI flag."""
        return self.default if self.wire_default is _UNSET else self.wire_default


def run_check(opt: Opt, value, name: str, choices=None):
    """``opt``'s check of ``value`` (a value outside the choices refused by name)."""
    choices = opt.choices if choices is None else choices
    if opt.check is not None:
        return opt.check(value, name, choices)
    if value is not None and choices and value not in choices:
        raise ServiceError(422, "invalid_parameter", f"{name} {value!r} unknown; accepted: {list(choices)}")
    return value


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


def _max_side(value, name, choices):
    lo, hi = PREVIEW_SIDE_RANGE
    if not lo <= value <= hi:
        raise ServiceError(422, "invalid_parameter", f"max_side must be in {lo}..{hi} pixels, not {value}")
    return value


# --------------------------------------------------------------------------- input
#: What is done with an upload whose colour tags say it is display-referred
#: (:mod:`service.decode.icc`): ``/v1/analyze``, ``/v1/white-balance`` and
#: ``/v1/surfaces``; the preview, batches and the CLI always linearise (and say so).
INPUT = {
    "display_referred": Opt(str, "linearise", "a TIFF/PNG whose ICC profile (or PNG sRGB/gAMA chunk) says it is "
                                              "display-referred (gamma-encoded, rendered): linearise (through "
                                              "its own tone curve, with a warning naming the profile) or refuse "
                                              "(415 display_referred_input)",
                            choices=("linearise", "refuse"), examples=("linearise",),
                            check=_must_be("{name} must be linearise or refuse, not {value!r}"), cli=False,
                            summary="a display-referred TIFF/PNG (by its ICC profile or PNG chunks): "
                                    "linearise through its own tone curve, or refuse"),
}

# --------------------------------------------------------------------------- estimation
#: How the light is estimated (:func:`recovery.estimate_illuminant`): every
#: endpoint that estimates, batches and the CLI.
ESTIMATION = {
    "camera": Opt(str | None, None, "measured camera name (see GET /v1/cameras), 'matrix' (the file's colour "
                                    "matrix) or 'generic'; default: from the file",
                  examples=("matrix", "generic", "Nikon 5100 (NPL)")),
    "method": Opt(str, "auto", "the estimator: auto (the learnt estimator, the light posterior as its fallback), "
                               "learned, bayes (the light posterior), maloney-wandell (the literal subspace "
                               "method) or a classical peer; GET /v1/models describes each",
                  choices=METHOD_NAMES, examples=("auto", "maloney-wandell")),
    "quality": Opt(str | None, None, "speed/accuracy preset (the measured trade-off); a RAW's demosaic too: "
                                     "fast = OpenCV's bilinear, otherwise RCD; default: neither",
                   choices=QUALITY_NAMES, examples=("balanced",)),
    "surface_dim": Opt(str | None, None, "surface model terms D(S): 1..C-1, or auto (BIC)",
                       examples=("2", "auto"), check=_dim),
    "light_dim": Opt(str | None, None, "light model terms D(E): 1..D(S)+1, or auto (BIC)",
                     examples=("3", "auto"), check=_dim),
    "region_size": Opt(int | None, None, "region side in pixels for a light map, 8..100000 (default: a quarter "
                                         "of the shorter side)", examples=(64,), check=_region_size),
    "surface_model": Opt(str | None, None, "surface reflectance basis; on /v1/surfaces naming one selects the "
                                           "literal method (eq. 36, pseudo-inverse in that basis, no band) instead "
                                           "of the prior over measured surfaces", choices=SURFACE_MODELS,
                         examples=("pca",)),
    "light_model": Opt(str | None, None, "light spectrum basis", choices=LIGHT_MODELS, examples=("daylight",)),
}
#: ``/v1/analyze`` also decides between one light and a light map.
SPATIAL = {
    "spatial": Opt(str | None, None, "auto (decide from the image), true (a light map) or false (one light)",
                   choices=("auto", "true", "false"), examples=("auto",), check=_spatial, cli=False),
}

# --------------------------------------------------------------------------- rendering and output
#: How the corrected image is rendered and written.
RENDERING = {
    "target": Opt(str, "D65", "light to render under: a CIE illuminant name, D<cct> (4000..25000 K) or BB<K> "
                              "(1000..25000 K), or estimate (as seen)",
                  examples=("D65", "estimate", "D5000"), check=_target),
    "output": Opt(str, "sRGB", "output space or display", choices=OUTPUTS, examples=("sRGB",), check=_output),
    "format": Opt(str, "tiff", "tiff (16-bit), png (8-bit), png16, jpeg", choices=IMAGE_FORMATS,
                  examples=("tiff", "png16"), check=_format),
    "exposure": Opt(float | None, None, checks.EXPOSURE_HELP, wire=str, wire_default="auto",
                    examples=("auto", "1.5"), check=_exposure, metavar="EV|auto",
                    summary="EV over LibRaw's auto-brightness base, or auto (that rule)"),
}
#: ``/v1/white-balance`` also answers a Camera Raw sidecar or JSON, and
#: renders the file's own white for comparison.
WHITE_BALANCE = {
    "white": Opt(str, "estimate", WHITE_HELP, examples=("estimate", "as-shot", "5200/+10"), check=check_white,
                 summary="estimate, as-shot, or TEMPERATURE/TINT on Camera Raw's scale (e.g. 5200/+10)"),
    "response": Opt(str, "image", "image, or json for the estimate and correction matrix only",
                    choices=("image", "json"), examples=("image",), check=_must_be("{name} must be image or json")),
}

# --------------------------------------------------------------------------- regions
#: A surface the user says is white.
NEUTRAL = {
    "neutral": Opt(list | None, None, checks.NEUTRAL_HELP, wire=str | None, wire_default=None,
                   examples=("[1200, 2040]", "[100, 200, 140, 260]", "[[1200, 2040], [1500, 800, 1540, 860]]"),
                   check=_neutral,
                   summary="a surface to use as white: JSON [row, col] or [r0, c0, r1, c1] in full-resolution "
                           "pixels, or a list of up to 16 such picks (averaged)"),
}
#: Where ``/v1/surfaces`` recovers reflectances, and how it answers.
REGIONS = {
    "points": Opt(list | None, None, "JSON [[row, col], ...] in full-resolution pixels", wire=str | None,
                  wire_default=None, examples=("[[100, 200], [300, 400]]",), check=_json_list(2)),
    "rects": Opt(list | None, None, "JSON [[r0, c0, r1, c1], ...] (end exclusive)", wire=str | None,
                 wire_default=None, examples=("[[0, 0, 50, 80]]",), check=_json_list(4)),
    "grid": Opt(tuple[int, int] | None, None, "a coarse grid, rows x columns", wire=str | None, wire_default=None,
                examples=("8x6",), check=_grid),
    "format": Opt(str, "json", "json or csv", choices=("json", "csv"), check=_must_be("{name} must be json or csv")),
    "metamers": Opt(bool, False, "also each surface's metamer set (metamer_lower, metamer_upper, metamer_slack): "
                                 "the least and greatest reflectance at each wavelength of any physical reflectance "
                                 "giving its response, about 90 ms per surface, at most 64 per request"),
    "metamer_model": Opt(str, "physical", "with metamers=true, which reflectances the metamer set holds: physical "
                                          "(any in [0, 1]) or measured (only those like measured surfaces: a "
                                          "narrower range; docs/surfaces.md)",
                         choices=("physical", "measured"), examples=("measured",),
                         check=_must_be("{name} must be physical or measured, not {value!r}")),
}

# --------------------------------------------------------------------------- preview
#: What ``/v1/preview`` shows.
PREVIEW = {
    "wb": Opt(str, "camera", "camera: the file's own as-shot white balance as LibRaw renders it (the original); "
                             "corrected: this service's correction, the same matrix as /v1/white-balance",
              choices=("camera", "corrected"), examples=("corrected",),
              check=_must_be("{name} must be camera or corrected, not {value!r}")),
    "max_side": Opt(int, PREVIEW_MAX_SIDE, f"longest side of the preview, {PREVIEW_SIDE_RANGE[0]}.."
                                           f"{PREVIEW_SIDE_RANGE[1]} pixels",
                    examples=(PREVIEW_MAX_SIDE,), check=_max_side),
}

# --------------------------------------------------------------------------- spectral rendering
def _wavelengths(value, name, choices):
    checks.parse_wavelengths(value, name)
    return value


def _strategy(value, name, choices):
    checks.rule_options(value, None, None, None)
    return value


def _n(value, name, choices):
    checks.rule_options("auto", value, None, None)
    return value


def _channel(value, name, choices):
    checks.rule_options("auto", None, value, None)
    return value


def _degrees(value, name, choices):
    checks.parse_degrees(value)
    return value


def _max_error(value, name, choices):
    import math

    if not (math.isfinite(value) and 0 < value <= 100):
        raise ServiceError(422, "invalid_parameter", "max_error must be in (0, 100]")
    return value


#: ``/v1/render``: the wavelength sampling of spectral data and the light,
#: with the output fields of :data:`RENDERING` and :data:`WHITE_BALANCE`.
SPECTRAL = {
    "wavelengths": Opt(str | None, None, "the cube's wavelengths in nm, comma-separated, strictly increasing; "
                                         "required for .npy", examples=("400,410,420,430,440,450,460,470,480,490,500",),
                       check=_wavelengths, cli=False),
    "illuminant": Opt(str | None, None, "light name (D65, A, FL11, D5000, BB3200...); default D65",
                      examples=("D65", "A"), cli=False),
    "strategy": Opt(str, "auto", "a sampling rule (GET /v1/sampling lists them), auto or full",
                    examples=("auto", "full"), check=_strategy, cli=False),
    "n": Opt(int | None, None, f"number of samples, 1..{checks.MAX_N}", examples=(8,), check=_n, cli=False),
    "channel": Opt(str | None, None, "gauss-ac1c2: A, C1, C2 or XYZ (Meyer's 4-wavelength rule)",
                   choices=("A", "C1", "C2", "XYZ"), examples=("XYZ",), check=_channel, cli=False),
    "degrees": Opt(str | None, None, "quasi-gauss-xyz: Borges' degree sequence for x, y, z, each 0..12",
                   examples=("2,2,2",), check=_degrees, cli=False),
    "format": RENDERING["format"],
    "output": RENDERING["output"],
    "adapt": Opt(bool, False, "CAT02 to the display white (off: the colour signal as is)", cli=False),
    "max_error": Opt(float, 1.0, "auto: bound on the mean CIEDE2000 against the full calculation, in (0, 100]",
                     examples=(1.0,), check=_max_error, cli=False),
    "response": WHITE_BALANCE["response"],
}

# --------------------------------------------------------------------------- batches
#: A batch: estimation, rendering and the lighting mode; its ``format`` (which
#: replaces :data:`RENDERING`'s in the model) also takes ``dng``: each RAW as a
#: DNG with its white balance inside, as ``/v1/white-balance format=dng``. Not a
#: flag of its own: ``wandell batch --format`` is :data:`RENDERING`'s flag, checked by this.
BATCH = {
    "lighting": Opt(str, "per-image", "per-image, or shared: one light estimated from all the images together",
                    choices=LIGHTING, examples=("per-image",)),
    "format": Opt(str, "tiff", "tiff (16-bit), png (8-bit), png16, jpeg, or dng: each RAW as a DNG with its "
                               "white balance inside (a DNG's copy, its raw data untouched; another RAW's raw data "
                               "written as a DNG; the same file POST /v1/white-balance format=dng answers), what "
                               "Lightroom reads for a DNG; a linear TIFF/PNG item fails (not_a_raw)",
                  choices=BATCH_FORMATS, examples=("tiff", "dng"), check=_format, cli=False),
}

# --------------------------------------------------------------------------- XMP sidecars (command line)
#: How a sidecar is named beside its RAW: ``stem`` IMG_0001.xmp (Lightroom,
#: Camera Raw, Capture One), ``full`` IMG_0001.dng.xmp (darktable, digiKam).
XMP_NAMES = ("stem", "full")
#: ``wandell white-balance`` and ``wandell batch``: Camera Raw XMP sidecars
#: beside the RAWs (no model: the server never writes beside an upload).
SIDECAR = {
    "xmp": Opt(bool, False, "also write a Camera Raw XMP sidecar (the estimate as Temperature/Tint) beside "
                            "the RAW, where editors look for it",
               summary="also write a Camera Raw XMP sidecar beside each RAW"),
    "xmp_dir": Opt(str | None, None, "write the XMP sidecars into DIR instead of beside the RAW (implies --xmp)",
                   metavar="DIR"),
    "xmp_name": Opt(str, "stem", "sidecar name: stem (IMG_0001.xmp, what Lightroom/Camera Raw read) or full "
                                 "(IMG_0001.dng.xmp, what darktable and digiKam read)",
                    choices=XMP_NAMES, examples=("stem",)),
    "xmp_overwrite": Opt(bool, False, "replace a sidecar that exists already (default: keep it, and say so)"),
}

#: The concerns in the README's options table, in order: (concern, fields, label suffix).
CONCERNS = (("input", INPUT, ""), ("estimation", {**ESTIMATION, **SPATIAL}, ""), ("rendering", {**RENDERING, **WHITE_BALANCE}, ""),
            ("regions", NEUTRAL, ""), ("regions", REGIONS, " (surfaces)"), ("preview", PREVIEW, ""),
            ("batches", BATCH, ""), ("spectral rendering", SPECTRAL, ""), ("sidecars (CLI)", SIDECAR, ""))


def _cell(value) -> str:
    return "" if value is None else f"`{value}`"


def options_table() -> str:
    """The README's options table (markdown): option, concern, default,
    accepted values. ``tests/test_options_agree.py`` checks that the README
    holds it as written here."""
    rows = ["| option | concern | default | accepted |", "|---|---|---|---|"]
    seen = set()
    for concern, fields, suffix in CONCERNS:
        for name, opt in fields.items():
            label = name + (suffix if name == "format" else "")
            if label in seen:
                continue
            seen.add(label)
            accepted = (", ".join(f"`{c}`" for c in opt.choices) if opt.choices
                        else (opt.summary or opt.description.split(";")[0]).replace("|", "/").replace("<", "&lt;"))
            rows.append(f"| `{label}` | {concern} | {_cell(opt.given_default)} | {accepted} |")
    return "\n".join(rows)
