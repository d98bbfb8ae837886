"""The light as the service reports it: its chromaticity, CCT/Duv and
Camera Raw Temperature/Tint through the file's colour matrices, and the JSON
of ``/v1/analyze``, headers, batch items and XMP (:mod:`service.pipeline`
re-exports every name)."""

from __future__ import annotations

import numpy as np

from recovery import Camera, IlluminantEstimate, angular_error

from .errors import ServiceError
from .estimation import AS_SHOT_WARN_DEG, EstimateRun, method_failure


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
    out["lights"] = lights_json(est, "light_map gives the light across the frame, and white-balanced outputs "
                                     "correct each pixel by it")
    lm = light_map_json(run, decoded)
    if lm is not None:
        out["light_map"] = lm
    if decoded.as_shot_neutral is not None and np.all(np.isfinite(decoded.as_shot_neutral)):
        asn = np.asarray(decoded.as_shot_neutral, float)
        ang = float(angular_error(asn, est.rgb))
        out["as_shot"] = {"camera_rgb": (asn / np.linalg.norm(asn)).tolist(), "angle_to_estimate_deg": ang}
        if ang > AS_SHOT_WARN_DEG:
            what = "the white you chose" if run.neutral is not None else "the estimate"
            out["warnings"].append(f"{what} is {ang:.1f} degrees from the camera's own as-shot white (more than "
                                   f"{AS_SHOT_WARN_DEG:g}): check the picture, or use a white surface "
                                   "('neutral') or white=as-shot")
    elif getattr(decoded, "as_shot_problem", None):   # said by white=as-shot and the preview; here too (round 8b)
        out["warnings"].append(f"{decoded.as_shot_problem}; the answer has no as_shot block")
    if run.neutral is not None:
        out["neutral"] = dict(run.neutral)
        if out["neutral"].get("warning"):
            out["warnings"].append(out["neutral"]["warning"])
    return out


def light_map_json(run: EstimateRun, decoded) -> dict | None:
    """The answer's ``light_map``: the light at the map's centres (unit camera
    RGB), as fractions of the image height and width; ``None`` for one light.
    Every answer whose ``lights.found`` is 2 carries it (``/v1/analyze``,
    ``/v1/white-balance``, ``/v1/surfaces``: probe round 4)."""
    lm = getattr(run.estimate, "light_map", None)
    if lm is None:
        return None
    rr, cc = np.meshgrid(lm.centres_r, lm.centres_c, indexing="ij")
    rgb = run.camera.response(lm.spectra_at(rr.ravel(), cc.ravel()))
    rgb = rgb / np.linalg.norm(rgb, axis=1, keepdims=True)
    eh, ew = decoded.estimation.shape[:2]
    return {"centres_row_fraction": ((lm.centres_r + 0.5) * run.factor / eh).tolist(),
            "centres_col_fraction": ((lm.centres_c + 0.5) * run.factor / ew).tolist(),
            "camera_rgb": rgb.reshape(rr.shape + (-1,)).tolist()}


def lm_found(est) -> bool:
    """Whether the estimate carries a light map (several lights)."""
    return getattr(est, "light_map", None) is not None


def lights_json(est, use: str) -> dict:
    """The answer's ``lights``: how many lights the decision found, the
    decision and its reason in words; with several, ``held`` says that
    ``illuminant`` is the scene's one light and (``use``) what the map does."""
    d = est.diagnostics
    mapped = lm_found(est)       # the one source of found and decision: the map the answer carries
    out = {"found": 2 if mapped else 1, "decision": "light map" if mapped else "one light",
           "reason": str(d.get("spatial_reason", ""))}
    if mapped:
        out["held"] = f"illuminant is the scene's one light (the whole image's estimate); {use}"
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


def rendering_json(info: dict) -> dict:
    """The rendering choice and its figures, for headers and JSON bodies."""
    keys = ("rendering", "color_source", "white_xy", "temperature", "tint", "calibration_weight",
            "forward_matrix", "baseline_exposure", "exposure", "tone", "curve", "target_white_xy", "crop", "notes")
    return {k: info[k] for k in keys if k in info}


def confidence_json(est: IlluminantEstimate) -> dict:
    """``confidence`` (P(error < 3 degrees)) and ``low_confidence`` (the
    flag), as the JSON answer's ``diagnostics`` carry them, for the
    ``X-Illuminant`` header and the XMP the outputs carry; empty when the
    estimate reports none (a white the user set). The header and the XMP
    had the confidence at most, never the flag (probe round 8): a
    photographer reading sidecars or headers could not pick the doubtful
    ones out."""
    d = est.diagnostics
    conf = d.get("confidence")
    if not (isinstance(conf, (int, float)) and not isinstance(conf, bool) and np.isfinite(conf)):
        return {}
    low = d.get("low_confidence")
    if not isinstance(low, (bool, np.bool_)):
        from recovery.api import LOW_CONFIDENCE

        low = conf < LOW_CONFIDENCE
    return {"confidence": float(conf), "low_confidence": bool(low)}


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
    out.update(confidence_json(est))
    if info:
        out["rendering"] = info.get("rendering")
    d = est.diagnostics
    if lm_found(est):
        out["lights"] = "several"
        out["lights_reason"] = str(d.get("spatial_reason", ""))
        out["light_held"] = ("the scene's one light (the whole image's estimate); a white-balanced output corrects "
                             "each pixel by the light map, a single white balance (this sidecar's) cannot")
    out.update(extra)
    return out


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
        from .rendering import light_source    # rendering imports this module

        who = light_source(run)      # a user's white was refused as "the estimated light" (probe round 6)
        advice = ("" if who == "the estimated light" else
                  "; choose a temperature and tint nearer the daylight locus" if who.startswith("the white you set")
                  else "; choose another white")
        raise ServiceError(422, "no_temperature", f"{who} is too far from the Planckian locus for a "
                           f"temperature/tint white balance{advice}")
    return tt


def _temperature_tint_xy(est: IlluminantEstimate, profile=None) -> dict:
    from recovery.dng_color import xy_to_temperature_tint

    xy, basis = light_xy(est, profile)
    if xy is None or light_cct_duv(est, profile)[0] is None:
        return {"basis": basis}
    t, tint = xy_to_temperature_tint(xy)
    return {"temperature": t, "tint": tint, "xy": [float(xy[0]), float(xy[1])], "basis": basis}
