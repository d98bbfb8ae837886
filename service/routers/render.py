"""``POST /v1/render`` (spectral data to a display image) and
``GET /v1/sampling`` (a sampling rule's nodes and weights).

Thin: parses and validates the upload, calls
:func:`recovery.spectral.render_spectra`, encodes.
"""

from __future__ import annotations

import io
import json
import math
import time

import numpy as np
from fastapi import APIRouter, Depends, File, Request, UploadFile
from fastapi.responses import JSONResponse, Response

from ..deps import checked_upload, read_upload
from ..errors import ServiceError
from ..headers import content_disposition
from ..jsonsafe import clean
from ..options import (FORMATS, MAX_N, MEDIA_TYPES, RENDER_FORMATS, RENDER_OUTPUTS, parse_wavelengths, rule_options,
                       rule_refusal, rule_takes)
from ..schemas import Sampling, SpectralRendering
from ..schemas.forms import form, query
from ..schemas.responses import RenderReport, SamplingRule
from ..settings import Settings, get_settings
from ..workers import run_heavy

router = APIRouter(prefix="/v1")

#: Fewest wavelengths a spectrum (or light) may have: colour-science
#: resamples uniform data with Sprague (1880) interpolation, a 6-point rule.
MIN_WAVELENGTHS = 6


#: The form fields of ``/v1/render`` (service.schemas): the sampling, the
#: light and the output, narrowed to lossless formats and the two sRGB spaces.
_RENDER = form(SpectralRendering, choices={"format": RENDER_FORMATS, "output": RENDER_OUTPUTS},
               describe={"format": "tiff (16-bit), png (8-bit), png16",
                         "output": "sRGB (encoded) or linear-sRGB",
                         "response": "image, or json for the report alone"})
#: The query parameters of ``GET /v1/sampling``: the same declarations, the
#: rule's name required.
_SAMPLING = query(Sampling, defaults={"strategy": ...},
                  describe={"strategy": "a sampling strategy name (not auto or full: those are render modes)",
                            "n": f"size 1..{MAX_N} (implied by degrees for quasi-gauss-xyz)",
                            "illuminant": "light the rule is made for (wiener-points: default D65; composite: "
                                          "its spikes)"})


# --- parsing ----------------------------------------------------------------------


def load_npy(data: bytes, settings: Settings) -> np.ndarray:
    """A numeric ``.npy`` array without copying its data; object arrays and
    pickles are refused (``allow_pickle=False`` semantics), and the size is
    checked from the header before anything is read (413)."""
    fmt = np.lib.format
    buf = io.BytesIO(data)
    try:
        major, _ = fmt.read_magic(buf)
        reader = fmt.read_array_header_1_0 if major == 1 else fmt.read_array_header_2_0
        shape, fortran, dtype = reader(buf)
    except Exception as e:  # noqa: BLE001 - any header failure is a bad upload
        raise ServiceError(422, "bad_npy", f"file is not a readable .npy array: {e}") from None
    if dtype.hasobject or dtype.kind not in "fiu":
        raise ServiceError(422, "bad_npy", f"the array's dtype {dtype} is not numeric (object arrays and pickles "
                       "are refused)")
    if len(shape) not in (2, 3):
        raise ServiceError(422, "bad_shape", f"the array must be a cube H x W x N (or M x N spectra); got shape "
                       f"{tuple(shape)}")
    if any(int(s) < 0 for s in shape):
        raise ServiceError(422, "bad_shape", f"the array's shape {tuple(shape)} has a negative dimension")
    count = math.prod(int(s) for s in shape)   # exact: numpy's product wraps round in int64
    if count > settings.max_render_values:
        raise ServiceError(413, "cube_too_large", f"the array has {count} values, over the limit of "
                       f"{settings.max_render_values} (WANDELL_MAX_RENDER_VALUES)")
    offset = buf.tell()
    if len(data) - offset < count * dtype.itemsize:
        raise ServiceError(422, "bad_npy", f"the .npy file is truncated: {len(data) - offset} bytes of data for "
                       f"shape {tuple(shape)} {dtype}")
    arr = np.frombuffer(data, dtype=dtype, count=count, offset=offset)
    return arr.reshape(shape, order="F" if fortran else "C")


