"""``GET /`` (the web page), its static files, and ``POST /v1/preview``.

The page is plain HTML, CSS and JavaScript from :mod:`service.static`, served
by the app itself: no build step, nothing fetched from another host. The page
calls the public REST endpoints (``/v1/analyze``, ``/v1/white-balance``,
``/v1/batches``) and ``/v1/preview`` below, which exists so a browser can show
a large RAW side by side before and after correction without transferring two
full-resolution images.
"""

from __future__ import annotations

import io
import json
import time
from importlib import resources

import numpy as np
from fastapi import APIRouter, Depends, File, Request, UploadFile
from fastapi.responses import HTMLResponse, Response

from .. import pipeline
from ..deps import checked_upload
from ..errors import ServiceError
from ..jsonsafe import clean
from ..options import FORMATS, MEDIA_TYPES, PREVIEW_FORMATS
from ..schemas import AnalyzeEstimation, Neutral, Preview, Rendering, WhiteBalanceRendering
from ..schemas.forms import form
from ..schemas.options import PREVIEW_MAX_SIDE, PREVIEW_SIDE_RANGE  # noqa: F401 (the preview limits, named here too)
from ..settings import Settings, get_settings
from ..white import with_white
from ..workers import run_heavy

router = APIRouter()

#: The only files served under ``/static/`` (a fixed list: no path from the
#: request ever reaches the file system).
STATIC_FILES = {"app.js": "text/javascript; charset=utf-8", "style.css": "text/css; charset=utf-8"}

#: The form fields of ``/v1/preview`` (service.schemas); the estimation and
#: rendering ones matter only for ``wb=corrected``, whose target is checked then.
_PREVIEW = form(Preview)
_PREVIEW_ESTIMATION = form(AnalyzeEstimation, include=("camera", "method", "quality", "spatial"),
                           prefix="corrected only: ")
_PREVIEW_RENDERING = form(Rendering, prefix="corrected only: ", lazy=("target",), choices={"format": PREVIEW_FORMATS},
                          defaults={"format": "jpeg"}, describe={"format": "jpeg or png (8-bit)"})
_NEUTRAL = form(Neutral, prefix="corrected only: ")
#: ``white`` as on ``/v1/white-balance`` (the estimate, as-shot, or a
#: Temperature/Tint: the page's sliders re-render through it)
_PREVIEW_WHITE = form(WhiteBalanceRendering, include=("white",), prefix="corrected only: ")

#: The page's Content-Security-Policy: its own script and style sheet only (no
#: inline script or style, nothing from another host), images also from the
#: ``blob:`` URLs the script makes of the previews, never inside a frame.
CSP = ("default-src 'self'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
       "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'")


def _static_text(name: str) -> str:
    return resources.files("service").joinpath("static", name).read_text(encoding="utf-8")


@router.get("/", response_class=HTMLResponse, include_in_schema=False)
def index() -> HTMLResponse:
    """The web page: upload a RAW, compare, read the diagnostics, run a batch."""
    return HTMLResponse(_static_text("index.html"), headers={"Cache-Control": "no-cache",
                                                             "Content-Security-Policy": CSP})


@router.get("/static/{name}", include_in_schema=False)
def static(name: str) -> Response:
    """The page's script and style sheet (only the files in :data:`STATIC_FILES`)."""
    if name not in STATIC_FILES:
        raise ServiceError(404, "not_found", f"no static file {name!r}; served: {sorted(STATIC_FILES)}")
    return Response(_static_text(name), media_type=STATIC_FILES[name], headers={"Cache-Control": "no-cache"})


# ---------------------------------------------------------------------------
# POST /v1/preview
# ---------------------------------------------------------------------------

def downsize_linear(img: np.ndarray, max_side: int) -> np.ndarray:
    """Area-average a linear (h, w, 3) float image so its longest side is at
    most ``max_side`` (unchanged if already smaller).

    Averaging is done on linear values, before any transfer function, so a
    preview pixel is the mean light of the pixels it covers (the same
    argument as the block averaging of the estimation image: mixtures of
    surfaces under one light stay linear, Wandell 1985, eq. 26).
    """
    import cv2

    h, w = img.shape[:2]
    s = min(1.0, max_side / max(h, w))
    if s >= 1.0:
        return img
    size = (max(1, int(round(w * s))), max(1, int(round(h * s))))
    return cv2.resize(img, size, interpolation=cv2.INTER_AREA)


