"""Option validation and the service's tables of formats and outputs.

Free of the web stack: the REST routers, the batch jobs
(:mod:`service.jobs`) and the CLI (:mod:`service.cli`) validate with the same
functions and refuse with the same :class:`~service.errors.ServiceError`
(422 ``invalid_parameter``, naming what is accepted).
"""

from __future__ import annotations

import json
import math
from typing import NamedTuple

from .errors import ServiceError

__all__ = ["Format", "FORMATS", "MEDIA_TYPES", "IMAGE_FORMATS", "BATCH_FORMATS", "RENDER_FORMATS", "PREVIEW_FORMATS",
           "OUTPUTS", "RENDER_OUTPUTS", "SURFACE_MODELS", "LIGHT_MODELS", "choose_format", "check_output",
           "check_target", "check_camera_name", "check_dim", "check_region_size", "check_spatial", "estimate_options", "parse_json_field", "parse_json_list", "parse_grid",
           "parse_exposure", "parse_neutral", "EXPOSURE_HELP", "NEUTRAL_HELP", "MAX_N", "parse_wavelengths",
           "parse_degrees", "rule_options"]


class Format(NamedTuple):
    """An output format: the encoder (``tiff``, ``png``, ``jpeg``, ``xmp``, ``dng``),
    its bits per sample (0: not an image) and the file extension."""

    encoder: str
    bits: int
    extension: str


#: Every output format a request may name (``format=``), the one table.
FORMATS = {
    "tiff": Format("tiff", 16, "tif"),
    "png": Format("png", 8, "png"),
    "png16": Format("png", 16, "png"),
    "jpeg": Format("jpeg", 8, "jpg"),
    "jpg": Format("jpeg", 8, "jpg"),
    "xmp": Format("xmp", 0, "xmp"),
    "dng": Format("dng", 0, "dng"),
}
#: Media type of each encoder.
MEDIA_TYPES = {"png": "image/png", "tiff": "image/tiff", "jpeg": "image/jpeg", "xmp": "application/rdf+xml",
               "dng": "image/x-adobe-dng"}
#: The formats of the corrected image (``/v1/white-balance`` adds ``xmp`` and ``dng``; batches and the CLI).
IMAGE_FORMATS = ("tiff", "png", "png16", "jpeg", "jpg")
#: A batch's results (``POST /v1/batches``): the corrected images, or each RAW as a DNG with its white inside.
BATCH_FORMATS = IMAGE_FORMATS + ("dng",)
#: ``/v1/render`` (spectral data): lossless only.
RENDER_FORMATS = ("tiff", "png", "png16")
#: ``/v1/preview``: 8-bit.
PREVIEW_FORMATS = ("jpeg", "jpg", "png")

#: Output spaces of the corrected image (``/v1/white-balance``, ``/v1/preview``, batches, CLI).
OUTPUTS = ("sRGB", "linear-sRGB", "Display P3", "Typical CRT Brainard 1997", "Apple Studio Display")
#: Output spaces of ``/v1/render``.
RENDER_OUTPUTS = ("sRGB", "linear-sRGB")

SURFACE_MODELS = ("pca", "fourier")
LIGHT_MODELS = ("daylight", "illuminant-pca", "fourier")


def choose_format(name: str, accepted=tuple(FORMATS)) -> Format:
    """The :class:`Format` named ``name`` among ``accepted`` (422 naming them)."""
    if name not in accepted:
        raise ServiceError(422, "invalid_parameter", f"format {name!r} unknown; accepted: {sorted(accepted)}")
    return FORMATS[name]


def check_output(output: str, accepted=OUTPUTS) -> str:
    """``output`` if it is one of ``accepted`` (422 naming them)."""
    if output not in accepted:
        raise ServiceError(422, "invalid_parameter", f"output must be one of {', '.join(accepted)}")
    return output


#: Targets known valid without looking them up: the default (CIE D65 is
#: always among colour-science's illuminants), so validating the options of
#: a command that renders nothing (``wandell analyze``) imports no colour-science.
_KNOWN_TARGETS = ("estimate", "as-seen", "D65")


