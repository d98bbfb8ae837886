"""The corrected image: the correction matrix of a light (with its exposure
rule), the DNG DefaultCrop, the per-pixel correction of the whole image or
strip by strip, and what the output file carries (:mod:`service.pipeline`
re-exports every name)."""

from __future__ import annotations

import json
import time

import numpy as np

from recovery.api import resolve_model
from recovery.errors import InputError
from recovery.synthesis import correction_matrix as _recovery_correction_matrix, output_space
from recovery.synthesis import exposure_gain as _recovery_exposure_gain

from .correction import Correction, apply_matrix_inplace, chunk_rows
from .errors import ServiceError
from .estimation import EstimateRun
from .image_files import _with_meta, encode_image
from .opening import _full_linear_u16, drain_prefetch
from .options import Format
from .report import estimate_summary, profile_of, rendering_choice, temperature_tint


def correction_matrix(run: EstimateRun, target: str, output: str, surface_model: str | None = None,
                      *, decoded=None, tone: str = "shoulder", exposure: float | None = None
                      ) -> tuple[np.ndarray, dict]:
    """Camera RGB (1.0 = saturation) -> linear display values for ``run``'s
    light, by :func:`recovery.synthesis.correction_matrix`: the spectral
    rendering, or the DNG-matrix rendering for a camera known only by its
    colour matrix (:func:`rendering_choice`, when ``decoded`` is given); its
    exposure rule (``exposure`` in EV, ``None`` for LibRaw's auto-brightness
    measured on ``decoded``'s estimation image, :func:`exposure_gain`), the
    highlight shoulder (``tone``) and LibRaw's tone curve for display
    encodings. The surface model has C terms of ``surface_model`` (default
    PCA of the shipped reflectances). ``info`` adds ``color_source``."""
    cam, est = run.camera, run.estimate
    try:
        space = output_space(output, cam.wavelengths)
    except (ValueError, KeyError) as e:
        raise ServiceError(422, "invalid_parameter", f"output: {e}") from None
    choice = rendering_choice(run, decoded)
    S = resolve_model(surface_model, "surface", cam.channels, cam.wavelengths).basis
    try:
        M, info = _recovery_correction_matrix(cam, est.rgb, est.spectrum, target, space, S,
                                              profile=choice["profile"], tone=tone, exposure=exposure,
                                              image=_estimation_image(decoded))
    except InputError as e:
        if e.code != "unrenderable":
            raise
        raise ServiceError(422, "unrenderable", f"{light_source(run)} cannot be rendered for target {target!r} "
                           f"on {output}: white comes out with no luminance; {_unrenderable_advice(run)}") from None
    info["color_source"] = choice["color_source"] if info["rendering"] == "dng-matrix" else cam.source
    if not np.all(np.isfinite(M)):
        # never a black image (NaN matrix) answered as a success
        raise ServiceError(422, "unrenderable", f"no finite correction from this light to target {target!r} "
                           f"on {output}; choose another target (e.g. D65) or check the estimate")
    return M, info


def light_source(run: EstimateRun) -> str:
    """Whose light ``run`` renders, in words for an error: the user's white
    (``white=T/tint``), the file's as-shot white, the surface the user chose
    as white, or the estimate (probe round 4: a user's white was refused as
    "the estimated light")."""
    method = getattr(run.estimate, "method", None)
    if run.white is not None or method == "temperature-tint":
        return f"the white you set (white={run.white!r})" if run.white else "the white you set"
    if method == "as-shot":
        return "the file's as-shot white (white='as-shot')"
    if run.neutral is not None or method == "neutral-surface":
        where = (run.neutral or {}).get("where")
        return f"the surface you chose as white (neutral={where})" if where else "the surface you chose as white"
    return "the estimated light"


def _unrenderable_advice(run: EstimateRun) -> str:
    method = getattr(run.estimate, "method", None)
    if run.white is not None or method == "temperature-tint":
        return "choose a temperature and tint nearer the daylight locus, or another target (e.g. D65)"
    if method in ("as-shot", "neutral-surface") or run.neutral is not None:
        return "choose another white (e.g. white=estimate) or another target (e.g. D65)"
    return "choose another target (e.g. D65), or give a white (white=TEMPERATURE/TINT)"


def _estimation_image(decoded):
    """The image the auto exposure measures: the estimation image (block-
    averaged, the same for the full image and the preview, so the rendering
    does not depend on the output size), or ``None``."""
    return getattr(decoded, "estimation", None)


