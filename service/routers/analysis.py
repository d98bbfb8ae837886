"""``POST /v1/analyze``, ``/v1/white-balance``, ``/v1/surfaces``."""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import threading
import time
import weakref

from fastapi import APIRouter, Depends, File, Request, UploadFile
from fastapi.responses import FileResponse, JSONResponse, Response, StreamingResponse

from .. import pipeline
from ..deps import checked_upload, read_upload
from ..errors import INSUFFICIENT_STORAGE, ServiceError, disk_full
from ..headers import content_disposition, download_name
from ..jsonsafe import clean
from ..options import FORMATS, MEDIA_TYPES
from ..schemas import AnalyzeEstimation, Input, Neutral, Regions, WhiteBalanceRendering
from ..schemas.responses import AnalyzeResult, SurfacesResult, WhiteBalanceResult
from ..schemas.forms import form
from ..settings import Settings, get_settings
from ..surfaces import regions_of, surfaces_answer, surfaces_csv
from ..white import as_shot_temperature_tint, with_white
from ..workers import run_heavy, work_slots

router = APIRouter(prefix="/v1")


class LargeChunkFileResponse(FileResponse):
    """A :class:`FileResponse` read and sent in 1 MiB chunks. Starlette's
    64 KiB made a 144 MB TIFF answer some 2,300 file reads handed to a
    thread and as many ASGI messages: more than half of the request's time
    (issue 19; 1 MiB sends it in about the time 4 or 16 MiB do, with a
    quarter of their memory). A chunk is in memory only while it is sent."""

    chunk_size = 1024 * 1024


class TemporaryFileResponse(LargeChunkFileResponse):
    """A :class:`LargeChunkFileResponse` of a temporary file, removed when
    the response ends however it ends: sent, the client gone, or the send
    given up after ``WANDELL_SEND_TIMEOUT`` (:class:`service.limits.SendDeadlineMiddleware`).
    A background task would run only after a complete send, so a reader
    that stopped reading kept the file for ever (issue 28)."""

    async def __call__(self, scope, receive, send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.path)


#: The form fields of each endpoint, from the option models (service.schemas).
_ANALYZE = form(AnalyzeEstimation)
_NEUTRAL = form(Neutral)
_WB_ESTIMATION = form(AnalyzeEstimation)
_WB_RENDERING = form(WhiteBalanceRendering, choices={"format": tuple(FORMATS)},
                     describe={"format": "tiff (16-bit), png (8-bit), png16, jpeg, or xmp: a Camera Raw sidecar "
                                         "(crs:WhiteBalance=Custom, Temperature, Tint) to apply the estimate to "
                                         "the original RAW in another editor, or dng: the RAW as a DNG with that "
                                         "white balance inside (a DNG's copy, its raw data untouched; another "
                                         "RAW's raw data written as a DNG), what Lightroom reads for a DNG"})
# every estimation field of /v1/analyze: the light the surfaces are estimated under is the one /v1/analyze
# answers for the same fields (the page's picture and its "read a surface" agree). quality was refused until
# probe round 8, region_size, surface_dim, light_dim and light_model until round 8b (422 unknown_field), though
# each changes the light (the map's regions, the literal method's models, the light's spectrum model)
_SURFACES_ESTIMATION = form(AnalyzeEstimation)
_REGIONS = form(Regions)
_INPUT = form(Input)

_FILE = File(..., description="RAW file (DNG, CR2, NEF, ARW, ... anything LibRaw reads) or linear 16-bit TIFF/PNG")
_SENS = File(None, description="optional camera sensitivities CSV: wavelength, one column per channel")


async def _inputs(file, sensitivities, settings):
    """The upload, unread until its work has a slot (:class:`service.deps.Upload`), and the
    sensitivities CSV's bytes."""
    data = await checked_upload(file, settings)
    sens = await read_upload(sensitivities, settings, "sensitivities") if sensitivities is not None else None
    return data, sens


def analyze_upload(data, filename, sens, camera, method, opts, settings, neutral=None,
                   display_referred="linearise", render=False):
    """Decode, choose the camera, estimate, or take the user's neutral
    surface as the light (:func:`service.pipeline.analyze`); ``render``:
    the corrected image follows (the RAW's mosaic is kept for it)."""
    return pipeline.analyze(data, filename, settings, camera=camera, sensitivities=sens, method=method,
                            options=opts, neutral=neutral, display_referred=display_referred, keep_mosaic=render)


