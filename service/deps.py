"""Request dependencies: settings, size-limited upload reading, options."""

from __future__ import annotations

import json

from fastapi import UploadFile

from recovery import METHODS, QUALITY_PRESETS

from .errors import ApiError
from .settings import Settings


async def read_upload(file: UploadFile | None, settings: Settings, field: str = "file") -> bytes:
    """The upload's bytes, refusing more than the configured limit (413)."""
    if file is None:
        raise ApiError(422, "missing_file", f"multipart field {field!r} is required")
    data = await file.read(settings.max_upload_bytes + 1)
    if len(data) > settings.max_upload_bytes:
        raise ApiError(413, "file_too_large",
                       f"{field} exceeds the upload limit of {settings.max_upload_bytes} bytes")
    return data


SURFACE_MODELS = ("pca", "fourier")
LIGHT_MODELS = ("daylight", "illuminant-pca", "fourier")


def estimate_options(method: str, surface_dim, light_dim, region_size: int | None,
                     spatial, surface_model: str | None = None, light_model: str | None = None,
                     quality: str | None = None) -> dict:
    """Validated keyword options for :func:`recovery.estimate_illuminant`."""
    if method not in METHODS:
        raise ApiError(422, "invalid_parameter", f"method {method!r} unknown; accepted: {list(METHODS)}")
    opts: dict = {"white_level": 1.0}
    for field, value, accepted, key in (("surface_model", surface_model, SURFACE_MODELS, "surface_basis"),
                                        ("light_model", light_model, LIGHT_MODELS, "light_basis"),
                                        ("quality", quality, tuple(QUALITY_PRESETS), "quality")):
        if value is not None:
            if value not in accepted:
                raise ApiError(422, "invalid_parameter", f"{field} {value!r} unknown; accepted: {list(accepted)}")
            opts[key] = value
    for name, val in (("surface_dim", surface_dim), ("light_dim", light_dim)):
        if val is None or val == "":
            continue
        if str(val) == "auto":
            opts[name] = "auto"
            continue
        try:
            iv = int(val)
        except (TypeError, ValueError):
            raise ApiError(422, "invalid_parameter", f"{name} must be an integer in 1..16 or 'auto', "
                           f"not {val!r}") from None
        if not 1 <= iv <= 16:
            raise ApiError(422, "invalid_parameter", f"{name} must be in 1..16 or 'auto'")
        opts[name] = iv
    if region_size is not None:
        if not 8 <= region_size <= 100000:
            raise ApiError(422, "invalid_parameter", "region_size must be in 8..100000 pixels")
        opts["region_size"] = region_size
    if spatial is not None and spatial != "":
        from recovery.spatial import parse_spatial

        try:
            mode = parse_spatial(spatial)
        except ValueError:
            raise ApiError(422, "invalid_parameter", f"spatial {spatial!r} unknown; accepted: auto, true (a light "
                           "map), false (one light)") from None
        opts["spatial"] = {"map": True, "uniform": False, "auto": "auto"}[mode]
    return opts


def parse_json_list(text: str | None, name: str, width: int) -> list:
    """A JSON list of ``width``-integer lists (points or rectangles)."""
    if not text:
        return []
    try:
        val = json.loads(text)
    except json.JSONDecodeError as e:
        raise ApiError(422, "invalid_parameter", f"{name} is not valid JSON: {e.msg}") from None
    if not isinstance(val, list) or not all(
            isinstance(v, list) and len(v) == width and all(isinstance(x, int) and not isinstance(x, bool) for x in v) for v in val):
        raise ApiError(422, "invalid_parameter", f"{name} must be a JSON list of [{width} integers] lists")
    if len(val) > 10000:
        raise ApiError(422, "invalid_parameter", f"{name}: at most 10000 entries")
    return val


def parse_grid(text: str | None) -> tuple[int, int] | None:
    """``"8x6"`` -> (8, 6) rows x columns."""
    if not text:
        return None
    try:
        a, b = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise ApiError(422, "invalid_parameter", f"grid must look like 8x6 (rows x columns), got {text!r}") from None
    if not (1 <= a <= 100 and 1 <= b <= 100):
        raise ApiError(422, "invalid_parameter", "grid dimensions must be in 1..100")
    return a, b