def check_target(target: str) -> str:
    """A light to render under: ``estimate``, ``as-seen`` or an illuminant name."""
    if target not in _KNOWN_TARGETS:
        from models import illuminant

        try:
            illuminant(target)
        except KeyError as e:
            raise ServiceError(422, "invalid_parameter", f"target: {e.args[0]}") from None
    return target


def check_camera_name(camera: str | None) -> str | None:
    """A camera option: ``None``, ``auto``, ``matrix``, ``generic`` or a measured camera."""
    if camera not in (None, "auto", "matrix", "generic"):
        from models import camera_names, canonical_camera_name

        try:
            known = canonical_camera_name(camera) is not None
        except (KeyError, ValueError):
            known = False
        if not known:
            raise ServiceError(422, "invalid_parameter", f"camera {camera!r} unknown; accepted: "
                               f"{list(camera_names()) + ['matrix', 'generic', 'auto']}")
    return camera


def check_dim(value, name: str) -> int | str | None:
    """``surface_dim``/``light_dim``: ``None``/``""`` (the default), ``auto``
    (BIC) or an integer in 1..16."""
    if value is None or value == "":
        return None
    if str(value) == "auto":
        return "auto"
    try:
        iv = int(value)
    except (TypeError, ValueError):
        raise ServiceError(422, "invalid_parameter", f"{name} must be an integer in 1..16 or 'auto', "
                           f"not {value!r}") from None
    if not 1 <= iv <= 16:
        raise ServiceError(422, "invalid_parameter", f"{name} must be in 1..16 or 'auto'")
    return iv


def check_region_size(region_size: int | None) -> int | None:
    """A light map's region side: 8..100000 pixels, or ``None``."""
    if region_size is not None and not 8 <= region_size <= 100000:
        raise ServiceError(422, "invalid_parameter", "region_size must be in 8..100000 pixels")
    return region_size


def check_spatial(spatial):
    """``spatial`` as :func:`recovery.estimate_illuminant` takes it (``True``,
    ``False`` or ``"auto"``), ``None`` when absent."""
    if spatial is None or spatial == "":
        return None
    from recovery.spatial import parse_spatial

    try:
        mode = parse_spatial(spatial)
    except ValueError:
        raise ServiceError(422, "invalid_parameter", f"spatial {spatial!r} unknown; accepted: auto, true "
                           "(a light map), false (one light)") from None
    return {"map": True, "uniform": False, "auto": "auto"}[mode]


def estimate_options(method: str, surface_dim, light_dim, region_size: int | None,
                     spatial, surface_model: str | None = None, light_model: str | None = None,
                     quality: str | None = None) -> dict:
    """Validated keyword options for :func:`recovery.estimate_illuminant`
    (what :class:`service.schemas.Estimation` hands the estimator)."""
    from recovery.methods import METHOD_NAMES, QUALITY_NAMES  # plain data: importing this module stays light

    if method not in METHOD_NAMES:
        raise ServiceError(422, "invalid_parameter", f"method {method!r} unknown; accepted: {list(METHOD_NAMES)}")
    opts: dict = {"white_level": 1.0}
    for field, value, accepted, key in (("surface_model", surface_model, SURFACE_MODELS, "surface_basis"),
                                        ("light_model", light_model, LIGHT_MODELS, "light_basis"),
                                        ("quality", quality, QUALITY_NAMES, "quality")):
        if value is not None:
            if value not in accepted:
                raise ServiceError(422, "invalid_parameter",
                                   f"{field} {value!r} unknown; accepted: {list(accepted)}")
            opts[key] = value
    for name, val in (("surface_dim", surface_dim), ("light_dim", light_dim)):
        dim = check_dim(val, name)
        if dim is not None:
            opts[name] = dim
    if check_region_size(region_size) is not None:
        opts["region_size"] = region_size
    mode = check_spatial(spatial)
    if mode is not None:
        opts["spatial"] = mode
    if (method == "maloney-wandell" and mode is True) or "region_size" in opts:
        # the light map's bound (413 past it): the literal map's regions, and the light posterior's
        # regions of a region_size asked for (probe round 6); read only where it applies (the CLI's
        # other commands start without pydantic-settings, issue 19)
        from .settings import get_settings

        opts["max_regions"] = get_settings().max_light_map_regions
    return opts


