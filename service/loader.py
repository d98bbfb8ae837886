"""The public loader: a camera file read into exactly what the service
analyses (issue 29, item 2)::

    from recovery import estimate_illuminant
    from service.loader import load

    photo = load("IMG_0001.dng")
    est = estimate_illuminant(photo.linear, photo.camera, mask=photo.mask)

``est`` is the light ``POST /v1/analyze`` answers for the same file with
the same options (``tests/test_loader.py`` checks it on the real
CinemaDNG). :func:`load` runs the service's own steps, nothing else: the
decode of :func:`service.decode.decode_upload` (LibRaw through rawpy for a
RAW, the black and white levels from the file, 2x2 CFA cells binned without
demosaic and block-averaged to ``WANDELL_ESTIMATION_PIXELS``; a linear 16-bit
TIFF/PNG linearised through its ICC profile when it says it is rendered), the
camera the file describes (:func:`recovery.cameras.resolve_camera`: a
measured camera matched by make and model, else the file's colour matrix),
and the block averaging of the estimate (:func:`recovery.analysis_pixels` of
``quality``, as :func:`service.estimation.run_estimate`).

Why here and not in :mod:`recovery`: reading files is I/O through LibRaw,
tifffile and ICC profiles, which :mod:`service.decode` does for the REST API,
the CLI and the batches; :mod:`recovery` stays the numerical core of pure
functions on arrays, and imports point down only (``service`` ->
``recovery`` -> ``models``). The loader is importable without the web stack
(no FastAPI is imported).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np

__all__ = ["Photo", "load"]

#: LibRaw's ``flip`` codes (what :attr:`Photo.orientation` holds) in words.
ORIENTATIONS = {0: "as stored", 3: "rotated 180 degrees", 5: "rotated 90 degrees counter-clockwise",
                6: "rotated 90 degrees clockwise"}


@dataclass
class Photo:
    """A camera file as the service analyses it.

    Attributes
    ----------
    linear : (h, w, C) float32
        Linear camera RGB, black subtracted, 1.0 = saturation, the file's
        orientation applied: the image the estimators receive (a RAW's 2x2
        CFA cells binned, block-averaged to at most
        ``recovery.analysis_pixels(quality)`` pixels; 250,000 by default).
    mask : (h, w) bool
        True where a pixel is used: False where any sample of its block is
        saturated or not finite (dark pixels are left out by the estimators
        themselves).
    saturated : (h', w') bool
        The saturation mask at the decode's resolution (before the block
        averaging of ``quality``).
    camera : recovery.Camera
        The camera as the file describes it (measured, matrix-derived,
        uploaded or generic: ``camera.source``).
    camera_warnings : list of str
        Why the camera is approximate, when it is.
    as_shot : (3,) float64 or None
        Camera RGB of the camera's own (as-shot) white, green = 1.
    orientation : int
        LibRaw's flip code applied to the pixels (:data:`ORIENTATIONS`).
    full_shape : (H, W)
        The full-resolution (demosaicked, oriented) image's shape: the frame
        of the service's ``neutral`` and ``points``.
    block_factor : int
        ``linear`` is the decode's analysis image averaged in blocks of this
        side.
    kind, make, model : str
        ``raw``, ``tiff`` or ``png``; the file's make and model.
    warnings : list of str
        What the decode says the user should know.
    decoded : service.decode.DecodedImage
        The decode itself (its ``full_linear()`` demosaics the whole image),
        for the service's rendering functions.
    """

    linear: np.ndarray
    mask: np.ndarray
    saturated: np.ndarray
    camera: object
    camera_warnings: list
    as_shot: np.ndarray | None
    orientation: int
    full_shape: tuple
    block_factor: int
    kind: str
    make: str | None
    model: str | None
    warnings: list = field(default_factory=list)
    decoded: object = field(default=None, repr=False)


def load(source, *, camera: str | None = None, sensitivities: bytes | str | os.PathLike | None = None,
         quality: str | None = None, display_referred: str = "linearise", max_pixels: int = 120_000_000,
         estimation_pixels: int = 1_000_000, name: str | None = None) -> Photo:
    """Read a RAW (anything LibRaw reads: DNG, CR2, NEF, ARW, ...) or a linear
    16-bit TIFF/PNG into what the service analyses (see the module doc).

    Parameters
    ----------
    source : str, os.PathLike or bytes
        The file's path, or its bytes.
    camera : str, optional
        As the REST field ``camera``: a measured camera's name, ``"matrix"``
        or ``"generic"``; default: chosen from the file.
    sensitivities : bytes or path, optional
        A camera sensitivities CSV (wavelength, one column per channel), as
        the REST field ``sensitivities``.
    quality : {None, "fast", "balanced", "accurate"}
        The analysis resolution of that preset (pass the same ``quality`` to
        :func:`recovery.estimate_illuminant` for its other knobs).
    display_referred : {"linearise", "refuse"}
        A TIFF/PNG whose colour tags say it is rendered: linearised through
        its profile (with a warning), or refused.
    max_pixels, estimation_pixels : int
        ``WANDELL_MAX_PIXELS`` and ``WANDELL_ESTIMATION_PIXELS`` (their
        defaults).
    name : str, optional
        The file name used in messages (default: the path's).

    Returns
    -------
    Photo

    Raises
    ------
    service.errors.ServiceError
        With ``status``, ``error`` and ``detail`` as the REST API answers
        them (415 not a format the service reads, 422 corrupt, ...).
    recovery.errors.RecoveryError
        An unknown camera or unusable sensitivities.
    """
    from recovery import analysis_pixels
    from recovery.cameras import resolve_camera
    from recovery.resolution import block_average

    from .decode import decode_upload

    if isinstance(source, (bytes, bytearray, memoryview)):
        data = bytes(source)
    else:
        name = name or os.path.basename(os.fspath(source))
        with open(source, "rb") as f:
            data = f.read()
    if sensitivities is not None and not isinstance(sensitivities, (bytes, bytearray)):
        with open(sensitivities, "rb") as f:
            sensitivities = f.read()
    decoded = decode_upload(data, name, max_pixels=max_pixels, estimation_pixels=estimation_pixels,
                            display_referred=display_referred)
    cam, cam_warnings = resolve_camera(decoded, camera, sensitivities)
    img, mask, f = block_average(decoded.estimation, ~decoded.saturated, analysis_pixels(quality))
    if mask is None:                          # nothing saturated: every pixel is used
        mask = np.ones(img.shape[:2], bool)
    asn = decoded.as_shot_neutral
    return Photo(linear=img, mask=mask, saturated=decoded.saturated, camera=cam, camera_warnings=list(cam_warnings),
                 as_shot=None if asn is None else np.asarray(asn, float),
                 orientation=int((decoded._postprocess or {}).get("user_flip", 0) or 0),
                 full_shape=tuple(decoded.full_shape), block_factor=int(f), kind=decoded.kind, make=decoded.make,
                 model=decoded.model, warnings=list(decoded.warnings), decoded=decoded)
