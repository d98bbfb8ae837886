"""The service's one pipeline: upload -> decode -> camera -> estimate ->
correction matrix -> apply -> encode, and the JSON of each step.

The REST routers (:mod:`service.routers.analysis`, :mod:`service.routers.web`),
the batch worker (:mod:`service.jobs`) and the CLI (:mod:`service.cli`) all
go through :func:`analyze` (decode + choose the camera + estimate) and
:func:`write_corrected` (matrix, apply, encode to a file). Thin by design:
every number comes from :mod:`recovery` (the camera from
:mod:`recovery.cameras`, the matrix with its exposure rule from
:func:`recovery.synthesis.correction_matrix`); this module chooses
resolutions, applies the one 3x3 matrix per pixel (Wandell 1985, Fig. 6: for
a fixed light camera RGB to display RGB is one matrix) in chunks, and
encodes. Its errors are :class:`~service.errors.ServiceError`; recovery
errors pass through (the edges map them, :func:`service.errors.service_error`).

Analysis resolution, the one rule: a RAW is binned to 2x2 CFA cells and
area-averaged to at most ``WANDELL_ESTIMATION_PIXELS`` (default 1 megapixel,
:attr:`service.settings.Settings.estimation_pixels`): that is the full
analysis resolution. The estimate then runs on that image block-averaged to
:func:`recovery.analysis_pixels` of the ``quality`` preset: 4096 pixels for
``fast``, 65536 for ``balanced``, all of it for ``accurate``, and
:data:`recovery.DEFAULT_ANALYSIS_PIXELS` (250,000) when no quality is given.
"""

from __future__ import annotations

import io
import json
import time
from dataclasses import dataclass, field

import numpy as np

from recovery import Camera, IlluminantEstimate, analysis_pixels, angular_error, estimate_illuminant
from recovery.api import resolve_model, surfaces_from_estimate
from recovery.resolution import block_average
from recovery.synthesis import correction_matrix as _recovery_correction_matrix, display_curve, highlight_white, \
    output_space
from recovery.synthesis import exposure_gain as _recovery_exposure_gain


from .errors import ServiceError
from .options import FORMATS, MEDIA_TYPES, Format


@dataclass
class EstimateRun:
    estimate: IlluminantEstimate
    camera: Camera
    camera_warnings: list
    timings_ms: dict = field(default_factory=dict)
    factor: int = 1
    neutral: dict | None = None     # set by with_neutral: where the user's white came from
    requested_method: str | None = None


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


def run_estimate(decoded, camera: Camera, camera_warnings: list, *, method: str, options: dict,
                 pixels: int | None = None) -> EstimateRun:
    """Estimate the light on the estimation image of an upload, block-
    averaged to the analysis resolution of ``options["quality"]``
    (:func:`recovery.analysis_pixels`; ``pixels`` overrides it), saturated
    cells excluded. Block averaging leaves the subspace method unchanged:
    mixtures of surfaces under one light stay in the same subspace (eq. 29)."""
    t0 = time.perf_counter()
    if pixels is None:
        pixels = analysis_pixels(options.get("quality"))
    img, mask, f = block_average(decoded.estimation, ~decoded.saturated, pixels)
    est = estimate_illuminant(img, camera, method, mask=mask, **options)
    t1 = time.perf_counter()
    run = EstimateRun(est, camera, list(camera_warnings), {"estimate": (t1 - t0) * 1e3}, f,
                      requested_method=method)
    if camera.source == "generic":
        generic_cross_check(decoded, run, img, mask, method, options)
        run.timings_ms["matrix_cross_check"] = (time.perf_counter() - t1) * 1e3
    return run


#: The angle (degrees) at which a white-balance error is commonly taken to
#: become visible (Hordley & Finlayson 2006 use 2-3 degrees for "good";
#: colour-constancy benchmarks quote 3): the generic camera's confidence is
#: halved when its estimate is this far from the colour matrix's.
VISIBLE_WB_ERROR_DEG = 3.0