#: Longest JSON form field accepted (10,000 points or rectangles fit in well under it).
JSON_FIELD_MAX_CHARS = 1_000_000
#: Deepest bracket nesting a JSON form field may have (the documented shapes need 2).
JSON_FIELD_MAX_DEPTH = 8


def _json_depth(text: str) -> int:
    """Deepest ``[``/``{`` nesting of ``text`` (brackets inside strings
    counted too: no accepted shape has strings), vectorised."""
    import numpy as np

    b = np.frombuffer(text.encode("utf-8", "surrogatepass"), np.uint8)
    step = (b == ord("[")).astype(np.int32) + (b == ord("{")) - (b == ord("]")) - (b == ord("}"))
    return int(np.cumsum(step).max(initial=0))


def parse_json_field(text: str, name: str, shape: str):
    """The one parser of JSON form fields (``neutral``, ``points``,
    ``rects``): the length (:data:`JSON_FIELD_MAX_CHARS`) and bracket depth
    (:data:`JSON_FIELD_MAX_DEPTH`) are bounded before ``json.loads``, and
    whatever it refuses (bad syntax, an integer of more than Python's 4,300
    digits, recursion) is a 422 ``invalid_parameter`` saying ``shape``, the
    form the field must take; never a 500."""
    def bad(why: str):
        return ServiceError(422, "invalid_parameter", f"{name} {why}; give {shape}")

    if not isinstance(text, str):
        raise bad("is not text")
    if len(text) > JSON_FIELD_MAX_CHARS:
        raise bad(f"is {len(text)} characters long, at most {JSON_FIELD_MAX_CHARS}")
    if _json_depth(text) > JSON_FIELD_MAX_DEPTH:
        raise bad(f"nests brackets deeper than {JSON_FIELD_MAX_DEPTH}")
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise bad(f"is not valid JSON: {e.msg}") from None
    except (ValueError, RecursionError, MemoryError) as e:   # e.g. an integer of more than 4300 digits
        raise bad(f"is not usable JSON ({type(e).__name__}: {str(e)[:80]})") from None


def parse_json_list(text: str | None, name: str, width: int) -> list:
    """A JSON list of ``width``-integer lists (points or rectangles)."""
    if not text:
        return []
    shape = f"a JSON list of [{width} integers] lists"
    val = parse_json_field(text, name, shape)
    if not isinstance(val, list) or not all(
            isinstance(v, list) and len(v) == width and all(isinstance(x, int) and not isinstance(x, bool) for x in v)
            for v in val):
        raise ServiceError(422, "invalid_parameter", f"{name} must be {shape}")
    # how many: the request's points + rectangles + grid cells together, against WANDELL_MAX_SURFACE_REGIONS
    # (413 too_many_regions); a cap of 10000 here refused a list alone with a 422 whatever the setting (round 7)
    return val


def parse_grid(text: str | None) -> tuple[int, int] | None:
    """``"8x6"`` -> (8, 6) rows x columns."""
    if not text:
        return None
    try:
        a, b = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise ServiceError(422, "invalid_parameter", f"grid must look like 8x6 (rows x columns), got {text!r}") from None
    if not (1 <= a <= 100 and 1 <= b <= 100):
        raise ServiceError(422, "invalid_parameter", "grid dimensions must be in 1..100")
    return a, b


#: Largest sampling size of ``/v1/render`` and ``/v1/sampling``.
MAX_N = 64