@router.post("/analyze", response_model=AnalyzeResult)
async def analyze(request: Request, file: UploadFile = _FILE, sensitivities: UploadFile | None = _SENS,
                  est: AnalyzeEstimation = Depends(_ANALYZE), nt: Neutral = Depends(_NEUTRAL),
                  inp: Input = Depends(_INPUT), settings: Settings = Depends(get_settings)):
    """Estimate the scene light: camera RGB, white-balance multipliers,
    relative spectrum, CCT/Duv, the method that ran, diagnostics, timings.
    With ``neutral`` the light is the one of that surface instead (method
    ``neutral-surface``, ``neutral`` says where, how many cells and its
    angle to the estimate)."""
    t0 = time.perf_counter()
    opts, where = est.estimate_kwargs(), nt.neutral
    data, sens = await _inputs(file, sensitivities, settings)
    decoded, run = await run_heavy(analyze_upload, data, file.filename, sens, est.camera, est.method, opts,
                                   settings, where, inp.display_referred, request=request)
    body = pipeline.analysis_json(run, decoded)
    if "as_shot" in body:     # the camera's own white on the scale of the estimate's Temperature/Tint
        body["as_shot"].update(as_shot_temperature_tint(decoded, run))
    body["timings_ms"]["total"] = (time.perf_counter() - t0) * 1e3
    return JSONResponse(clean(body))


def _analyzed_for_sidecar(data, filename, sens, camera, method, opts, settings, neutral, display_referred,
                          dng: bool):
    """:func:`analyze_upload` for ``format=xmp`` / ``dng``; for ``dng``, 422
    ``not_a_raw`` for a file that cannot become one, before any white is
    chosen (probe round 6)."""
    decoded, run = analyze_upload(data, filename, sens, camera, method, opts, settings, neutral, display_referred)
    if dng:
        pipeline.dng_possible(data, decoded)
    return decoded, run


def _with_white(decoded, run, white: str):
    """The run whose light renders the image (:func:`service.white.with_white`):
    the estimate (or the user's neutral surface), the file's own as-shot
    white (the same rendering, for a side-by-side download), or a white
    given as Temperature/Tint."""
    return with_white(decoded, run, white)


def _white_balance_sync(data, filename, sens, camera, method, opts, target, output, fmt, settings,
                        white="estimate", exposure=None, neutral=None, display_referred="linearise"):
    decoded, run = analyze_upload(data, filename, sens, camera, method, opts, settings, neutral, display_referred,
                                  render=True)
    del data
    run = _with_white(decoded, run, white)
    kw = dict(target=target, output=output, fmt=fmt, surface_basis=opts.get("surface_basis"), white=white,
              exposure=exposure)
    if fmt.encoder == "tiff" and held_answers.take():
        # a 16-bit TIFF is its header and then the pixels as they are: sent
        # from memory, not a 144 MB file written and read back (issue 19);
        # at most as many such answers held at once as there are work slots
        # (a slow reader keeps its image after its slot is free), beyond
        # that the answer is a file in TMPDIR as PNG and JPEG answers are
        try:
            out, M, info, meta = pipeline.render_corrected(decoded, run, **kw)
            t0 = time.perf_counter()
            head = pipeline.tiff_head(out, meta)
        except BaseException:
            held_answers.give()
            raise
        if head is not None:
            run.timings_ms["encode"] = (time.perf_counter() - t0) * 1e3
            release = held_answers.releaser()      # given back when the answer is sent (or let go of)
            weakref.finalize(out, release)
            return decoded, run, M, (head, out, release), info
        held_answers.give()
        with temp_output(prefix="wb-", suffix=".tiff") as path:
            pipeline.encode_image(out, "tiff", path, meta=meta)
        run.timings_ms["encode"] = (time.perf_counter() - t0) * 1e3
        return decoded, run, M, path, info
    with temp_output(prefix="wb-", suffix="." + fmt.encoder) as path:
        M, info = pipeline.write_corrected(decoded, run, path, **kw)
    return decoded, run, M, path, info