def exposure_gain(decoded, M: np.ndarray, neutral=None, exposure: float | None = None) -> tuple[float, dict]:
    """The exposure gain on the linear display values of ``M`` for an upload
    (:func:`recovery.synthesis.exposure_gain` on its estimation image):
    ``2 ** exposure`` for a user's EV, else LibRaw's auto-brightness; 1
    without an image."""
    return _recovery_exposure_gain(_estimation_image(decoded), M, neutral, exposure)


def default_crop(decoded, img: np.ndarray) -> np.ndarray:
    """The DNG DefaultCrop of a full-resolution image (a view), the file's
    orientation taken into account; the image itself when there is none or
    it does not fit."""
    bounds = crop_bounds(decoded, img.shape[:2])
    if bounds is None:
        return img
    r0, r1, c0, c1 = bounds
    return img[r0:r1, c0:c1]


def crop_bounds(decoded, shape) -> tuple[int, int, int, int] | None:
    """The rows and columns ``(r0, r1, c0, c1)`` of :func:`default_crop` in
    a full-resolution image of ``shape`` (oriented), or ``None`` (the whole
    image)."""
    from .metadata import color_profile

    prof = color_profile(decoded)
    crop = None if prof is None else prof.default_crop
    if not crop:
        return None
    top, left, h, w = crop
    flip = int(getattr(decoded, "_postprocess", {}).get("user_flip", 0) or 0)
    H, W = shape
    sh, sw = (W, H) if flip & 4 else (H, W)          # the sensor's (unoriented) shape
    if top < 0 or left < 0 or top + h > sh or left + w > sw or (h, w) == (sh, sw):
        return None
    from .decode import FLIP_OPS

    rows = np.broadcast_to(np.arange(sh)[:, None], (sh, sw))
    cols = np.broadcast_to(np.arange(sw)[None, :], (sh, sw))
    op = FLIP_OPS.get(flip, FLIP_OPS[0])
    r, c = op(rows), op(cols)                       # views: no memory
    keep_r = (r[:, 0] >= top) & (r[:, 0] < top + h) if np.ptp(r[:, 0]) else (c[:, 0] >= left) & (c[:, 0] < left + w)
    keep_c = (c[0] >= left) & (c[0] < left + w) if np.ptp(c[0]) else (r[0] >= top) & (r[0] < top + h)
    ri, ci = np.flatnonzero(keep_r), np.flatnonzero(keep_c)
    return int(ri[0]), int(ri[-1]) + 1, int(ci[0]), int(ci[-1]) + 1


def light_gain_field(decoded, run: EstimateRun, full_shape):
    """The per-pixel white balances of the estimate's light map in the
    full image's pixels (:mod:`service.light_field`), None for one light."""
    from .light_field import gain_field

    est = run.estimate
    if getattr(est, "light_map", None) is None or decoded.estimation is None:
        return None
    return gain_field(est, run.camera, run.factor, decoded.estimation.shape, full_shape)


def render_full(decoded, run: EstimateRun, target: str, output: str, bits: int, surface_model=None,
                threads: int | None = None, timings: dict | None = None, tone: str = "shoulder",
                exposure: float | None = None) -> tuple[np.ndarray, np.ndarray, dict]:
    """The corrected full-resolution image: matrix, demosaic, DefaultCrop,
    highlights, exposure, encoding. Returns ``(image, M, info)``."""
    try:
        M, info = correction_matrix(run, target, output, surface_model, decoded=decoded, tone=tone,
                                    exposure=exposure)
    except BaseException:
        drain_prefetch(decoded)
        raise
    t0 = time.perf_counter()
    full = _full_linear_u16(decoded)
    field = light_gain_field(decoded, run, full.shape)
    b = crop_bounds(decoded, full.shape[:2]) if field is not None else None
    rgb16 = default_crop(decoded, full)
    if field is not None:         # each pixel white-balanced by the light there (service.light_field)
        import os

        field.apply(rgb16, *((b[0], b[2]) if b is not None else (0, 0)), threads=threads or os.cpu_count() or 1)
        info["light_map_gains"] = list(field.range)
    t1 = time.perf_counter()
    out = apply_matrix_inplace(rgb16, M, info["encoding"], bits, threads=threads, neutral=info.get("neutral"),
                               shoulder=info.get("shoulder"), curve=info.get("curve"), reuse_input=True)
    t2 = time.perf_counter()
    if timings is not None:
        timings.update(demosaic=(t1 - t0) * 1e3, correct=(t2 - t1) * 1e3)
    info["crop"] = [int(out.shape[0]), int(out.shape[1])]
    return out, M, info