def parse_wavelengths(text: str | None, field: str = "wavelengths") -> np.ndarray | None:
    """``"400,410,...,700"`` -> float array; finite, strictly increasing."""
    import numpy as np

    if text is None or not text.strip():
        return None
    try:
        wl = np.array([float(t) for t in text.replace(";", ",").split(",") if t.strip()])
    except ValueError:
        raise ServiceError(422, "invalid_parameter", f"{field} must be comma-separated numbers in nm") from None
    if wl.size < 2 or not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
        raise ServiceError(422, "invalid_parameter", f"{field} must be at least two finite, strictly increasing "
                       "values in nm")
    return wl


def parse_degrees(text: str | None):
    """``"2,2,2"`` -> (2, 2, 2) (Borges' degree sequence for x, y, z)."""
    if text is None or not text.strip():
        return None
    try:
        deg = tuple(int(t) for t in text.split(","))
    except ValueError:
        raise ServiceError(422, "invalid_parameter", f"degrees must look like 2,2,2, got {text!r}") from None
    if len(deg) != 3 or not all(0 <= d <= 12 for d in deg):
        raise ServiceError(422, "invalid_parameter", "degrees must be three integers in 0..12 (x, y, z)")
    return deg


def rule_options(strategy: str, n: int | None, channel: str | None, degrees: str | None) -> dict:
    """Validated strategy, size and options (422 naming what is wrong)."""
    from recovery.spectral import render_strategies

    names = render_strategies()
    if strategy not in names + ["auto", "full"]:
        raise ServiceError(422, "unknown_strategy", f"strategy {strategy!r} unknown; accepted: auto, full, "
                       f"{', '.join(names)}")
    if n is not None and not 1 <= n <= MAX_N:
        raise ServiceError(422, "n_out_of_range", f"n must be in 1..{MAX_N}, got {n}")
    opts: dict = {}
    if channel is not None and channel != "":
        if channel not in ("A", "C1", "C2", "XYZ"):
            raise ServiceError(422, "invalid_parameter", f"channel must be A, C1, C2 or XYZ, got {channel!r}")
        opts["channel"] = channel
    deg = parse_degrees(degrees)
    if deg is not None:
        opts["degrees"] = deg
    return opts


def rule_takes(strategy: str) -> dict[str, str]:
    """The query options of ``GET /v1/sampling`` that ``strategy`` takes, each
    with what it accepts (from its builder's signature,
    :data:`models.sampling.STRATEGIES`): ``n`` always, ``channel`` and
    ``degrees`` only where the builder has them."""
    import inspect

    from models.sampling import STRATEGIES

    params = inspect.signature(STRATEGIES[strategy]).parameters
    takes = {"n": ("n, the rule's size" if "degrees" not in params
                   else "n omitted, or equal to the sum of the degrees (they imply it)")}
    if "channel" in params:
        takes["n"] += " (omitted with channel=XYZ, whose orders imply it)"
        takes["channel"] = f"channel A, C1, C2 or XYZ (default {params['channel'].default})"
    if "degrees" in params:
        takes["degrees"] = ("degrees=x,y,z, each 0..12, default " + ",".join(map(str, params["degrees"].default)))
    return takes


def rule_refusal(strategy: str, n: int | None, opts: dict, error: BaseException | str) -> ServiceError:
    """The 422 of a sampling rule that cannot be made: what was asked (only
    the values given, never an empty ``{}``: probe round 4), why not, and
    what ``strategy`` accepts (:func:`rule_takes`)."""
    takes = rule_takes(strategy)
    given = ([f"n={n}"] if n is not None else []) + [
        f"{k}={','.join(map(str, v)) if isinstance(v, (tuple, list)) else v}" for k, v in opts.items()]
    asked = f"{strategy} with {' and '.join(given)}" if given else f"{strategy} with no n and no options"
    refused = [k for k in opts if k not in takes]
    why = (f"{strategy} takes no {' or '.join(refused)}" if refused else str(error).rstrip("."))
    return ServiceError(422, "invalid_parameter", f"{asked}: {why}. {strategy} accepts: {'; '.join(takes.values())}"
                        + "".join(f"; no {k}" for k in ("channel", "degrees") if k not in takes))