def load_csv(data: bytes, what: str = "file", max_values: int | None = None) -> tuple[np.ndarray, np.ndarray, list]:
    """CSV with one row per wavelength (:func:`recovery.tables.read_csv_table`):
    the first column is the wavelength in nm, each further column one
    spectrum; an optional first row of names. Returns wavelengths ``(N,)``,
    spectra ``(M, N)`` and the names. The value limit (413
    ``cube_too_large``) and the 6-wavelength rule (422
    ``too_few_wavelengths``) are checked from a scan of the text, before any
    value is parsed (a 100 MB row of 25 million values costs no more than
    its text)."""
    from recovery.errors import InputError
    from recovery.tables import MAX_CSV_VALUES, read_csv_table

    try:
        table = read_csv_table(data, what, finite=False, min_rows=MIN_WAVELENGTHS,   # InputError "bad_csv" -> 422
                               max_values=max_values or MAX_CSV_VALUES)
    except InputError as e:
        if e.code == "too_many_values":
            raise ServiceError(413, "cube_too_large", f"{e} (WANDELL_MAX_RENDER_VALUES)") from None
        if e.code == "too_few_rows":
            label = "the spectra have" if what == "file" else f"{what} has"
            raise ServiceError(422, "too_few_wavelengths", f"{label} {e.rows} wavelength(s); at least "
                               f"{MIN_WAVELENGTHS} are needed (they are interpolated with Sprague's 6-point "
                               "rule)") from None
        raise
    if table.values.shape[1] < 1 or table.wavelengths.size < 2:
        raise ServiceError(422, "bad_csv", f"{what}: need a wavelength column and at least one spectrum column, "
                           "at least two rows, every row the same length")
    wl = table.wavelengths
    if not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
        raise ServiceError(422, "bad_wavelengths", f"{what}: the first column (wavelength, nm) must be finite and "
                           "strictly increasing")
    return wl, np.ascontiguousarray(table.values.T), table.names("spectrum")   # no copy: column-major


def check_values(arr: np.ndarray, what: str = "spectra") -> None:
    """Refuse non-finite or negative values (chunked: no full-size temporary)."""
    flat = arr.reshape(-1)
    step = 1 << 22
    for s in range(0, flat.size, step):
        chunk = flat[s:s + step]
        if chunk.dtype.kind == "f" and not np.all(np.isfinite(chunk)):
            raise ServiceError(422, "non_finite_values", f"the {what} contain NaN or Inf")
        if chunk.size and chunk.min() < 0:
            raise ServiceError(422, "negative_values", f"the {what} contain negative values (minimum "
                           f"{float(chunk.min()):.4g}); reflectances are >= 0")


def _is_npy(data: bytes, filename: str | None) -> bool:
    return data[:6] == b"\x93NUMPY" or (filename or "").lower().endswith(".npy")


# --- endpoints --------------------------------------------------------------------


@router.post("/render", responses={200: {
    "model": RenderReport,
    "content": {"image/tiff": {"schema": {"type": "string", "format": "binary"}},
                "image/png": {"schema": {"type": "string", "format": "binary"}}},
    "description": "the rendered image (format tiff, png or png16; the report in the X-Render-Report header), "
                   "or the report alone as JSON (response=json)"}})
