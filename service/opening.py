"""An upload decoded and its camera chosen, and the estimate run on it:
the first steps of :mod:`service.pipeline` (which re-exports every name),
with the full-resolution demosaic started ahead on a thread."""

from __future__ import annotations

import time

import numpy as np

from .estimation import run_estimate, with_neutral


def decode(data: bytes, filename: str | None, limits, display_referred: str = "linearise",
           keep_mosaic: bool = False):
    """The upload decoded (:func:`service.decode.decode_upload`) within
    ``limits`` (anything with ``max_pixels`` and ``estimation_pixels``: the
    settings, a batch item); ``display_referred``: linearise or refuse a
    TIFF/PNG whose colour tags say it is rendered (:mod:`service.decode.icc`);
    ``keep_mosaic``: the caller renders the full image next (a RAW's mosaic
    is kept for it instead of being unpacked again)."""
    from . import decode

    return decode.decode_upload(data, filename, max_pixels=limits.max_pixels,
                               estimation_pixels=limits.estimation_pixels, display_referred=display_referred,
                               keep_mosaic=keep_mosaic)


def open_image(data: bytes, filename: str | None, limits, camera: str | None = None,
               sensitivities: bytes | None = None, prefetch: bool = False, display_referred: str = "linearise",
               keep_mosaic: bool | None = None):
    """Decode and choose the camera (:func:`recovery.cameras.resolve_camera`):
    ``(decoded, camera, warnings, milliseconds)``. With ``prefetch`` (a
    caller that renders the full image next) the demosaic starts at once on
    a thread (:func:`prefetch_full_linear`). ``keep_mosaic`` (default:
    ``prefetch``): the full image is rendered later (:func:`decode`)."""
    from recovery.cameras import resolve_camera

    t0 = time.perf_counter()
    decoded = decode(data, filename, limits, display_referred, prefetch if keep_mosaic is None else keep_mosaic)
    if prefetch:
        prefetch_full_linear(decoded)
    try:
        cam, warns = resolve_camera(decoded, camera, sensitivities)
    except BaseException:
        drain_prefetch(decoded)
        raise
    return decoded, cam, warns, (time.perf_counter() - t0) * 1e3


def prefetch_full_linear(decoded) -> None:
    """Start the full-resolution linear image (``decoded.full_linear("uint16")``,
    the demosaic) on a thread while the caller chooses the camera and
    estimates the light: LibRaw's unpack and OpenCV's demosaic release the
    GIL, the estimate (and a fresh process's imports) need it, so the two
    overlap on two cores. :func:`render_full` takes the result (once: it is
    corrected in place); errors are raised there, as without the thread."""
    if getattr(decoded, "_full_future", None) is not None:
        return
    import threading
    from concurrent.futures import Future

    fut: Future = Future()

    def run():
        try:
            fut.set_result(decoded.full_linear("uint16"))
        except BaseException as exc:  # noqa: BLE001 - handed to whoever takes the result
            fut.set_exception(exc)

    decoded._full_future = fut
    threading.Thread(target=run, name="wandell-demosaic", daemon=True).start()


def drain_prefetch(decoded) -> None:
    """Wait for a prefetched demosaic nobody will use (the estimate failed)
    and drop it, so no work outlives the request that started it."""
    fut = decoded.__dict__.pop("_full_future", None) if decoded is not None else None
    if fut is not None:
        fut.exception()


def _full_linear_u16(decoded) -> np.ndarray:
    fut = decoded.__dict__.pop("_full_future", None)
    return fut.result() if fut is not None else decoded.full_linear("uint16")


def analyze(data: bytes, filename: str | None, limits, *, camera: str | None = None,
            sensitivities: bytes | None = None, method: str = "auto", options: dict | None = None,
            neutral: list[int] | None = None, prefetch: bool = False, display_referred: str = "linearise",
            keep_mosaic: bool | None = None):
    """Decode, choose the camera, estimate the light: ``(decoded, run)``.
    With ``neutral`` (a point or rectangle the user says is white,
    :func:`service.options.parse_neutral`) the light is that surface's
    (:func:`with_neutral`), rendered like an estimate. ``prefetch``: the
    caller renders next, demosaic meanwhile (:func:`prefetch_full_linear`);
    ``keep_mosaic``: it renders later (:func:`open_image`)."""
    decoded, cam, warns, ms = open_image(data, filename, limits, camera, sensitivities, prefetch=prefetch,
                                         display_referred=display_referred, keep_mosaic=keep_mosaic)
    try:
        run = run_estimate(decoded, cam, warns, method=method, options=options or {})
        run.timings_ms["decode"] = ms
        if neutral is not None:
            run = with_neutral(decoded, run, neutral)
    except BaseException:
        drain_prefetch(decoded)
        raise
    return decoded, run


def analyze_file(path: str, limits, *, name: str | None = None, **kw):
    """:func:`analyze` of a file on disk."""
    import os

    with open(path, "rb") as f:
        data = f.read()
    return analyze(data, name or os.path.basename(path), limits, **kw)
