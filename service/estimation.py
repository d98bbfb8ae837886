"""The estimate of one image, as the service runs it: the analysis
resolution of the ``quality`` preset, the camera cross-check of
``camera=generic``, the literal method's own failure tests, a white the
user picked (``neutral``) or the file's as-shot white (:mod:`service.pipeline`
re-exports every name; split from it by concern, issue 29)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from recovery import Camera, IlluminantEstimate, analysis_pixels, angular_error, estimate_illuminant
from recovery.api import resolve_model
from recovery.errors import InsufficientSurfaceVariation
from recovery.resolution import block_average

from .errors import ServiceError


@dataclass
class EstimateRun:
    estimate: IlluminantEstimate
    camera: Camera
    camera_warnings: list
    timings_ms: dict = field(default_factory=dict)
    factor: int = 1
    neutral: dict | None = None     # set by with_neutral: where the user's white came from
    requested_method: str | None = None
    white: str | None = None        # set by with_white: the user's white as given (``white=5200/+10``)


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
    # a RAW's estimation image is on the sensor's scale (1 = its white level): the estimate can say when the
    # picture is so underexposed that its light rests on noise (probe round 9b)
    scale = {"full_scale": 1.0} if getattr(decoded, "kind", None) == "raw" and "full_scale" not in options else {}
    try:
        est = estimate_illuminant(img, camera, method, mask=mask, **options, **scale)
    except InsufficientSurfaceVariation as exc:
        why = float_scale_refusal(decoded, exc)
        if why is None:
            raise
        raise why from None
    t1 = time.perf_counter()
    run = EstimateRun(est, camera, list(camera_warnings), {"estimate": (t1 - t0) * 1e3}, f,
                      requested_method=method)
    if camera.source == "generic":
        generic_cross_check(decoded, run, img, mask, method, options)
        run.timings_ms["matrix_cross_check"] = (time.perf_counter() - t1) * 1e3
    return run


def float_scale_refusal(decoded, exc):
    """For a float TIFF whose every pixel is at or above 1.0 (the full scale
    of float samples, so every pixel is saturated), the estimator's "no usable
    pixels" with the reason and what to do: its values are on another scale
    (an HDR merge's, 0..1000); else ``None`` (probe round 9: the reason was
    said nowhere)."""
    if not (decoded.kind == "tiff" and decoded.white_level == 1.0 and decoded.saturated.size
            and decoded.saturated.all()):
        return None
    est = decoded.estimation
    return InsufficientSurfaceVariation(
        f"{exc}: every pixel of this float TIFF has a channel at or above 1.0, the full scale (saturation) of "
        f"float samples; its values run from {float(est.min()):.4g} to {float(est.max()):.4g}: scale them into "
        "0..1 (divide by the largest) and send it again")


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


#: Whose white a run fixed by :func:`run_with_white` renders, by its method.
_GIVEN_WHITE = {"as-shot": "the file's as-shot white (white=as-shot)",
                "temperature-tint": "the white you set (white=TEMPERATURE/TINT)",
                "neutral-surface": "the surface you chose as white (neutral)"}


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
    who = _GIVEN_WHITE.get(method, "the white given")
    est = _finish(rgb, spd, w, run.camera, model, method,
                  {"light_model": model.name + " (spectrum fitted to the given white)",
                   # lights.reason was empty (probe round 6), also where spatial=true asked for a map
                   "spatial_decision": "one light", "lights_found": 1,
                   "spatial_reason": f"one light: {who} is one light for the whole image (a light map comes from "
                                     "the estimate, without neutral or white)"}, [])
    return EstimateRun(est, run.camera, list(run.camera_warnings), dict(run.timings_ms), run.factor)


#: Above this angle between the light used and the file's as-shot white the answer warns.
AS_SHOT_WARN_DEG = 5.0


#: A surface chosen as white whose brightest channel averages less than
#: this fraction of the white level gets a low-signal warning (a 14-bit
#: sensor keeps about 800 levels there, and a 0.1 % black-level error is
#: already a 2 % colour error).
NEUTRAL_LOW_SIGNAL = 0.05


def neutral_white(decoded, where: list) -> tuple[np.ndarray, dict]:
    """The light's camera RGB from a surface the user says is white or grey:
    the mean camera RGB of the unclipped cells of the estimation image under
    the point or rectangle ``where`` (full-resolution pixels, as
    :func:`surfaces_at`). 422 when it is outside the image or every cell
    there is clipped or black.

    Several picks (``where`` a list of points and rectangles): each pick's
    white as above, scaled to unit length, and their mean, so each pick
    weighs the same whatever its area and brightness (a white card and a
    grey one say the same light). The answer's ``picks`` give each pick's
    own; a 422 names the pick that was wrong."""
    if where and isinstance(where[0], list):
        units, picks = [], []
        for i, w in enumerate(where):
            try:
                rgb, info = neutral_white(decoded, w)
            except ServiceError as e:
                raise ServiceError(e.status, e.code, f"pick {i + 1} of {len(where)}: {e.detail}") from None
            units.append(rgb / np.linalg.norm(rgb))
            picks.append(info)
        rgb = np.mean(units, axis=0)
        out = {"where": [list(w) for w in where], "cells_used": sum(p["cells_used"] for p in picks),
               "cells_clipped_or_black": sum(p["cells_clipped_or_black"] for p in picks),
               "camera_rgb": (rgb / np.linalg.norm(rgb)).tolist(), "level": min(p["level"] for p in picks),
               "picks": picks,
               "spread_deg": max(float(angular_error(u, rgb)) for u in units)}
        dark = [str(i + 1) for i, p in enumerate(picks) if p.get("warning")]
        if dark:
            out["warning"] = (f"pick {', '.join(dark)} of {len(where)} is dark (its brightest channel under "
                              f"{100 * NEUTRAL_LOW_SIGNAL:g} % of the white level): noise and black-level error "
                              "dominate its colour; a brighter white or grey surface gives a more reliable white")
        return rgb, out
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