EXPOSURE_HELP = ("exposure in EV, or auto (default): auto is LibRaw's auto-brightness (the 99th "
                 "percentile of the brightest display channel is display white); a number overrides it, "
                 "0 rendering the brightest neutral the sensor records as display white, each +1 doubling")


def parse_exposure(value) -> float | None:
    """``None``/``""``/``"auto"`` -> ``None`` (the auto rule,
    :func:`recovery.synthesis.exposure_gain`); a number of EV in
    :data:`recovery.synthesis.EXPOSURE_RANGE` -> float; anything else a 422."""
    if value is None or (isinstance(value, str) and value.strip().lower() in ("", "auto")):
        return None
    from recovery.synthesis import EXPOSURE_RANGE

    try:
        ev = float(value)
    except (TypeError, ValueError):
        ev = math.nan
    lo, hi = EXPOSURE_RANGE
    if not (math.isfinite(ev) and lo <= ev <= hi):
        raise ServiceError(422, "invalid_parameter", f"exposure must be auto or a number of EV in {lo:g}..{hi:g}, "
                           f"not {value!r}")
    return ev


#: At most this many picks in one ``neutral`` (a darktable/RawTherapee user
#: samples a few grey patches, never hundreds; each costs one rectangle mean).
MAX_NEUTRAL_PICKS = 16

NEUTRAL_HELP = ("'use this as white': JSON [row, col] (a point) or [r0, c0, r1, c1] (a rectangle, end "
                "exclusive) in full-resolution pixels of the image as decoded (before DefaultCrop); the light "
                "is the mean camera RGB of the unclipped pixels there, rendered like an estimate. Several picks: "
                f"a list of points and rectangles, [[row, col], [r0, c0, r1, c1], ...] (at most "
                f"{MAX_NEUTRAL_PICKS}): the light is the mean of the picks' whites, each pick weighing the same "
                "(each pick's camera RGB scaled to unit length), as the web page's Shift-click averages them")

_NEUTRAL_SHAPE = (f"[row, col], [r0, c0, r1, c1], or a list of up to {MAX_NEUTRAL_PICKS} of them "
                  "([[row, col], [r0, c0, r1, c1], ...])")


def _is_region(v) -> bool:
    return (isinstance(v, list) and len(v) in (2, 4)
            and all(isinstance(x, int) and not isinstance(x, bool) for x in v))


def parse_neutral(text) -> list | None:
    """``neutral``: JSON ``[row, col]`` or ``[r0, c0, r1, c1]`` (integers), or
    a list of up to :data:`MAX_NEUTRAL_PICKS` of them (several picks,
    averaged by :func:`service.estimation.neutral_white`); ``None`` when
    absent; otherwise a 422 saying what is accepted and which pick was
    wrong."""
    if text is None or (isinstance(text, str) and not text.strip()):
        return None
    val = parse_json_field(text, "neutral", _NEUTRAL_SHAPE) if isinstance(text, str) else text
    shown = repr(text) if len(repr(text)) <= 80 else repr(text)[:77] + "..."
    if _is_region(val):
        return val
    if isinstance(val, list) and val and all(isinstance(v, list) for v in val):
        if len(val) > MAX_NEUTRAL_PICKS:
            raise ServiceError(422, "invalid_parameter", f"neutral has {len(val)} picks, at most "
                               f"{MAX_NEUTRAL_PICKS}")
        for i, v in enumerate(val):
            if not _is_region(v):
                pick = repr(v) if len(repr(v)) <= 60 else repr(v)[:57] + "..."
                raise ServiceError(422, "invalid_parameter", f"neutral pick {i + 1} of {len(val)} is {pick}: each "
                                   "pick must be [row, col] or [r0, c0, r1, c1] (integers)")
        return val
    if isinstance(val, list) and not val:
        raise ServiceError(422, "invalid_parameter", f"neutral is an empty list; give {_NEUTRAL_SHAPE}")
    raise ServiceError(422, "invalid_parameter", f"neutral must be {_NEUTRAL_SHAPE} (integers), got {shown}")