def generic_cross_check(decoded, run: EstimateRun, img, mask, method: str, options: dict) -> None:
    """``camera=generic`` on a file that has a colour matrix: estimate again
    with the matrix-derived camera (same image, mask, method and options),
    report the angle between the two lights (both are camera RGB of this
    sensor) in ``diagnostics["generic_vs_matrix_deg"]``, scale the reported
    confidence by ``1 / (1 + (angle / 3 deg)^2)`` (1 when they agree, 1/2
    at a just-visible 3 degrees, about 0.1 at 9 degrees; a method that
    reports no confidence gets this factor as its confidence) and warn
    when the angle exceeds 3 degrees. Nothing happens for a file without a
    matrix (nothing to compare with)."""
    from recovery.cameras import resolve_camera
    from recovery.errors import RecoveryError

    try:
        mcam, _ = resolve_camera(decoded, "matrix")
    except RecoveryError:
        return
    if mcam.source != "matrix-derived" or mcam.channels != run.camera.channels:
        return
    ref = estimate_illuminant(img, mcam, method, mask=mask, **options)
    ang = float(angular_error(run.estimate.rgb, ref.rgb))
    factor = 1.0 / (1.0 + (ang / VISIBLE_WB_ERROR_DEG) ** 2)
    d = run.estimate.diagnostics
    before = d.get("confidence")
    d["generic_vs_matrix_deg"] = ang
    d["matrix_estimate_camera_rgb"] = (ref.rgb / np.linalg.norm(ref.rgb)).tolist()
    d["confidence_factor_generic"] = factor
    if isinstance(before, (int, float)) and np.isfinite(before):
        d["confidence_before_cross_check"] = float(before)
        d["confidence"] = float(before) * factor
    else:
        d["confidence"] = factor
    msg = (f"camera=generic: this estimate is {ang:.1f} degrees from the one made with the file's colour matrix "
           f"(confidence x {factor:.2f})")
    if ang > VISIBLE_WB_ERROR_DEG:
        run.estimate.warnings.append(msg + "; camera=matrix (the default for this file) is the better choice")
    else:
        d["generic_cross_check"] = msg


#: The literal method's own failure tests (recovery.api): subspace fit above
#: its tolerance, a poorly determined light, a fallback.
LITERAL_FIT_TOLERANCE = 0.1
LITERAL_NULL_RATIO = 0.5


def method_failure(est: IlluminantEstimate, requested: str | None = None) -> dict | None:
    """When the literal Maloney-Wandell method was asked for (or ran) and
    its own diagnostics say it failed: ``{"method", "reasons"}``, else
    ``None``. The page flags the corrected image with it."""
    d = est.diagnostics or {}
    if "maloney-wandell" not in (requested, est.method):
        return None
    reasons = []
    if d.get("failure"):
        reasons.append(f"it could not run ({d['failure']}); {est.method} was used instead")
    fit = d.get("subspace_fit_ratio")
    if isinstance(fit, (int, float)) and np.isfinite(fit) and fit > LITERAL_FIT_TOLERANCE:
        reasons.append(f"the data are not confined to a {d.get('D(S)', '?')}-dimensional surface subspace "
                       f"(s ratio {fit:.3g} > {LITERAL_FIT_TOLERANCE:g})")
    nr = d.get("pi_null_ratio")
    if isinstance(nr, (int, float)) and np.isfinite(nr) and nr > LITERAL_NULL_RATIO:
        reasons.append(f"the light is poorly determined (null-space ratio {nr:.3g} > {LITERAL_NULL_RATIO:g})")
    return {"method": "maloney-wandell", "reasons": reasons} if reasons else None


def run_with_white(run: EstimateRun, camera_rgb, method: str) -> EstimateRun:
    """The same image and camera with the light fixed to a given camera RGB
    (the file's as-shot white, or a surface the user says is white): the
    spectrum is the 3-term daylight-model light with that response (as the
    peer estimators do), so both renderings (DNG-matrix and spectral) work."""
    from recovery.api import _finish, _spectrum_from_rgb

    rgb = np.asarray(camera_rgb, float)
    if rgb.shape != (run.camera.channels,) or not np.all(np.isfinite(rgb)) or not np.all(rgb > 0):
        raise ServiceError(422, "invalid_parameter", f"a white must be {run.camera.channels} positive camera "
                           f"values, got {np.round(rgb, 6).tolist()}")
    model = resolve_model(None, "light", min(3, run.camera.channels), run.camera.wavelengths)
    w, spd = _spectrum_from_rgb(rgb, run.camera, model)
    est = _finish(rgb, spd, w, run.camera, model, method,
                  {"light_model": model.name + " (spectrum fitted to the given white)"}, [])
    return EstimateRun(est, run.camera, list(run.camera_warnings), dict(run.timings_ms), run.factor)


#: Above this angle between the light used and the file's as-shot white the answer warns.
AS_SHOT_WARN_DEG = 5.0


#: A surface chosen as white whose brightest channel averages less than
#: this fraction of the white level gets a low-signal warning (a 14-bit
#: sensor keeps about 800 levels there, and a 0.1 % black-level error is
#: already a 2 % colour error).
NEUTRAL_LOW_SIGNAL = 0.05