class _HeldAnswers:
    """How many TIFF answers are held in memory (their corrected images,
    6 bytes a pixel, until the client has read them): at most
    ``max_concurrent_work`` (the number of work slots) at once, so what
    slow readers hold is bounded by what the work itself may hold."""

    def __init__(self):
        self.n = 0
        self._lock = threading.Lock()

    def limit(self) -> int:
        return work_slots()

    def take(self) -> bool:
        with self._lock:
            if self.n >= self.limit():
                return False
            self.n += 1
            return True

    def give(self) -> None:
        with self._lock:
            self.n = max(0, self.n - 1)

    def releaser(self):
        """A function that gives one place back the first time it is called
        and does nothing after: the answer's stream calls it when the client
        has read it (or the stream is closed), and a finalizer on the image
        calls it too in case the stream never ran, so a place is given back
        exactly once, and not only when the garbage collector gets to the
        image (a reference cycle could keep it for a while)."""
        lock, done = threading.Lock(), []

        def release() -> None:
            with lock:
                if done:
                    return
                done.append(True)
            self.give()

        return release


held_answers = _HeldAnswers()


#: bytes of the pixels per message of a TIFF answer sent from memory (as
#: LargeChunkFileResponse's chunks)
MEMORY_CHUNK = 1024 * 1024


