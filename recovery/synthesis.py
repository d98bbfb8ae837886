"""Synthesis: display gun intensities from surfaces and a light.

References
----------
Wandell (1985) [docs/references.md#seed-002]:

* eq. 22-24: :math:`\\Gamma I^x = \\Lambda'_{E'} \\sigma^x`, so
  :math:`I^x = \\Gamma^{-1}\\Lambda'_{E'}\\sigma^x`, where :math:`\\Lambda'` uses the
  observer :math:`R'` and :math:`E'` is the light to render under;
* eq. 25 and 'Display gamut limitations': negative gun intensities are
  handled either per pixel (clip) or for the whole image by adjusting the
  light vector;
* Fig. 6: the camera's sensors analyse (:math:`\\sigma = \\Lambda_E^+\\rho`,
  eq. 36) and the observer synthesises, so everything collapses, for a
  fixed light, to one matrix from camera responses to display values.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models import display as get_display, observer as get_observer, wavelength_step
from models.displays import Display

from .lighting import display_matrix, lighting_matrix_from_spectrum, lighting_tensor

__all__ = [
    "output_space",
    "OutputSpace",
    "synthesis_matrix",
    "display_intensities",
    "adjust_light_for_gamut",
    "encode",
    "correction_matrix",
    "exposure_gain",
    "display_linear",
    "display_curve",
    "highlight_white",
]


@dataclass
class OutputSpace:
    """Where :func:`synthesis_matrix` lands: observer responses (``Gamma is
    None``) or display intensities through ``Gamma`` (K x 3)."""

    name: str
    observer: np.ndarray
    Gamma: np.ndarray | None = None
    encoding: str | None = None
    notes: list = field(default_factory=list)


def output_space(output: str, wavelengths: np.ndarray, observer: str | None = None) -> OutputSpace:
    """Resolve an output name: ``"XYZ"``, ``"linear-sRGB"``, ``"sRGB"``
    (encoded), or a display name (``"Typical CRT Brainard 1997"``,
    ``"Apple Studio Display"``, linear gun intensities).

    :math:`\\Gamma` (eq. 4) is scaled so full-on white has the same second
    observer response (Y for XYZ) as a perfect white under the render light,
    i.e. display white = 1.
    """
    wl = np.asarray(wavelengths, float)
    if output == "XYZ":
        obs = get_observer(observer or "CIE 1931 2 Degree Standard Observer", wl)
        return OutputSpace("XYZ", obs)
    if output in ("linear-sRGB", "sRGB"):
        if observer not in (None, "XYZ", "CIE 1931", "CIE 1931 2 Degree Standard Observer"):
            raise ValueError("sRGB is defined for the CIE 1931 observer only")
        d = get_display("sRGB")
        obs = get_observer("CIE 1931 2 Degree Standard Observer", wl)
        return OutputSpace(output, obs, d.primaries_XYZ, "sRGB" if output == "sRGB" else None)
    try:
        d: Display = get_display(output, wl)
    except KeyError:
        raise ValueError(f"unknown output {output!r}; accepted: XYZ, linear-sRGB, sRGB, Display P3, "
                         "Typical CRT Brainard 1997, Apple Studio Display") from None
    obs = get_observer(observer or "CIE 1931 2 Degree Standard Observer", wl)
    if d.guns is None:  # a colorimetric display (Display P3, Rec. 709): its primaries, encoded
        return OutputSpace(output, obs, d.primaries_XYZ, d.encoding)
    G = display_matrix(d.guns, obs, wavelength_step(wl))
    G = G / G.sum(axis=1)[1]
    return OutputSpace(output, obs, G)


def synthesis_matrix(sensors: np.ndarray, wavelengths: np.ndarray, light: np.ndarray,
                     target: np.ndarray, surface_basis: np.ndarray, space: OutputSpace
                     ) -> tuple[np.ndarray, float]:
    """The matrix from camera responses to output values for one light.

    ``M = Gamma^{-1} k Lambda'_{E'} Lambda_E^{+}`` with
    ``k = 1 / sum_n E'(l_n) R'_2(l_n) dl_n`` (a perfect white under E' has
    second observer response 1). Also accepts stacks of lights
    ``(..., N)`` and returns ``(..., K, C)``.

    Returns
    -------
    M : (K, C) or (..., K, C)
    condition : float, worst condition number of Lambda_E (eq. 36)
    """
    dl = wavelength_step(wavelengths)
    L_E = lighting_matrix_from_spectrum(light, surface_basis, sensors, dl)       # (..., C, DS)
    L_T = lighting_matrix_from_spectrum(target, surface_basis, space.observer, dl)  # (..., K, DS)
    white = np.einsum("...n,n,n->...", np.asarray(target, float), space.observer[:, 1], dl)
    s = np.linalg.svd(L_E, compute_uv=False)
    cond = float(np.max(s[..., 0] / np.maximum(s[..., -1], np.finfo(float).tiny)))
    # singular values below 1e-6 of the largest are noise for any camera
    # data (their directions are cut, not amplified a million-fold)
    M = (L_T / white[..., None, None]) @ np.linalg.pinv(L_E, rcond=1e-6)
    if space.Gamma is not None:
        M = np.linalg.solve(space.Gamma, M) if M.ndim == 2 else np.linalg.inv(space.Gamma) @ M
    return M, cond


def display_intensities(sigma: np.ndarray, lighting_observer: np.ndarray, Gamma: np.ndarray) -> np.ndarray:
    """Eq. 23: :math:`I^x = \\Gamma^{-1} \\Lambda'_{E'} \\sigma^x` for surface
    weights ``(..., D(S))``; returns ``(..., 3)``."""
    return np.asarray(sigma, float) @ np.linalg.solve(Gamma, lighting_observer).T


def adjust_light_for_gamut(pixels: np.ndarray, sensors: np.ndarray, wavelengths: np.ndarray,
                           light: np.ndarray, target: np.ndarray, surface_basis: np.ndarray,
                           space: OutputSpace, light_basis: np.ndarray,
                           max_points: int = 4000) -> tuple[np.ndarray, dict]:
    """Wandell's second gamut option: change the render light for the whole
    image so no gun intensity is negative.

    Finds :math:`E' = E'_0 + B\\delta` (``B`` a light basis, e.g. CIE
    daylight) with the smallest :math:`\\|\\delta\\|` such that
    :math:`\\Gamma^{-1}\\Lambda'_{E'}\\sigma^x \\ge 0` for every pixel and
    :math:`E' \\ge 0`. The constraints are linear in :math:`\\delta` for each
    pixel and linear in :math:`\\sigma` for fixed :math:`\\delta`, so the
    vertices of the convex hull of the pixels suffice.

    Returns
    -------
    target : (N,) the adjusted render light (``target`` itself when no
        pixel is out of gamut or no feasible light exists)
    info : dict with ``out_of_gamut_fraction``, ``adjusted`` (bool),
        ``delta`` and ``feasible``
    """
    px = np.asarray(pixels, float)
    px = px[np.all(np.isfinite(px), axis=1)]
    rng = np.random.default_rng(0)
    if px.shape[0] > max_points:
        px = px[rng.choice(px.shape[0], max_points, replace=False)]
    if space.Gamma is None:
        return target, {"adjusted": False, "reason": "no display gamut for observer output"}
    M, _ = synthesis_matrix(sensors, wavelengths, light, target, surface_basis, space)
    I0 = px @ M.T
    frac = float(np.mean(np.any(I0 < 0, axis=1))) if px.size else 0.0
    if frac == 0.0:
        return target, {"adjusted": False, "out_of_gamut_fraction": 0.0, "feasible": True}
    pts = px
    from scipy import optimize, spatial  # here: imported only when the gamut is adjusted (start-up, issue 19)

    if px.shape[1] <= 4:  # qhull's cost grows like n^(C/2): beyond 4 channels use the sample
        try:
            pts = px[spatial.ConvexHull(px).vertices]
        except Exception:  # degenerate (coplanar) data: use the sample itself
            pts = px
    elif px.shape[0] > 1000:
        pts = px[rng.choice(px.shape[0], 1000, replace=False)]
    # A pixel's constraints are linear in it, so scaling it by a positive factor keeps the feasible
    # lights. Pixels more than 1e150 times fainter than the brightest (no photograph's: float32 cannot
    # hold the ratio; e.g. one pixel at 1e300) are brought up to its level: rows of 1e-300 crashed
    # SciPy's SLSQP (a segmentation fault, probe pyapi7). Valid images have none, so are unchanged.
    mags = np.abs(pts).max(axis=1) if pts.size else np.zeros(0)
    top = float(mags.max()) if mags.size else 0.0
    faint = (mags > 0) & (mags < 1e-150 * top)
    if faint.any():
        pts = pts.copy()
        pts[faint] *= (top / mags[faint])[:, None]
    dl = wavelength_step(wavelengths)
    L_E = lighting_matrix_from_spectrum(light, surface_basis, sensors, dl)
    sig = pts @ np.linalg.pinv(L_E).T                                   # (Q, DS)
    B = np.asarray(light_basis, float)
    T = lighting_tensor(B, surface_basis, space.observer, dl)           # (DB, K, DS)
    Ginv = np.linalg.inv(space.Gamma)
    base = sig @ (Ginv @ lighting_matrix_from_spectrum(target, surface_basis, space.observer, dl)).T
    J = np.einsum("gk,ikj,qj->qgi", Ginv, T, sig).reshape(-1, B.shape[1])
    b = base.reshape(-1)
    scale = float(np.abs(b).max()) or 1.0
    tnorm = float(np.abs(target).max()) or 1.0
    cons = [
        {"type": "ineq", "fun": lambda d: (b + J @ d) / scale, "jac": lambda d: J / scale},
        {"type": "ineq", "fun": lambda d: (target + B @ d) / tnorm, "jac": lambda d: B / tnorm},
    ]
    x0 = np.zeros(B.shape[1])
    res = optimize.minimize(lambda d: float(d @ d), x0, jac=lambda d: 2 * d, constraints=cons,
                            method="SLSQP", options={"maxiter": 200, "ftol": 1e-12})
    d = res.x
    feasible = bool(res.success and np.all(b + J @ d >= -1e-9 * scale)
                    and np.all(target + B @ d >= -1e-9 * tnorm))
    if not feasible:
        return target, {"adjusted": False, "out_of_gamut_fraction": frac, "feasible": False,
                        "reason": f"no light in the basis brings every pixel into gamut ({res.message})"}
    return target + B @ d, {"adjusted": True, "out_of_gamut_fraction": frac, "feasible": True,
                            "delta": [float(v) for v in d]}


def encode(values: np.ndarray, encoding: str | None) -> np.ndarray:
    """Apply a colourspace's transfer function (colour-science's
    ``cctf_encoding``) to linear values clipped to [0, 1]."""
    if encoding is None:
        return values
    import colour

    return np.asarray(colour.RGB_COLOURSPACES[encoding].cctf_encoding(np.clip(values, 0, 1)),
                      dtype=values.dtype)


def _target_spectrum(target, light_spectrum: np.ndarray, wavelengths: np.ndarray) -> np.ndarray:
    """The light to render under: the estimated light itself for
    ``"estimate"``/``"as-seen"`` (no adaptation), a named light, or a spectrum."""
    from models import illuminant as get_illuminant

    from .errors import InputError

    if isinstance(target, str):
        if target in ("estimate", "as-seen"):
            return np.asarray(light_spectrum, float)
        try:
            return np.asarray(get_illuminant(target, wavelengths), float)
        except KeyError as e:
            raise InputError(f"target: {e.args[0]}", code="invalid_parameter") from None
    return np.asarray(target, float)


def _target_xy(target, white_xy, wavelengths) -> tuple[float, float]:
    """Chromaticity the rendered white takes (DNG rendering): D65 for
    ``D65``, the light's own (no adaptation) for ``estimate``, else the
    named light's."""
    from .dng_color import D65_XY

    if isinstance(target, str) and target == "D65":
        return D65_XY
    if isinstance(target, str) and target in ("estimate", "as-seen"):
        return tuple(white_xy)
    spd = _target_spectrum(target, None, wavelengths)
    xyz = get_observer("CIE 1931 2 Degree Standard Observer", wavelengths).T @ spd
    return tuple(xyz[:2] / xyz.sum())