def neutral_white(decoded, where: list[int]) -> tuple[np.ndarray, dict]:
    """The light's camera RGB from a surface the user says is white or grey:
    the mean camera RGB of the unclipped cells of the estimation image under
    the point or rectangle ``where`` (full-resolution pixels, as
    :func:`surfaces_at`). 422 when it is outside the image or every cell
    there is clipped or black."""
    H, W = decoded.full_shape
    r0, c0, r1, c1 = (where[0], where[1], where[0] + 1, where[1] + 1) if len(where) == 2 else where
    if len(where) == 4 and (r0 >= r1 or c0 >= c1):
        bad = " and ".join(x for x, b in ((f"r0 >= r1 ({r0} >= {r1})", r0 >= r1),
                                          (f"c0 >= c1 ({c0} >= {c1})", c0 >= c1)) if b)
        raise ServiceError(422, "invalid_parameter", f"neutral {list(where)} is an inverted or empty rectangle: "
                           f"{bad}; give [r0, c0, r1, c1] with r0 < r1 and c0 < c1 (top-left, then bottom-right, "
                           "exclusive)")
    if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
        raise ServiceError(422, "invalid_parameter", f"neutral {list(where)} is outside the {H}x{W} image: "
                           f"a point needs 0 <= row < {H} and 0 <= col < {W}; a rectangle 0 <= r0 < r1 <= {H} "
                           f"and 0 <= c0 < c1 <= {W}")
    img = decoded.estimation
    h, w = img.shape[:2]
    a0, b0 = min(int(r0 * h / H), h - 1), min(int(c0 * w / W), w - 1)
    a1, b1 = max(a0 + 1, min(h, -(-r1 * h // H))), max(b0 + 1, min(w, -(-c1 * w // W)))
    cells = np.asarray(img[a0:a1, b0:b1], float).reshape(-1, img.shape[-1])
    sat = np.asarray(decoded.saturated[a0:a1, b0:b1]).ravel()
    ok = ~sat & np.all(np.isfinite(cells), axis=1) & np.all(cells > 0, axis=1)
    n_ok = int(ok.sum())
    if n_ok == 0:
        why = "clipped (saturated)" if sat.all() else "clipped or black"
        raise ServiceError(422, "unusable_neutral", f"every pixel of neutral {list(where)} is {why}: choose "
                           "a white or grey surface that is not blown out")
    rgb = cells[ok].mean(axis=0)
    info = {"where": list(where), "cells_used": n_ok, "cells_clipped_or_black": int(ok.size - n_ok),
            "camera_rgb": (rgb / np.linalg.norm(rgb)).tolist(), "level": float(rgb.max())}
    if rgb.max() < NEUTRAL_LOW_SIGNAL:
        info["warning"] = (f"the surface chosen as white is dark: its brightest channel averages "
                           f"{100 * rgb.max():.1f} % of the white level (below {100 * NEUTRAL_LOW_SIGNAL:g} %), "
                           "so its colour is dominated by noise and black-level error; a brighter white or grey "
                           "surface gives a more reliable white")
    return rgb, info


def with_neutral(decoded, run: EstimateRun, where: list[int]) -> EstimateRun:
    """The run whose light is the surface at ``where`` (:func:`neutral_white`),
    rendered the same way as an estimate; ``neutral`` records where it came
    from and its angle to the estimate it replaces."""
    rgb, info = neutral_white(decoded, where)
    if run.estimate is not None:
        info["angle_to_estimate_deg"] = float(angular_error(rgb, run.estimate.rgb))
        info["estimate_method"] = run.estimate.method
    out = run_with_white(run, rgb, "neutral-surface")
    out.neutral = info
    return out


def profile_of(decoded):
    """The file's camera -> XYZ profile (:func:`service.metadata.color_profile`),
    ``None`` without one (TIFF/PNG input, a RAW LibRaw has no matrix for)."""
    from .metadata import color_profile

    return color_profile(decoded) if decoded is not None else None


#: Camera sources whose sensitivities approximate the file's colour matrix
#: (:mod:`recovery.cameras`): their light's chromaticity is read through the
#: file's matrices; measured and uploaded sensitivities see the spectrum.
MATRIX_COLORIMETRY = ("matrix-derived", "generic")


def light_xy(est: IlluminantEstimate, profile=None, camera: Camera | None = None) -> tuple[np.ndarray | None, str]:
    """The chromaticity (CIE 1931 xy) of the estimated light, the one from
    which the temperatures the service reports are computed: the light's
    camera RGB through the file's colour matrices (DNG ``NeutralToXY``, as
    Camera Raw does) when the file has them and the camera's sensitivities
    are only derived from them (``camera`` matrix-derived or generic, or not
    given); else the xy of the estimate's spectrum (CIE 1931 2 degree
    observer; for measured sensitivities that is the better colorimetry).
    ``(xy, basis)``: basis is the profile's source (``"DNG tags"``,
    ``"LibRaw"``) or ``"spectrum"``; ``xy`` is ``None`` for a non-physical
    light."""
    rgb = np.asarray(est.rgb, float)
    if (profile is not None and rgb.shape == (3,) and np.all(np.isfinite(rgb)) and np.all(rgb > 0)
            and (camera is None or camera.source in MATRIX_COLORIMETRY)):
        from recovery.dng_color import neutral_to_xy

        return np.asarray(neutral_to_xy(profile, rgb), float), profile.source
    from models import observer

    spd = np.asarray(est.spectrum, float)
    if not np.all(np.isfinite(spd)) or np.any(spd < -0.01 * np.max(np.abs(spd))):
        return None, "spectrum"
    XYZ = np.clip(spd, 0, None) @ observer("XYZ", est.wavelengths)
    if XYZ[1] <= 0 or XYZ.sum() <= 0:
        return None, "spectrum"
    return XYZ[:2] / XYZ.sum(), "spectrum"


def light_cct_duv(est: IlluminantEstimate, profile=None,
                  camera: Camera | None = None) -> tuple[float | None, float | None]:
    """The one CCT (K) and Duv the service reports for a light (``/v1/analyze``,
    headers, batches, the CLI, the metadata of outputs and XMP sidecars):
    Ohno (2013) on the xy of :func:`light_xy`; ``(None, None)`` when the light
    is not physical or far from the Planckian locus (|Duv| > 0.05, 1000 to
    100000 K, as :meth:`recovery.IlluminantEstimate.cct_duv`)."""
    from models._colour import uv_to_CCT_Ohno2013, xy_to_UCS_uv  # colour-science's, without importing it

    xy, _ = light_xy(est, profile, camera)
    if xy is None:
        return None, None
    try:
        cct, duv = uv_to_CCT_Ohno2013(xy_to_UCS_uv(xy))
    except Exception:
        return None, None
    if not (np.isfinite(cct) and np.isfinite(duv)) or abs(duv) > 0.05 or not 1000 <= cct <= 100000:
        return None, None
    return float(cct), float(duv)


def illuminant_json(est: IlluminantEstimate, profile=None, camera: Camera | None = None) -> dict:
    """The light as JSON: camera RGB, multipliers, spectrum, its CCT/Duv
    (:func:`light_cct_duv`) with the xy and basis they come from
    (:func:`light_xy`), and its Camera Raw Temperature/Tint with theirs
    (:func:`temperature_tint`: always through the file's matrices when it
    has them, the same xy for a matrix-derived camera). ``profile``: the
    file's (:func:`profile_of`); ``camera``: the camera of the estimate."""
    cct, duv = light_cct_duv(est, profile, camera)
    xy, basis = light_xy(est, profile, camera)
    tt = _temperature_tint_xy(est, profile)
    return {
        "camera_rgb": est.rgb.tolist(),
        "wb_multipliers": est.wb_multipliers.tolist(),
        "wavelengths": est.wavelengths.tolist(),
        "spectrum": est.spectrum.tolist(),
        "cct": cct,
        "duv": duv,
        "xy": None if xy is None else [float(xy[0]), float(xy[1])],
        "chromaticity_basis": basis,
        "temperature": tt.get("temperature"),
        "tint": tt.get("tint"),
        "temperature_basis": tt.get("basis"),
    }


def camera_json(camera: Camera) -> dict:
    return {"name": camera.name, "source": camera.source, "channels": camera.channels,
            "approximate": camera.source in ("matrix-derived", "generic"), "notes": list(camera.notes)}


def analysis_json(run: EstimateRun, decoded) -> dict:
    est = run.estimate
    out = {
        "illuminant": illuminant_json(est, profile_of(decoded), run.camera),
        "camera": camera_json(run.camera),
        "method": est.method,
        "diagnostics": dict(est.diagnostics, analysis_block_factor=run.factor),
        "warnings": run.camera_warnings + list(decoded.warnings) + list(est.warnings),
        "timings_ms": dict(run.timings_ms),
        "image": {"kind": decoded.kind, "width": decoded.full_shape[1], "height": decoded.full_shape[0],
                  "make": decoded.make, "model": decoded.model},
    }
    if getattr(decoded, "encoding", None) is not None:   # what a TIFF/PNG's ICC profile or PNG chunks say
        out["image"]["encoding"] = dict(decoded.encoding)
    choice = rendering_choice(run, decoded)
    out["rendering"] = {"rendering": choice["rendering"], "color_source": choice["color_source"]}
    failed = method_failure(est, run.requested_method)
    if failed is not None:
        out["method_failed"] = failed
    lm = est.light_map
    if lm is not None:  # the light at the map's centres, as fractions of the image height and width
        rr, cc = np.meshgrid(lm.centres_r, lm.centres_c, indexing="ij")
        rgb = run.camera.response(lm.spectra_at(rr.ravel(), cc.ravel()))
        rgb = rgb / np.linalg.norm(rgb, axis=1, keepdims=True)
        eh, ew = decoded.estimation.shape[:2]
        out["light_map"] = {"centres_row_fraction": ((lm.centres_r + 0.5) * run.factor / eh).tolist(),
                            "centres_col_fraction": ((lm.centres_c + 0.5) * run.factor / ew).tolist(),
                            "camera_rgb": rgb.reshape(rr.shape + (-1,)).tolist()}
    if decoded.as_shot_neutral is not None and np.all(np.isfinite(decoded.as_shot_neutral)):
        asn = np.asarray(decoded.as_shot_neutral, float)
        ang = float(angular_error(asn, est.rgb))
        out["as_shot"] = {"camera_rgb": (asn / np.linalg.norm(asn)).tolist(), "angle_to_estimate_deg": ang}
        if ang > AS_SHOT_WARN_DEG:
            what = "the white you chose" if run.neutral is not None else "the estimate"
            out["warnings"].append(f"{what} is {ang:.1f} degrees from the camera's own as-shot white (more than "
                                   f"{AS_SHOT_WARN_DEG:g}): check the picture, or use a white surface "
                                   "('neutral') or white=as-shot")
    if run.neutral is not None:
        out["neutral"] = dict(run.neutral)
        if out["neutral"].get("warning"):
            out["warnings"].append(out["neutral"]["warning"])
    return out


def rendering_choice(run: EstimateRun, decoded=None) -> dict:
    """How the corrected image is rendered: ``"dng-matrix"`` (the DNG
    specification's camera -> XYZ pipeline, :mod:`recovery.dng_color`) for a
    camera known only by its colour matrix (DNG tags, or LibRaw's matrix for
    other RAWs), ``"spectral"`` (Wandell 1985, eq. 22-25) for measured,
    uploaded or generic sensitivities."""
    from .metadata import color_profile

    prof = color_profile(decoded) if decoded is not None else None
    if prof is not None and run.camera.source == "matrix-derived":
        return {"rendering": "dng-matrix", "color_source": prof.source, "profile": prof}
    return {"rendering": "spectral", "color_source": run.camera.source, "profile": None}


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
    M, info = _recovery_correction_matrix(cam, est.rgb, est.spectrum, target, space, S,
                                          profile=choice["profile"], tone=tone, exposure=exposure,
                                          image=_estimation_image(decoded))
    info["color_source"] = choice["color_source"] if info["rendering"] == "dng-matrix" else cam.source
    if not np.all(np.isfinite(M)):
        # never a black image (NaN matrix) answered as a success
        raise ServiceError(422, "unrenderable", f"no finite correction from this light to target {target!r} "
                           f"on {output}; choose another target (e.g. D65) or check the estimate")
    return M, info


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


def rendering_json(info: dict) -> dict:
    """The rendering choice and its figures, for headers and JSON bodies."""
    keys = ("rendering", "color_source", "white_xy", "temperature", "tint", "calibration_weight",
            "forward_matrix", "baseline_exposure", "exposure", "tone", "curve", "target_white_xy", "crop", "notes")
    return {k: info[k] for k in keys if k in info}


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
    rgb16 = default_crop(decoded, _full_linear_u16(decoded))
    t1 = time.perf_counter()
    out = apply_matrix_inplace(rgb16, M, info["encoding"], bits, threads=threads, neutral=info.get("neutral"),
                               shoulder=info.get("shoulder"), curve=info.get("curve"), reuse_input=True)
    t2 = time.perf_counter()
    if timings is not None:
        timings.update(demosaic=(t1 - t0) * 1e3, correct=(t2 - t1) * 1e3)
    info["crop"] = [int(out.shape[0]), int(out.shape[1])]
    return out, M, info


def estimate_summary(run: EstimateRun, info: dict | None = None, profile=None, **extra) -> dict:
    """The estimate in short (the ``X-Illuminant`` of an XMP download, the
    ``wandell:`` XMP an output file carries, the XMP sidecar's): method,
    camera RGB, multipliers, CCT/Duv and the xy they come from, the
    confidence when the method reports one, camera name, and the rendering
    when ``info``."""
    est = run.estimate
    cct, duv = light_cct_duv(est, profile, run.camera)
    out = {"method": est.method, "camera_rgb": est.rgb.tolist(), "wb_multipliers": est.wb_multipliers.tolist(),
           "cct": cct, "duv": duv, "camera": run.camera.name}
    if cct is not None:                 # the xy the CCT/Duv come from (light_xy)
        xy, _ = light_xy(est, profile, run.camera)
        out["xy"] = [float(xy[0]), float(xy[1])]
    conf = est.diagnostics.get("confidence")
    if isinstance(conf, (int, float)) and np.isfinite(conf):
        out["confidence"] = float(conf)
    if info:
        out["rendering"] = info.get("rendering")
    out.update(extra)
    return out


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
    without the full-resolution 16-bit image; timing ``render``); anything
    else through the whole image (timings ``demosaic``, ``correct``,
    ``encode``)."""
    from . import strips

    source = None
    if fmt.encoder in STRIP_ENCODERS and getattr(decoded, "_full_future", None) is None:
        source = strips.mosaic_rows(decoded, lambda shape: crop_bounds(decoded, shape))
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


from .correction import (CHUNK_PIXELS, Correction, _encoding_lut, _highlight_code, apply_matrix_inplace,  # noqa: E402,F401,E501 (re-exported)
                         chunk_rows)


def encode_image(img: np.ndarray, fmt: str, path: str | None = None, meta: dict | None = None,
                 threads: int | None = None) -> bytes | None:
    """PNG (8-bit or 16-bit), 16-bit TIFF or 8-bit JPEG of an RGB image, as
    bytes, or written to ``path`` (TIFF straight from the array, no copy).
    PNG and JPEG are encoded in strips on ``threads`` threads
    (:func:`service.encode.png_encode`, :func:`service.encode.jpeg_encode`;
    default: one per CPU).

    ``meta`` (:func:`output_meta`): ``icc`` (profile bytes), ``facts`` (EXIF
    facts, :func:`service.outputs.output_facts`) and ``text`` (PNG text) are
    embedded so other tools read the colours and the source right."""
    meta = meta or {}
    if fmt == "tiff":
        import tifffile

        kw = _tiff_kwargs(meta)
        if path is not None:
            tifffile.imwrite(path, img, photometric="rgb", **kw)
            return None
        buf = io.BytesIO()
        tifffile.imwrite(buf, img, photometric="rgb", **kw)
        return buf.getvalue()
    if fmt == "png" and img.ndim == 3 and img.shape[2] == 3 and img.size:
        from .encode import png_encode

        data = png_encode(img, threads)
    elif fmt == "jpeg" and img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8 and img.size:
        from .encode import jpeg_encode

        try:
            data = jpeg_encode(img, 95, threads)
        except ValueError:
            raise ServiceError(422, "encode_failed", "could not encode jpeg") from None
    else:
        import cv2

        bgr = np.ascontiguousarray(img[..., ::-1])
        ok, enc = cv2.imencode(".png" if fmt == "png" else ".jpg", bgr,
                               [cv2.IMWRITE_JPEG_QUALITY, 95] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1])
        if not ok:
            raise ServiceError(422, "encode_failed", f"could not encode {fmt}")
        data = enc.tobytes()
    data = _with_meta(data, fmt, meta)
    if path is not None:
        with open(path, "wb") as f:
            f.write(data)
        return None
    return data


def _with_meta(data: bytes, fmt: str, meta: dict | None) -> bytes:
    """A PNG or JPEG's bytes with ``meta``'s ICC profile, EXIF facts and PNG
    text embedded (:func:`service.outputs.embed`)."""
    from . import outputs

    meta = meta or {}
    icc, facts = meta.get("icc"), meta.get("facts")
    if icc or facts or meta.get("text"):
        data = outputs.embed(data, fmt, icc, outputs.exif_block(facts) if facts else None, meta.get("text"))
    return data


def _tiff_kwargs(meta: dict) -> dict:
    """tifffile's keywords for an output TIFF carrying ``meta`` (:func:`encode_image`)."""
    from . import outputs

    icc, facts = meta.get("icc"), meta.get("facts")
    kw = {}
    if icc:
        kw["iccprofile"] = icc
    if facts:
        kw["extratags"] = outputs.tiff_extratags(facts)
        kw["metadata"] = None          # no tifffile shape JSON in ImageDescription (photo tools show it)
        if facts.get("ImageDescription"):   # the source's own caption only; the estimate is in the XMP
            kw["description"] = outputs.ascii_text(facts["ImageDescription"])
        kw["software"] = facts.get("Software", "wandell-recovery")
    return kw


class _SparseFile:
    """A seekable file that keeps what is written and only the size of what
    is skipped (tifffile's ``write_empty``: a seek and one zero byte)."""

    def __init__(self):
        self.pos = self.size = 0
        self.parts: list[tuple[int, bytes]] = []

    def write(self, b) -> int:
        b = bytes(b)
        self.parts.append((self.pos, b))
        self.pos += len(b)
        self.size = max(self.size, self.pos)
        return len(b)

    def seek(self, off: int, whence: int = 0) -> int:
        self.pos = off if whence == 0 else self.pos + off if whence == 1 else self.size + off
        return self.pos

    def tell(self) -> int:
        return self.pos

    def flush(self) -> None:
        pass

    def seekable(self) -> bool:
        return True

    def writable(self) -> bool:
        return True


def tiff_head(img: np.ndarray, meta: dict | None = None) -> bytes | None:
    """The bytes of the TIFF :func:`encode_image` writes for ``img``, up to
    where its pixels start: the file is these bytes then ``img``'s bytes in
    C order (uncompressed, one strip, pixels last), so an answer can send
    the image from memory instead of a 144 MB file written and read back
    (issue 19). Made by tifffile with the pixels left empty; ``None`` when
    its layout is not header-then-pixels (then write the file)."""
    import tifffile

    f = _SparseFile()
    tifffile.imwrite(f, shape=img.shape, dtype=img.dtype, photometric="rgb", **_tiff_kwargs(meta or {}))
    start = f.size - img.nbytes
    head = bytearray(start)
    for off, b in f.parts:
        if off + len(b) <= start:
            head[off:off + len(b)] = b
        elif not (off == f.size - 1 and b == b"\x00"):      # anything but the pixels' one zero byte
            return None
    return bytes(head)


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


def temperature_tint(decoded, run: EstimateRun) -> dict:
    """Camera Raw's Temperature/Tint of the estimated light (Adobe's scale:
    Robertson's temperature, and the tint, -3000 times the distance from the
    locus, of the DNG SDK, :func:`recovery.dng_color.xy_to_temperature_tint`):
    the camera neutral -> xy through the file's colour matrices (DNG
    ``NeutralToXY``, so Camera Raw gets back this neutral), else the
    spectrum's xy (:func:`light_xy`). For a matrix-derived camera this is
    the xy of the reported CCT/Duv, so they differ only by the method and
    the scale (a few kelvin; Tint about 3000 x Duv); with measured
    sensitivities the CCT is the spectrum's and may differ more. 422
    ``no_temperature`` for a light far from the Planckian locus."""
    tt = _temperature_tint_xy(run.estimate, profile_of(decoded))
    if tt.get("temperature") is None:
        raise ServiceError(422, "no_temperature", "the estimated light is too far from the Planckian locus for a "
                           "temperature/tint white balance")
    return tt


def _temperature_tint_xy(est: IlluminantEstimate, profile=None) -> dict:
    from recovery.dng_color import xy_to_temperature_tint

    xy, basis = light_xy(est, profile)
    if xy is None or light_cct_duv(est, profile)[0] is None:
        return {"basis": basis}
    t, tint = xy_to_temperature_tint(xy)
    return {"temperature": t, "tint": tint, "xy": [float(xy[0]), float(xy[1])], "basis": basis}


def _box_sums(a: np.ndarray) -> np.ndarray:
    """Summed-area table of ``a`` (H, W[, C]) with a zero first row and
    column: the sum over rows r0..r1-1, columns c0..c1-1 is
    ``S[r1, c1] - S[r0, c1] - S[r1, c0] + S[r0, c0]``."""
    S = np.zeros((a.shape[0] + 1, a.shape[1] + 1) + a.shape[2:], np.float64)
    np.cumsum(a, axis=0, dtype=np.float64, out=S[1:, 1:])
    np.cumsum(S[1:, 1:], axis=1, out=S[1:, 1:])
    return S


def _box(S: np.ndarray, r0, c0, r1, c1) -> np.ndarray:
    return S[r1, c1] - S[r0, c1] - S[r1, c0] + S[r0, c0]


def surfaces_at(decoded, run: EstimateRun, points, rects, grid, options: dict) -> dict:
    """Reflectance spectra at full-resolution pixel points, rectangle means,
    or a coarse grid: the prior's posterior mean with a band per wavelength
    and an expected RMS error (:mod:`recovery.surface_prior`), or eq. 36 with
    a C-term surface model when the request names a surface model.

    The cost is bounded whatever the rectangles: a rectangle's mean camera
    RGB comes from a summed-area table of the estimation image (built once,
    four look-ups per rectangle), and a rectangle's reflectance is the
    estimate of its mean RGB (for eq. 36, linear in the camera RGB, that is
    also the mean of its pixels' reflectances; the prior's mixture posterior
    is not linear: there it is the estimate of the surface the rectangle's
    pixels average to). All entries are then solved in one
    vectorised step."""
    img = decoded.estimation
    h, w = img.shape[:2]
    H, W = decoded.full_shape
    sy, sx = h / H, w / W
    # the light estimated once (run.estimate) serves the surfaces too
    res = surfaces_from_estimate(img, run.camera, run.estimate, synthesis_basis=options.get("surface_basis"))

    def to_est(r, c):
        if not (0 <= r < H and 0 <= c < W):
            raise ServiceError(422, "invalid_parameter", f"point ({r}, {c}) outside the {H}x{W} image")
        return min(int(r * sy), h - 1), min(int(c * sx), w - 1)

    kinds, wheres, rows, cols = [], [], [], []
    for r, c in points:
        a, b = to_est(r, c)
        kinds.append("point"), wheres.append([r, c]), rows.append((a, a + 1)), cols.append((b, b + 1))
    for r0, c0, r1, c1 in rects:
        if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
            raise ServiceError(422, "invalid_parameter", f"rectangle {[r0, c0, r1, c1]} must satisfy "
                           f"0 <= r0 < r1 <= {H} and 0 <= c0 < c1 <= {W}")
        a0, b0 = to_est(r0, c0)
        a1, b1 = to_est(r1 - 1, c1 - 1)
        kinds.append("rect"), wheres.append([r0, c0, r1, c1]), rows.append((a0, a1 + 1)), cols.append((b0, b1 + 1))
    if grid:
        gr, gc = grid
        for i in range(gr):
            for j in range(gc):
                r = int((i + 0.5) * H / gr)
                c = int((j + 0.5) * W / gc)
                a, b = to_est(r, c)
                kinds.append("grid"), wheres.append([r, c]), rows.append((a, a + 1)), cols.append((b, b + 1))
    entries = []
    if kinds:
        r0, r1 = np.asarray(rows, np.intp).T
        c0, c1 = np.asarray(cols, np.intp).T
        finite = np.all(np.isfinite(img), axis=2)
        data = np.where(finite[..., None], img, 0.0)
        n = ((r1 - r0) * (c1 - c0)).astype(float)
        rho = _box(_box_sums(data), r0, c0, r1, c1) / n[:, None]
        bad = _box(_box_sums(~finite), r0, c0, r1, c1) > 0
        if bad.any():
            k = int(np.argmax(bad))
            raise ServiceError(422, "invalid_parameter", f"{kinds[k]} {wheres[k]} covers non-finite pixel values: "
                           "no reflectance there")
        sat = _box(_box_sums(np.asarray(decoded.saturated, bool)), r0, c0, r1, c1) > 0
        # the light at each entry's centre (one light: the same everywhere)
        rows_c, cols_c = (r0 + r1 - 1) / 2.0, (c0 + c1 - 1) / 2.0
        if res.surface_estimator == "prior":
            # a rectangle: the estimate of its mean RGB (the mixture posterior is not linear in it)
            pe = res.estimates_from_responses(rho, rows_c, cols_c)
            refl, stds, ermse = pe.mean, pe.std, pe.expected_rmse
        else:
            L = res._lighting(rows_c, cols_c)
            weights = np.einsum("pjk,pk->pj", np.linalg.pinv(L), rho) * res.reflectance_scale
            refl = weights @ res.surface_model.basis.T
            stds, ermse = [None] * len(kinds), [None] * len(kinds)
        fit = res.illuminant.diagnostics.get("subspace_fit_ratio")
        for kind, where, r, s_, sd, er in zip(kinds, wheres, refl, sat, stds, ermse):
            warns = []
            if np.any(r < -0.02):
                warns.append(f"non-physical: reflectance below 0 (min {r.min():.3f})")
            if np.any(r > 1.02):
                warns.append(f"non-physical: reflectance above 1 (max {r.max():.3f}); the scale is relative")
            if s_:
                warns.append("saturated pixels: the estimate is clipped")
            if fit is not None and fit > 0.1:
                warns.append("poor subspace fit for the scene (see diagnostics)")
            entries.append({"kind": kind, "where": where, "reflectance": r.tolist(), "warnings": warns,
                            "reflectance_std": None if sd is None else sd.tolist(),
                            "expected_rmse": None if er is None else float(er)})
    return {"wavelengths": run.camera.wavelengths.tolist(), "surfaces": entries,
            "surface_estimator": res.surface_estimator,
            "band": ("reflectance_std: posterior standard deviation per wavelength (mean +- 1 std should hold "
                     "the truth about 68 % of the time, +- 1.645 std 90 %; measured in benchmarks.surfaces); "
                     "expected_rmse: the RMS error the model expects for the surface"
                     if res.surface_estimator == "prior" else
                     "none: the literal method (eq. 36, pseudo-inverse in the surface model) has no band"),
            "surface_model": res.diagnostics.get("surface_model"),
            "reflectance_scale_convention": res.diagnostics.get("reflectance_scale_convention"),
            "diagnostics": res.diagnostics}