def render_corrected(decoded, run: EstimateRun, *, target: str, output: str, fmt: Format,
                     surface_basis=None, threads: int | None = None, white: str = "estimate",
                     exposure: float | None = None) -> tuple[np.ndarray, np.ndarray, dict, dict]:
    """Correction matrix -> apply: the corrected full-resolution image in
    ``fmt``'s bits (:data:`service.options.FORMATS`) at ``exposure`` (EV;
    ``None``: the auto rule, :func:`correction_matrix`) and what its file
    carries (ICC profile, the source's EXIF, the estimate: :func:`output_meta`).
    Returns ``(image, M, info, meta)``; timings go to ``run.timings_ms``."""
    out, M, info = render_full(decoded, run, target, output, fmt.bits, surface_basis, threads=threads,
                               timings=run.timings_ms, exposure=exposure)
    summary = estimate_summary(run, info, profile_of(decoded), white=white, target=target, output=output)
    return out, M, info, output_meta(decoded, output, summary)


def write_corrected(decoded, run: EstimateRun, path: str, **kw) -> tuple[np.ndarray, dict]:
    """:func:`render_corrected`, encoded to ``path``: ``(M, info)``. A PNG or
    JPEG is made strip by strip when it can be (:func:`render_encoded`)."""
    if kw["fmt"].encoder in STRIP_ENCODERS:
        data, M, info, _ = render_encoded(decoded, run, **kw)
        with open(path, "wb") as f:
            f.write(data)
        return M, info
    out, M, info, meta = render_corrected(decoded, run, **kw)
    t0 = time.perf_counter()
    encode_image(out, kw["fmt"].encoder, path, meta=meta, threads=kw.get("threads"))
    run.timings_ms["encode"] = (time.perf_counter() - t0) * 1e3
    return M, info


#: the encoders :func:`render_encoded` runs strip by strip (:mod:`service.strips`)
STRIP_ENCODERS = ("png", "jpeg")


def render_encoded(decoded, run: EstimateRun, *, target: str, output: str, fmt: Format,
                   surface_basis=None, threads: int | None = None, white: str = "estimate",
                   exposure: float | None = None) -> tuple[bytes, np.ndarray, dict, dict]:
    """:func:`render_corrected` encoded as ``fmt`` with its metadata:
    ``(bytes, M, info, meta)``. A PNG or JPEG of a RAW whose mosaic was kept
    (``keep_mosaic``, no demosaic started ahead) is demosaicked, corrected
    and encoded strip by strip (:mod:`service.strips`: the same pixels
    without the full-resolution 16-bit image; timing ``render``), and so
    is an unrotated LinearRaw DNG read from its strips or tiles; anything
    else through the whole image (timings ``demosaic``, ``correct``,
    ``encode``)."""
    from . import strips

    source = None
    if fmt.encoder in STRIP_ENCODERS and getattr(decoded, "_full_future", None) is None:
        source = strips.mosaic_rows(decoded, lambda shape: crop_bounds(decoded, shape))
        if source is None:           # a LinearRaw DNG: its strips or tiles read as the output's strips need them
            source = strips.linear_rows(decoded, lambda shape: crop_bounds(decoded, shape))
    if source is None:
        out, M, info, meta = render_corrected(decoded, run, target=target, output=output, fmt=fmt,
                                              surface_basis=surface_basis, threads=threads, white=white,
                                              exposure=exposure)
        t0 = time.perf_counter()
        data = encode_image(out, fmt.encoder, meta=meta, threads=threads)
        run.timings_ms["encode"] = (time.perf_counter() - t0) * 1e3
        return data, M, info, meta
    M, info = correction_matrix(run, target, output, surface_basis, decoded=decoded, exposure=exposure)
    t0 = time.perf_counter()
    field = light_gain_field(decoded, run, decoded.full_shape)
    if field is not None:         # each pixel white-balanced by the light there (service.light_field)
        source = strips.FieldRows(source, field)
        info["light_map_gains"] = list(field.range)
    H, W = source.shape
    kernel = Correction(M, info["encoding"], fmt.bits, neutral=info.get("neutral"), shoulder=info.get("shoulder"),
                        curve=info.get("curve"), rows_per_chunk=min(chunk_rows(W), max(H, 1)),
                        bgr=fmt.encoder == "jpeg")
    try:
        data = strips.encode_strips(source, kernel, fmt.encoder, threads)
    except ValueError:
        raise ServiceError(422, "encode_failed", f"could not encode {fmt.encoder}") from None
    info["crop"] = [int(H), int(W)]
    summary = estimate_summary(run, info, profile_of(decoded), white=white, target=target, output=output)
    meta = output_meta(decoded, output, summary)
    data = _with_meta(data, fmt.encoder, meta)
    run.timings_ms["render"] = (time.perf_counter() - t0) * 1e3
    return data, M, info, meta