async def _from_memory(head: bytes, img, release=None):
    """``head`` then ``img``'s bytes in C order, in about 1 MiB pieces (views
    when ``img`` is contiguous, a copy of the piece's rows when it is a crop);
    ``release()`` once the last piece is sent or the stream is closed."""
    import numpy as np

    try:
        yield head
        rows = max(1, MEMORY_CHUNK // max(1, img[:1].nbytes))
        for r in range(0, img.shape[0], rows):
            yield np.ascontiguousarray(img[r:r + rows]).data.cast("B")
    finally:
        if release is not None:
            release()


@contextlib.contextmanager
def temp_output(**kw):
    """A temporary file in TMPDIR for an output to be streamed: removed if
    anything fails while it is written, and a full file system (ENOSPC,
    EDQUOT) is a 507 ``insufficient_storage``, not a 500."""
    try:
        fd, path = tempfile.mkstemp(**kw)
    except OSError as e:
        if disk_full(e):
            raise ServiceError(507, "insufficient_storage", INSUFFICIENT_STORAGE) from None
        raise
    os.close(fd)
    try:
        yield path
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(path)
        if disk_full(e):
            raise ServiceError(507, "insufficient_storage", INSUFFICIENT_STORAGE) from None
        raise


@router.post("/white-balance", responses={200: {"model": WhiteBalanceResult}})
async def white_balance(request: Request, file: UploadFile = _FILE, sensitivities: UploadFile | None = _SENS,
                        est: AnalyzeEstimation = Depends(_WB_ESTIMATION), rend: WhiteBalanceRendering = Depends(_WB_RENDERING),
                        nt: Neutral = Depends(_NEUTRAL), inp: Input = Depends(_INPUT),
                        settings: Settings = Depends(get_settings)):
    """The corrected image at full resolution (one 3x3 matrix per pixel
    from camera RGB to the display), with the estimate in the
    ``X-Illuminant`` header (JSON)."""
    t0 = time.perf_counter()
    camera, method, opts = est.camera, est.method, est.estimate_kwargs()
    target, output, white, response, ev, where = (rend.target, rend.output, rend.white, rend.response,
                                                  rend.exposure, nt.neutral)
    fmt = FORMATS[rend.format]
    if where is not None and white != "estimate":   # as-shot, or a Temperature/Tint
        raise ServiceError(422, "invalid_parameter", "neutral fixes the white from a surface; it cannot be "
                           f"combined with white={white!r}")
    data, sens = await _inputs(file, sensitivities, settings)
    if fmt.encoder in ("xmp", "dng") and response != "json":   # response=json: the estimate whatever the format
        decoded, run = await run_heavy(_analyzed_for_sidecar, data, file.filename, sens, camera, method, opts,
                                       settings, where, inp.display_referred, fmt.encoder == "dng", request=request)
        run = _with_white(decoded, run, white)
        text, _, summary = pipeline.xmp_sidecar(decoded, run)
        stem = os.path.splitext(download_name(file.filename, "image"))[0] or "image"
        body = text if fmt.encoder == "xmp" else await run_heavy(pipeline.white_balanced_dng, data, decoded, text,
                                                                  summary["camera_rgb"], request=request)
        return Response(body, media_type=MEDIA_TYPES[fmt.encoder],
                        headers={"Content-Disposition": content_disposition(f"{stem}.{fmt.extension}",
                                                                            default="image"),
                                 "X-Illuminant": json.dumps(clean(summary), separators=(",", ":"))})
    if response == "json":
        decoded, run = await run_heavy(analyze_upload, data, file.filename, sens, camera, method, opts, settings,
                                       where, inp.display_referred, request=request)
        run = _with_white(decoded, run, white)
        M, info = pipeline.correction_matrix(run, target, output, opts.get("surface_basis"), decoded=decoded,
                                             exposure=ev)
        body = pipeline.analysis_json(run, decoded)
        if "as_shot" in body:     # as /v1/analyze answers it
            body["as_shot"].update(as_shot_temperature_tint(decoded, run))
        body["correction_matrix"] = M.tolist()
        body["rendering"] = pipeline.rendering_json(info)
        return JSONResponse(clean(body))
    decoded, run, M, path, info = await run_heavy(_white_balance_sync, data, file.filename, sens, camera,
                                                  method, opts, target, output, fmt, settings, white, ev,
                                                  where, inp.display_referred, request=request)
    body = pipeline.analysis_json(run, decoded)
    body["timings_ms"]["total"] = (time.perf_counter() - t0) * 1e3
    header = {k: body[k] for k in ("method", "camera", "warnings", "timings_ms")}
    header["illuminant"] = {k: v for k, v in body["illuminant"].items() if k not in ("wavelengths", "spectrum")}
    header["correction_matrix"] = M.tolist()
    header["rendering"] = pipeline.rendering_json(info)
    header["white"] = "neutral" if where is not None else white
    header["lights"] = body["lights"]
    header.update(pipeline.confidence_json(run.estimate))   # the flag, as diagnostics has it (probe round 8)
    if "neutral" in body:
        header["neutral"] = body["neutral"]
    headers = {"X-Illuminant": json.dumps(clean(header), separators=(",", ":")),
               "Content-Disposition": content_disposition(
                   f'{"as-shot" if white == "as-shot" else "corrected"}.{fmt.extension}', "inline")}
    if isinstance(path, tuple):            # a TIFF: its header, then the corrected image from memory
        head, img, release = path
        headers["Content-Length"] = str(len(head) + img.nbytes)
        return StreamingResponse(_from_memory(head, img, release), media_type=MEDIA_TYPES[fmt.encoder],
                                 headers=headers)
    # streamed from a temporary file (deleted after sending): the encoded
    # image never sits in memory next to the decoded one
    return TemporaryFileResponse(path, media_type=MEDIA_TYPES[fmt.encoder], headers=headers)


@router.post("/surfaces", response_model=SurfacesResult,
             responses={200: {"content": {"text/csv": {"schema": {"type": "string"}}},
                              "description": "JSON (format=json), or CSV (format=csv): kind, where, warnings, "
                                             "one column per wavelength, expected_rmse, then the band's standard "
                                             "deviation per wavelength (std <nm>)"}})
async def surfaces(request: Request, file: UploadFile = _FILE, sensitivities: UploadFile | None = _SENS,
                   est: AnalyzeEstimation = Depends(_SURFACES_ESTIMATION), regions: Regions = Depends(_REGIONS),
                   inp: Input = Depends(_INPUT), settings: Settings = Depends(get_settings)):
    """Reflectance spectra at points, rectangle means or a coarse grid, with
    per-estimate warnings. At most ``WANDELL_MAX_SURFACE_REGIONS`` points,
    rectangles and grid cells together (413 ``too_many_regions``); a
    rectangle costs the same whatever its area (a summed-area table).
    ``metamers=true`` adds each surface's metamer set (at most 64 surfaces,
    about 90 ms each)."""
    camera, method, format = est.camera, est.method, regions.format
    where = regions_of(regions, settings.max_surface_regions)      # the limits before the upload is read
    opts = est.estimate_kwargs()
    data, sens = await _inputs(file, sensitivities, settings)

    def work(data):
        decoded, run = analyze_upload(data, file.filename, sens, camera, method, opts, settings,
                                      display_referred=inp.display_referred)
        res = surfaces_answer(decoded, run, regions, where, opts)
        # the body is rendered here too, not on the event loop (10,000 entries are ~1 MB)
        if format == "csv":
            return Response(surfaces_csv(res), media_type="text/csv")
        return JSONResponse(clean(res))

    return await run_heavy(work, data, request=request)