#: LibRaw's ``auto_bright_thr``: the fraction of pixels auto-brightness lets reach display white.
AUTO_BRIGHT_THR = 0.01
#: LibRaw's bounds on the auto-brightness gain (its histogram search stops at 32 of 8192 bins:
#: at most 256; it never darkens: at least 1).
AUTO_BRIGHT_GAIN = (1.0, 256.0)
#: Pixels of the image the auto rule looks at (a regular subsample).
AUTO_BRIGHT_PIXELS = 250_000
#: The EV range a user's exposure may take.
EXPOSURE_RANGE = (-10.0, 16.0)


def highlight_white(A64: np.ndarray):
    """The white-balanced colour a matrix sends to display white (1, 1, 1),
    or ``None`` when it is not a positive colour."""
    try:
        wb_white = np.linalg.solve(A64, np.ones(3))
    except np.linalg.LinAlgError:
        return None
    return wb_white if np.all(wb_white > 0) else None


def display_linear(cam_rgb: np.ndarray, M: np.ndarray, neutral=None) -> np.ndarray:
    """Linear display values of camera RGB ``(N, 3)`` (1.0 = saturation), as
    the service applies ``M`` before exposure, shoulder, clipping and
    encoding (clipped highlights made neutral,
    :func:`recovery.highlights.balance_highlights`, when ``neutral`` is
    given)."""
    c = np.asarray(cam_rgb, np.float32).reshape(-1, 3)
    if neutral is None:
        return _transform(c, M)
    from .highlights import balance_highlights

    n = np.asarray(neutral, float)
    n = n / n.max()
    A64 = np.asarray(M, float) @ np.diag(n)
    wb = balance_highlights(c, n, white=highlight_white(A64))
    return _transform(wb, A64)