async def render(request: Request, file: UploadFile = File(..., description=".npy reflectance cube H x W x N (or M x N), or CSV: "
                                          "first column wavelength (nm), one spectrum per further column, "
                                          "optional header row"),
                 light_file: UploadFile | None = File(None, description="light spectrum CSV: wavelength, value"),
                 sp: SpectralRendering = Depends(_RENDER),
                 settings: Settings = Depends(get_settings)):
    """Render spectral data under a light with a chosen wavelength sampling.

    The image is the colour signal's own tristimulus values (a perfect white
    reflector under the light has Y = 1) on the display, without chromatic
    adaptation unless ``adapt`` (Wandell 1985, eq. 22-24). The report (JSON
    body with ``response=json``, else the ``X-Render-Report`` header) gives
    the strategy, nodes, bands read, time and the estimated CIEDE2000 error
    against the full calculation.
    """
    t0 = time.perf_counter()
    fmt = FORMATS[sp.format]
    wavelengths, illuminant, strategy, n, output, adapt, max_error, response = (
        sp.wavelengths, sp.illuminant, sp.strategy, sp.n, sp.output, sp.adapt, sp.max_error, sp.response)
    opts = rule_options(strategy, n, sp.channel, sp.degrees)
    wl_form = parse_wavelengths(wavelengths)
    data = await checked_upload(file, settings)     # read once the work has its slot (probe round 9)
    light_data = await read_upload(light_file, settings, "light_file") if light_file is not None else None
    if light_data is not None and illuminant:
        raise ServiceError(422, "invalid_parameter", "give either illuminant or light_file, not both")

    def work(data):
        from recovery.errors import InputError
        from recovery.spectral import render_spectra

        names = None
        if _is_npy(data, file.filename):
            arr = load_npy(data, settings)
            if wl_form is None:
                raise ServiceError(422, "missing_wavelengths", "wavelengths (comma-separated nm) are required "
                               "with a .npy cube")
            wl = wl_form
        else:
            wl, arr, names = load_csv(data, max_values=settings.max_render_values)
            if arr.size > settings.max_render_values:
                raise ServiceError(413, "cube_too_large", f"{arr.size} values, over the limit of "
                               f"{settings.max_render_values}")
            if wl_form is not None and (wl_form.size != wl.size or not np.allclose(wl_form, wl)):
                raise ServiceError(422, "wavelength_mismatch", "wavelengths disagree with the CSV's first column")
        if arr.shape[-1] != wl.size:
            raise ServiceError(422, "wavelength_mismatch", f"the array has {arr.shape[-1]} bands (last axis) for "
                           f"{wl.size} wavelengths")
        if wl.size < MIN_WAVELENGTHS:
            raise ServiceError(422, "too_few_wavelengths", f"the spectra have {wl.size} wavelength(s); at least "
                           f"{MIN_WAVELENGTHS} are needed (they are interpolated with Sprague's 6-point rule)")
        if arr.size == 0:
            raise ServiceError(422, "empty_input", "the spectra are empty")
        check_values(arr)
        light, light_wl = illuminant or "D65", None
        if light_data is not None:
            light_wl, lv, _ = load_csv(light_data, "light_file", settings.max_render_values)
            if lv.shape[0] != 1:
                raise ServiceError(422, "bad_csv", "light_file must have exactly one spectrum column")
            if light_wl.size < MIN_WAVELENGTHS:
                raise ServiceError(422, "too_few_wavelengths", f"light_file has {light_wl.size} wavelength(s); at "
                               f"least {MIN_WAVELENGTHS} are needed (Sprague's 6-point interpolation)")
            check_values(lv, "light values")
            light = lv[0]
        try:
            result = render_spectra(arr, wl, light, strategy=strategy, n=n, output=output, adapt=adapt,
                                    light_wavelengths=light_wl, max_error=max_error, **opts)
        except InputError as e:
            msg = str(e)
            code = "unknown_illuminant" if "illuminant" in msg else "invalid_input"
            raise ServiceError(422, code, msg) from None
        return _response(result, names)

    def _response(result, names):
        # in the worker thread too: a JSON report of millions of values or the
        # image's quantisation and encoding would otherwise hold the event loop
        image, report = result.image, result.report
        report["timings_ms"]["request"] = (time.perf_counter() - t0) * 1e3
        if response == "json":
            body = dict(report)
            if names is not None:
                body["spectra"] = [{"name": nm, output: v} for nm, v in zip(names, image.tolist())]
            return JSONResponse(clean(body))
        from ..pipeline import encode_image

        bits = fmt.bits
        img = image if image.ndim == 3 else image[None]
        scale = 65535 if bits == 16 else 255
        q = np.empty(img.shape, np.uint16 if bits == 16 else np.uint8)
        np.multiply(np.clip(img, 0, 1), scale, out=img)
        np.rint(img, out=img)
        q[...] = img
        t1 = time.perf_counter()
        payload = encode_image(q, fmt.encoder)
        report["timings_ms"]["file_encode"] = (time.perf_counter() - t1) * 1e3
        header = {k: v for k, v in report.items() if k != "tried"}
        header["tried"] = len(report.get("tried", []))
        headers = {"X-Render-Report": json.dumps(clean(header), separators=(",", ":")),
                   "Content-Disposition": content_disposition(f"render.{fmt.extension}", "inline")}
        return Response(payload, media_type=MEDIA_TYPES[fmt.encoder], headers=headers)

    # under the same bound as every other heavy request (service.workers)
    return await run_heavy(work, data, request=request)