def _to_uint16(lin: np.ndarray) -> np.ndarray:
    """Linear float (1.0 = saturation) -> uint16 (65535 = saturation),
    non-finite values mapped to 0 so no NaN reaches the encoder."""
    v = np.nan_to_num(np.asarray(lin, np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return np.rint(np.clip(v, 0.0, 1.0) * np.float32(65535.0)).astype(np.uint16)


class LibRawCannotRender(Exception):
    """LibRaw's ``postprocess`` failed on a RAW this service decoded."""


def own_camera_wb_preview(data: bytes, name: str | None, settings, camera, max_side: int, why: str):
    """``wb=camera`` of a RAW LibRaw cannot render but this service reads:
    the file's as-shot white through this service's own rendering (what
    ``/v1/white-balance`` with ``white=as-shot`` writes, under D65 in sRGB);
    without an as-shot white, the camera RGB unbalanced, as for a TIFF. It
    was a 422 ``corrupt_file`` "it is damaged" for a file every other
    endpoint reads (probe round 8). ``(decoded, image, info)``."""
    decoded, run = pipeline.analyze(data, name, settings, camera=camera, method="gray-world")
    note = (f"LibRaw cannot render this file ({why}); it is shown by this service's own rendering")
    if decoded.as_shot_neutral is None:
        small = _to_uint16(downsize_linear(decoded.estimation, max_side))
        img = pipeline.apply_matrix_inplace(small, np.eye(3), "sRGB", 8)
        why = decoded.as_shot_problem or "the file records no as-shot white balance"
        return decoded, img, {"wb": "camera", "warnings": [note + f", unbalanced: {why}"]}
    img, info = corrected_preview(decoded, with_white(decoded, run, "as-shot"), "D65", "sRGB", None, max_side)
    asn = [float(v) for v in decoded.as_shot_neutral]
    return decoded, img, {"wb": "camera", "camera_multipliers": [asn[1] / v for v in asn],
                          "rendering": info["rendering"],
                          "warnings": [note + " with its as-shot white (as /v1/white-balance white=as-shot)"]}


def camera_wb_preview(decoded, data: bytes, max_side: int) -> tuple[np.ndarray, dict]:
    """The image as the camera's own white balance renders it, 8-bit sRGB.

    RAW: LibRaw's rendering (``rawpy.postprocess``) with the file's as-shot
    multipliers (``use_camera_wb=True``), its colour matrix to sRGB and its
    default tone curve and brightening, half size, then area-downsized. This
    is "the original" a raw converter shows, not a product of this service's
    estimate. TIFF/PNG: such files carry no as-shot white balance; the
    linear camera RGB is shown sRGB-encoded without any balance, with a
    warning.
    """
    import cv2

    info: dict = {"wb": "camera", "warnings": []}
    if decoded.kind == "raw":
        import rawpy

        try:
            with rawpy.imread(io.BytesIO(data)) as raw:
                mult = [float(x) for x in raw.camera_whitebalance[:3]]
                rgb = raw.postprocess(use_camera_wb=True, half_size=True, output_bps=8)
        except rawpy.LibRawError as exc:
            # the file was decoded (this service reads some DNGs LibRaw cannot render: a LinearRaw of 32-bit
            # integers, deflate with a predictor), so it is not damaged (probe round 8): the caller renders it
            raise LibRawCannotRender(type(exc).__name__) from None
        if decoded.as_shot_neutral is None:
            why = decoded.as_shot_problem or "the file records no as-shot white balance"
            info["warnings"].append(f"{why}; LibRaw used its default (daylight) multipliers")
        else:
            info["camera_multipliers"] = [m / mult[1] if mult[1] else m for m in mult]
        h, w = rgb.shape[:2]
        s = min(1.0, max_side / max(h, w))
        if s < 1.0:
            rgb = cv2.resize(rgb, (max(1, int(round(w * s))), max(1, int(round(h * s)))),
                             interpolation=cv2.INTER_AREA)
        return np.ascontiguousarray(rgb[..., :3]), info
    info["warnings"].append(f"a linear {decoded.kind.upper()} carries no camera white balance: shown "
                            "unbalanced, sRGB-encoded")
    small = _to_uint16(downsize_linear(decoded.estimation, max_side))
    return pipeline.apply_matrix_inplace(small, np.eye(3), "sRGB", 8), info


def corrected_preview(decoded, run, target: str, output: str, surface_basis, max_side: int,
                      exposure: float | None = None) -> tuple[np.ndarray, dict]:
    """The corrected image, downsized: the 3x3 matrix of ``/v1/white-balance``
    (:func:`service.pipeline.correction_matrix`, Wandell 1985, eq. 23 and 36)
    applied to the area-downsized estimation image (binned CFA cells for a
    RAW, no demosaic needed at preview size), encoded 8-bit. Under a light
    map each pixel is first white-balanced by the light there, as the
    downloads are (:func:`service.rendering.light_gain_field`; the
    estimation image spans the full frame, so the field maps onto it)."""
    from ..rendering import light_gain_field

    M, minfo = pipeline.correction_matrix(run, target, output, surface_basis, decoded=decoded, exposure=exposure)
    small = _to_uint16(downsize_linear(decoded.estimation, max_side))
    field = light_gain_field(decoded, run, small.shape[:2])
    if field is not None:
        field.apply(small)
    out = pipeline.apply_matrix_inplace(small, M, minfo["encoding"], 8, neutral=minfo.get("neutral"),
                                       shoulder=minfo.get("shoulder"), curve=minfo.get("curve"))
    return out, {"wb": "corrected", "target": target, "output": output, "method": run.estimate.method,
                 "correction_matrix": M.tolist(), "rendering": pipeline.rendering_json(minfo), "warnings": []}


def output_box(decoded) -> tuple[int, int, int, int]:
    """``(top, left, height, width)`` of what ``/v1/white-balance`` writes (the
    DNG DefaultCrop, :func:`service.pipeline.default_crop`, orientation
    included) in the decoded image's full-resolution pixels; the whole image
    when the file has no crop."""
    H, W = decoded.full_shape
    rows = pipeline.default_crop(decoded, np.broadcast_to(np.arange(H)[:, None], (H, W)))
    cols = pipeline.default_crop(decoded, np.broadcast_to(np.arange(W)[None, :], (H, W)))
    return int(rows[0, 0]), int(cols[0, 0]), int(rows.shape[0]), int(rows.shape[1])


def crop_preview(img: np.ndarray, full_shape, box) -> np.ndarray:
    """The part of a downsized image ``img`` (of a ``full_shape`` image) that
    is the output ``box`` (:func:`output_box`), in the preview's pixels."""
    H, W = full_shape
    top, left, h, w = box
    if (h, w) == (H, W):
        return img
    sy, sx = img.shape[0] / H, img.shape[1] / W
    r0, c0 = int(round(top * sy)), int(round(left * sx))
    r1 = max(r0 + 1, min(img.shape[0], int(round((top + h) * sy))))
    c1 = max(c0 + 1, min(img.shape[1], int(round((left + w) * sx))))
    return np.ascontiguousarray(img[r0:r1, c0:c1])


@router.post("/v1/preview", response_class=Response, responses={
    200: {"content": {"image/jpeg": {}, "image/png": {}},
          "description": "An 8-bit preview image of what the downloads hold (the DNG DefaultCrop "
                         "applied); the header ``X-Preview`` (JSON) says what it shows: "
                         "``wb``, ``width``/``height`` of the preview, ``full_width``/``full_height`` "
                         "of the decoded image (the frame of ``neutral``), ``crop`` [top, left, height, "
                         "width] of the output in that frame, ``output_width``/``output_height`` (the "
                         "size /v1/white-balance writes), ``warnings``, and the camera multipliers "
                         "(camera) or the correction matrix, method and target (corrected)."},
    415: {"description": "not a format the service reads"},
    422: {"description": "bad option or unusable file"}})
async def preview(request: Request, file: UploadFile = File(..., description="RAW file (anything LibRaw reads) or linear "
                                                           "16-bit TIFF/PNG"),
                  pv: Preview = Depends(_PREVIEW),
                  est: AnalyzeEstimation = Depends(_PREVIEW_ESTIMATION), rend: Rendering = Depends(_PREVIEW_RENDERING),
                  nt: Neutral = Depends(_NEUTRAL), wh: WhiteBalanceRendering = Depends(_PREVIEW_WHITE),
                  settings: Settings = Depends(get_settings)):
    """A small 8-bit preview for the web page: the original as the camera's
    white balance renders it (``wb=camera``) or the corrected image
    (``wb=corrected``), longest side at most ``max_side``."""
    t0 = time.perf_counter()
    wb, max_side, fmt = pv.wb, pv.max_side, FORMATS[rend.format].encoder
    if wb == "corrected":
        rend.check("target")
    camera, method, opts = est.camera, est.method, est.estimate_kwargs()
    target, output, ev, where, white = rend.target, rend.output, rend.exposure, nt.neutral, wh.white
    if wb == "corrected" and where is not None and white != "estimate":
        raise ServiceError(422, "invalid_parameter", "neutral fixes the white from a surface; it cannot be "
                           f"combined with white={white!r}")
    data = await checked_upload(file, settings)     # read once the work has its slot (probe round 9)
    name = file.filename

    def work(data):
        if wb == "camera":
            decoded = pipeline.decode(data, name, settings)
            try:
                img, info = camera_wb_preview(decoded, data, max_side)
            except LibRawCannotRender as e:
                del decoded
                decoded, img, info = own_camera_wb_preview(data, name, settings, camera, max_side, str(e))
        else:
            decoded, run = pipeline.analyze(data, name, settings, camera=camera, method=method, options=opts,
                                            neutral=where)
            run = with_white(decoded, run, white)
            img, info = corrected_preview(decoded, run, target, output, opts.get("surface_basis"), max_side, ev)
            info["white"] = "neutral" if where is not None else white
            info["warnings"] = run.camera_warnings + list(decoded.warnings) + list(run.estimate.warnings)
        box = output_box(decoded)
        img = crop_preview(img, decoded.full_shape, box)
        info.update(width=int(img.shape[1]), height=int(img.shape[0]),
                    full_width=int(decoded.full_shape[1]), full_height=int(decoded.full_shape[0]),
                    crop=list(box), output_width=box[3], output_height=box[2])
        return pipeline.encode_image(img, fmt), info

    body, info = await run_heavy(work, data, request=request)
    info["ms"] = (time.perf_counter() - t0) * 1e3
    return Response(body, media_type=MEDIA_TYPES[fmt],
                    headers={"X-Preview": json.dumps(clean(info), separators=(",", ":")),
                             "Cache-Control": "no-store"})