def _transform(c: np.ndarray, M) -> np.ndarray:
    """``c @ M.T`` for (N, 3) float32 ``c``, by OpenCV's ``transform`` (as
    the correction applies its matrices): a BLAS product of this shape
    waits for BLAS's threads, which on a loaded machine took 27-54 ms for
    the auto-exposure's 333,000 pixels where this takes under 1 ms (issue 19)."""
    import cv2

    c = np.ascontiguousarray(c, np.float32)
    return cv2.transform(c.reshape(-1, 1, 3), np.asarray(M, np.float32)).reshape(-1, 3)


def exposure_gain(image, M: np.ndarray, neutral=None, exposure: float | None = None) -> tuple[float, dict]:
    """The exposure gain on the linear display values of ``M``, and how it
    was chosen.

    ``exposure`` in EV (a user's choice, in :data:`EXPOSURE_RANGE`):
    ``2 ** exposure``. ``None``: LibRaw's auto-brightness (dcraw
    ``write_ppm_tiff``): per display channel the level that
    :data:`AUTO_BRIGHT_THR` of the pixels of ``image`` (camera RGB, 1.0 =
    saturation) exceed (values clipped at white first, as LibRaw clips
    before its histogram), the largest over the channels is sent to white;
    the gain is kept in :data:`AUTO_BRIGHT_GAIN`. Without an image the gain
    is 1 (the brightest recordable neutral at display white). Raises
    :class:`~recovery.errors.InputError` (``invalid_parameter``) for an
    exposure out of range."""
    if exposure is not None:
        from .errors import InputError

        try:
            ev = float(exposure)
        except (TypeError, ValueError):
            ev = float("nan")
        lo, hi = EXPOSURE_RANGE
        if not (np.isfinite(ev) and lo <= ev <= hi):
            raise InputError(f"exposure must be a number of EV in {lo:g}..{hi:g}, or auto; got {exposure!r}",
                             code="invalid_parameter")
        return 2.0 ** ev, {"rule": "user", "ev": ev}
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[-1] != 3 or image.size == 0:
        return 1.0, {"rule": "none", "ev": 0.0, "note": "no image to measure: the brightest recordable "
                     "neutral renders as display white"}
    flat = image.reshape(-1, 3)
    step = max(1, flat.shape[0] // AUTO_BRIGHT_PIXELS)
    sample = np.nan_to_num(np.clip(flat[::step], 0.0, 1.0))
    lin = np.clip(display_linear(sample, M, neutral), 0.0, 1.0)
    level = float(np.max(np.percentile(lin, 100.0 * (1.0 - AUTO_BRIGHT_THR), axis=0)))
    lo, hi = AUTO_BRIGHT_GAIN
    gain = float(np.clip(1.0 / level, lo, hi)) if level > 0 else hi
    return gain, {"rule": "auto", "ev": float(np.log2(gain)),
                  "description": f"LibRaw's auto-brightness: the {100 * (1 - AUTO_BRIGHT_THR):g}th percentile "
                                 f"of the brightest display channel is display white (gain {lo:g}..{hi:g})",
                  "percentile_level": level}


def display_curve(x: np.ndarray) -> np.ndarray:
    """LibRaw's tone: its default output curve (``gamma=(2.222, 4.5)``, the
    ITU-R BT.709 transfer function) read by a display as sRGB, as a curve on
    linear values: ``sRGB_decode(BT709_encode(x))``. It maps 0 -> 0 and
    1 -> 1, darkens the mid-tones (0.18 -> 0.14) and deepens the shadows, so
    with LibRaw's auto-brightness gain the encoded image is as bright as
    LibRaw's at every level."""
    x = np.clip(np.asarray(x, float), 0.0, 1.0)
    v = np.where(x < 0.018, 4.5 * x, 1.099 * x ** 0.45 - 0.099)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _with_exposure(M, info, image, exposure, tone, Gamma):
    """``M`` times the exposure gain (:func:`exposure_gain`), with the
    highlight shoulder when the gain lifts the sensor's range above white
    and LibRaw's tone curve for display-encoded outputs."""
    gain, einfo = exposure_gain(image, M, info.get("neutral"), exposure)
    info["exposure"] = einfo
    if gain > 1.0 and tone == "shoulder":
        from .highlights import SHOULDER_KNEE

        lum = Gamma[1] if Gamma is not None else np.array([0.2126, 0.7152, 0.0722])
        info["shoulder"] = {"luminance": [float(v) for v in lum], "knee": SHOULDER_KNEE, "peak": gain}
    info["tone"] = "shoulder" if "shoulder" in info else "linear"
    if tone != "linear" and info.get("encoding") is not None:
        info["curve"] = "libraw"        # display-encoded outputs take LibRaw's tone; linear ones stay linear
    return M * gain, info


def correction_matrix(camera, light_rgb, light_spectrum: np.ndarray, target, space: OutputSpace,
                      surface_basis: np.ndarray | None = None, *, profile=None, tone: str = "shoulder",
                      exposure: float | None = None, image: np.ndarray | None = None,
                      normalize: bool = True) -> tuple[np.ndarray, dict]:
    """Camera RGB (1.0 = saturation) -> linear output values for one light:
    the one 3x3 matrix of Wandell (1985), Fig. 6, with its exposure rule.

    Spectral rendering (``profile`` None: measured, uploaded or generic
    sensitivities): ``M = Gamma^{-1} Lambda'_{E'} Lambda_E^{-1}``
    (:func:`synthesis_matrix`, eq. 23 and 36 with ``surface_basis``, a
    surface model of as many terms as sensors). With ``normalize`` it is
    scaled so that the brightest neutral the sensor records unclipped (the
    light's own camera RGB ``light_rgb`` with its largest channel at
    saturation) renders with luminance 1 before the exposure (below);
    without, white has Y = 1 up to the image's exposure and no exposure
    rule applies (:func:`recovery.render`).

    DNG-matrix rendering (``profile``, a
    :class:`~recovery.dng_color.ColorProfile`: a camera known only by its
    colour matrix): the DNG specification's camera -> XYZ D50 for the
    estimated camera neutral (:func:`recovery.dng_color.camera_to_xyz_d50`),
    Bradford to the target white, ``Gamma^{-1}``; the same neutral at
    saturation renders with luminance 1 before the exposure. Used when the
    neutral is positive and the output has primaries; otherwise the
    spectral rendering.

    Exposure (both renderings, :func:`exposure_gain`): ``exposure=None``
    (the default, "auto") is LibRaw's auto-brightness rule measured on
    ``image`` (the camera RGB the picture is made of; none: gain 1), the
    same for every file: the gain that sends the 99th percentile of the
    brightest display channel to display white (dcraw/LibRaw
    ``auto_bright_thr`` = 0.01), at least 1 and at most 256; a number is the
    user's exposure in EV on the same base (0: the brightest neutral the
    sensor records is display white). The DNG BaselineExposure is reported,
    not applied (linear, it made the Blackmagic file 2 stops brighter than
    LibRaw's rendering). When the gain lifts the sensor's range above
    display white, ``tone="shoulder"`` (the default) asks for the
    highlights to roll off above a knee
    (:func:`recovery.highlights.highlight_shoulder`, ``info["shoulder"]``)
    rather than clip; ``tone="linear"`` clips. Display-encoded outputs
    (sRGB, Display P3) then take LibRaw's tone curve (``info["curve"] =
    "libraw"``, :func:`display_curve`) unless ``tone="linear"``, so the
    picture is as bright as LibRaw's default rendering at every level.

    ``target``: a light name, ``"estimate"``/``"as-seen"`` (the light
    itself) or a spectrum. ``info`` has ``rendering``, ``neutral`` (the
    light's camera RGB, largest channel 1, for the highlight handling),
    ``encoding``, ``exposure``, ``tone`` and the rendering's figures. Raises
    :class:`~recovery.errors.InputError` (``invalid_parameter`` for an
    unknown target or an exposure out of range, ``unrenderable`` when white
    has no luminance).
    """
    from .errors import InputError

    wl = np.asarray(camera.wavelengths, float)
    neutral = None
    if light_rgb is not None:
        rgb = np.asarray(light_rgb, float)
        neutral = rgb / np.max(rgb)
    if profile is not None and neutral is not None and np.all(neutral > 0) and space.Gamma is not None:
        from .dng_color import D50_XY, bradford, camera_to_xyz_d50

        M50, dinfo = camera_to_xyz_d50(profile, neutral)
        wxy = _target_xy(target, dinfo["white_xy"], wl)
        M = np.linalg.solve(space.Gamma, bradford(D50_XY, wxy) @ M50)
        info = {"rendering": "dng-matrix", "encoding": space.encoding,
                "neutral": neutral.tolist(), "white_xy": dinfo["white_xy"],
                "temperature": dinfo["temperature"], "tint": dinfo["tint"],
                "calibration_weight": dinfo["calibration_weight"], "forward_matrix": dinfo["forward_matrix"],
                "baseline_exposure": float(profile.baseline_exposure), "target_white_xy": [float(v) for v in wxy]}
        if profile.notes:
            info["notes"] = list(profile.notes)
        return _with_exposure(M, info, image, exposure, tone, space.Gamma)
    tgt = _target_spectrum(target, light_spectrum, wl)
    M, cond = synthesis_matrix(camera.sensitivities, wl, light_spectrum, tgt, surface_basis, space)
    info = {"lighting_condition": cond, "encoding": space.encoding, "rendering": "spectral"}
    if not normalize:
        return M, info
    y = M @ neutral
    lum = float(y[1]) if space.Gamma is None else float((space.Gamma @ y)[1])
    if not (np.isfinite(lum) and lum > 0):
        raise InputError("the light renders white with no luminance", code="unrenderable")
    if np.all(neutral > 0):
        info["neutral"] = neutral.tolist()
    return _with_exposure(M / lum, info, image, exposure, tone, space.Gamma)