def xmp_sidecar(decoded, run: EstimateRun) -> tuple[str, dict, dict]:
    """The Camera Raw XMP sidecar of ``run``'s light (Temperature/Tint by
    :func:`temperature_tint`): ``(text, temperature_tint, summary)``."""
    from .outputs import xmp_sidecar as _xmp

    tt = temperature_tint(decoded, run)
    summary = estimate_summary(run, None, profile_of(decoded), temperature=tt["temperature"], tint=tt["tint"],
                               basis=tt["basis"])
    return _xmp(tt["temperature"], tt["tint"], summary), tt, summary


#: Why a linear image (TIFF, PNG) has no DNG (``format=dng``: 422 ``not_a_raw``).
NOT_A_RAW = ("format=dng needs a camera RAW (a DNG, NEF, CR2, ARW, ...); this file is a linear image "
             "(TIFF/PNG), which has no raw data to put in a DNG: ask for tiff, png16, png or jpeg")


def dng_possible(data: bytes, decoded) -> None:
    """Raise 422 ``not_a_raw`` (:data:`NOT_A_RAW`) unless ``data`` is a DNG
    or ``decoded`` a camera RAW: what :func:`white_balanced_dng` needs, known
    before the estimate is made."""
    from .dngxmp import is_dng

    if decoded.kind != "raw" and not is_dng(data):
        raise ServiceError(422, "not_a_raw", NOT_A_RAW)


def white_balanced_dng(data: bytes, decoded, xmp: str, neutral) -> bytes:
    """``format=dng`` (``POST /v1/white-balance`` and batches): the upload
    ``data`` as a DNG with the white balance inside, the sidecar's packet
    ``xmp`` (:func:`xmp_sidecar`) and the light's camera RGB ``neutral`` as
    AsShotNeutral: a DNG's copy, its raw data untouched
    (:func:`service.dngxmp.dng_with_white`), or another camera RAW's raw data
    written as a DNG (:func:`service.dngwrite.raw_as_dng`). 422 ``not_a_raw``
    for a linear image, ``dng_failed`` for a RAW that cannot be one.

    References
    ----------
    Adobe, *Digital Negative (DNG) Specification* 1.4.0.0 (2012): AsShotNeutral, the XMP packet in IFD 0.
    """
    from .dngwrite import raw_as_dng
    from .dngxmp import NotADng, dng_with_white

    try:
        return dng_with_white(data, xmp, neutral)
    except NotADng:
        pass
    except ValueError as e:
        raise ServiceError(422, "dng_failed", f"no DNG copy of this DNG: {e}") from None
    dng_possible(data, decoded)
    try:
        return raw_as_dng(data, xmp, neutral, make=decoded.make, model=decoded.model,
                          color_matrix=decoded.color_matrix)
    except ValueError as e:          # NotConvertible among them
        raise ServiceError(422, "dng_failed", f"this RAW cannot be written as a DNG: {e}") from None


def output_meta(decoded, output: str, estimate: dict | None) -> dict:
    """What an output file carries: the ICC profile of ``output`` (sRGB,
    linear sRGB, Display P3, and the spectral displays' own, linear), the
    source's EXIF facts (its own ImageDescription, never the estimate),
    orientation 1, and the estimate in the XMP packet (``wandell:``
    namespace, :func:`service.outputs.xmp_facts`) and as a PNG text chunk."""
    from . import metadata, outputs

    facts = outputs.output_facts(metadata.source_exif(decoded), estimate)
    text = {"wandell:estimate": json.dumps(estimate, separators=(",", ":"))} if estimate is not None else None
    if facts.get("XMP"):       # the estimate, non-ASCII facts (PNG iTXt / JPEG APP1; TIFF takes them from facts)
        text = dict(text or {}, **{outputs.XMP_KEY: facts["XMP"]})
    return {"icc": outputs.shipped_icc(output), "facts": facts, "text": text}