@router.get("/sampling", responses={200: {"model": SamplingRule}})
def sampling(q: Sampling = Depends(_SAMPLING)):
    """Nodes and weights of a sampling rule on the analysis grid (400-700 nm,
    10 nm), ``defined`` false with a ``reason`` when the order does not exist
    (e.g. Gaussian nodes outside the interval, Meyer 1988, Table 1a).

    ``weights`` are the rule's own weights when it has them (quadrature
    weights, or the nm each node stands for), otherwise its integration
    weights against CIE 1931 xbar, ybar, zbar (one row per node);
    ``weights_kind`` says which. ``integration_weights_xyz`` are always the
    latter (``T ~= coefficients @ W`` for an equal-energy light)."""
    import models
    from recovery.spectral import LIGHT_AWARE, cached_rule

    strategy, n, channel, degrees, illuminant = q.strategy, q.n, q.channel, q.degrees, q.illuminant
    if strategy in ("auto", "full"):
        raise ServiceError(422, "unknown_strategy", f"{strategy!r} is a render mode, not a sampling rule")
    opts = rule_options(strategy, n, channel, degrees)
    if any(k not in rule_takes(strategy) for k in opts):   # e.g. channel for quasi-gauss-xyz
        raise rule_refusal(strategy, n, opts, "")
    grid = models.DEFAULT_WAVELENGTHS
    cmfs = models.observer("XYZ", grid)
    light = None
    if illuminant is not None or strategy in LIGHT_AWARE:
        try:
            light = models.illuminant(illuminant or "D65", grid)
        except KeyError:
            raise ServiceError(422, "unknown_illuminant", f"illuminant {illuminant!r} unknown; accepted: "
                           f"{models.illuminant_names()} or D<cct>, BB<cct>") from None
    try:
        rule = cached_rule(strategy, n, grid, opts, light, cmfs)
    except (ValueError, TypeError, KeyError) as e:
        raise rule_refusal(strategy, n, opts, e) from None
    except (AttributeError, ImportError, NotImplementedError) as e:
        raise ServiceError(422, "strategy_unavailable", f"strategy {strategy!r} is not available in this "
                       f"build: {e}") from None
    integ = rule.integration_weights(cmfs) if rule.defined else None
    if rule.weights is not None:
        weights, kind = np.asarray(rule.weights, float), "the rule's own"
    else:
        weights, kind = integ, "integration weights against CIE 1931 xbar, ybar, zbar"
    body = {"strategy": strategy, "n": rule.n if rule.defined or n is None else n, "defined": bool(rule.defined),
            "nodes_nm": None if rule.nodes_nm is None else np.asarray(rule.nodes_nm, float),
            "weights": weights, "weights_kind": kind, "integration_weights_xyz": integ, "options": opts,
            "diagnostics": dict(rule.diagnostics or {})}
    if not rule.defined:
        body["reason"] = rule.reason
    return JSONResponse(clean(body))
