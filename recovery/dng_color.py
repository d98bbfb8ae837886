"""Camera RGB to XYZ and to a display by the DNG specification's colour model.

For a camera known only by its colour matrices (no measured spectral
sensitivities) the rendering follows the *Digital Negative (DNG)
Specification* 1.4.0.0 (Adobe, 2012), chapter 6, "Mapping Camera Color
Space to CIE XYZ Space", as the DNG SDK implements it
(``dng_color_spec.cpp``, ``dng_temperature.cpp``):

1. ``XYZtoCamera = AB * CC * CM`` with ``CM`` the ColorMatrix interpolated
   between ColorMatrix1/2 linearly in inverse correlated colour temperature
   of the white (``g = (1/T - 1/T2) / (1/T1 - 1/T2)``, clamped to [0, 1],
   ``T1 < T2`` the temperatures of CalibrationIlluminant1/2), ``CC`` the
   CameraCalibration (interpolated the same way), ``AB`` the diagonal
   AnalogBalance. The white's temperature depends on the matrix, so the
   camera neutral's xy is found by iteration (``NeutralToXY``: start at D50,
   at most 30 passes, converged when ``|dx| + |dy| < 1e-7``).
2. With ForwardMatrix tags: ``CameraToXYZ_D50 = FM * D^-1 * (AB * CC)^-1``
   where ``FM`` is interpolated like ``CM`` and normalised so that
   ``FM * (1, 1, 1)`` is the D50 white, and ``D = diag(ReferenceNeutral)``,
   ``ReferenceNeutral = (AB * CC)^-1 * CameraNeutral``. Without them:
   ``CameraToXYZ_D50 = CA * XYZtoCamera^-1`` with ``CA`` the (linearised)
   Bradford adaptation from the white's xy to D50.
3. The camera neutral is scaled so its largest channel is 1 ("PCS white can
   just be reached when the first camera channel saturates"), i.e. a neutral
   surface saturating the sensor maps to Y = 1; BaselineExposure multiplies
   by ``2 ** BaselineExposure``.

For non-DNG RAWs the single XYZ(D65) -> camera matrix LibRaw carries for the
camera (``rawpy``'s ``rgb_xyz_matrix``, from Adobe's DNG converter) is used
as a one-illuminant profile (no ForwardMatrix: path 2's second branch).

Temperature and tint (:func:`xy_to_temperature_tint`) are Adobe's: Robertson's
(1968) method on the isotemperature lines of Wyszecki & Stiles, *Color
Science* 2nd ed. (1982), Table 1(3.11), p. 228, with tint the signed
distance from the locus along the isotemperature line times -3000 (the DNG
SDK's ``kTintScale``): a light greener than the locus (above it in xy) has
a positive tint, which Camera Raw's slider compensates with magenta.

Everything here is plain numpy on 3x3 matrices and 3-vectors.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "D50_XY", "D65_XY", "ColorProfile", "illuminant_temperature", "xy_to_temperature_tint",
    "temperature_tint_to_xy", "xy_to_xyz", "xyz_to_xy", "bradford", "rgb_to_xyz_matrix",
    "PRIMARIES", "neutral_to_xy", "xy_to_neutral", "xyz_to_camera", "camera_to_xyz_d50", "camera_to_output",
]

#: D50 and D65 as the DNG SDK writes them (``D50_xy_coord``, ``D65_xy_coord``).
D50_XY = (0.3457, 0.3585)
D65_XY = (0.3127, 0.3290)

#: Linearised Bradford cone response matrix (Lam 1985; DNG SDK ``MapWhiteMatrix``).
BRADFORD = np.array([[0.8951, 0.2664, -0.1614],
                     [-0.7502, 1.7135, 0.0367],
                     [0.0389, -0.0685, 1.0296]])

#: Output RGB spaces: primaries xy (R, G, B) and white xy.
PRIMARIES = {
    "sRGB": (((0.64, 0.33), (0.30, 0.60), (0.15, 0.06)), D65_XY),            # IEC 61966-2-1
    "Display P3": (((0.680, 0.320), (0.265, 0.690), (0.150, 0.060)), D65_XY),  # SMPTE EG 432-1, D65
}

# EXIF LightSource -> temperature (K), DNG SDK ``dng_camera_profile::IlluminantToTemperature``
_LIGHT_SOURCE_K = {
    17: 2850.0, 3: 2850.0,                      # Standard light A, tungsten
    24: 3200.0,                                 # ISO studio tungsten
    23: 5000.0,                                 # D50
    20: 5500.0, 1: 5500.0, 9: 5500.0, 4: 5500.0, 18: 5500.0,  # D55, daylight, fine weather, flash, B
    21: 6500.0, 19: 6500.0, 10: 6500.0,         # D65, C, cloudy
    22: 7500.0, 11: 7500.0,                     # D75, shade
    12: (5700.0 + 7100.0) * 0.5,                # daylight fluorescent
    13: (4600.0 + 5500.0) * 0.5,                # day white fluorescent
    14: (3800.0 + 4500.0) * 0.5, 2: (3800.0 + 4500.0) * 0.5,  # cool white, fluorescent
    15: (3250.0 + 3800.0) * 0.5,                # white fluorescent
    16: (2600.0 + 3250.0) * 0.5,                # warm white fluorescent
}

# Robertson's isotemperature lines: reciprocal megakelvin, u, v (CIE 1960) of
# the Planckian locus and the slope of the line (Wyszecki & Stiles 1982,
# Table 1(3.11), as tabulated in the DNG SDK, ``dng_temperature.cpp``).
_ROBERTSON = np.array([
    [0, 0.18006, 0.26352, -0.24341], [10, 0.18066, 0.26589, -0.25479],
    [20, 0.18133, 0.26846, -0.26876], [30, 0.18208, 0.27119, -0.28539],
    [40, 0.18293, 0.27407, -0.30470], [50, 0.18388, 0.27709, -0.32675],
    [60, 0.18494, 0.28021, -0.35156], [70, 0.18611, 0.28342, -0.37915],
    [80, 0.18740, 0.28668, -0.40955], [90, 0.18880, 0.28997, -0.44278],
    [100, 0.19032, 0.29326, -0.47888], [125, 0.19462, 0.30141, -0.58204],
    [150, 0.19962, 0.30921, -0.70471], [175, 0.20525, 0.31647, -0.84901],
    [200, 0.21142, 0.32312, -1.0182], [225, 0.21807, 0.32909, -1.2168],
    [250, 0.22511, 0.33439, -1.4512], [275, 0.23247, 0.33904, -1.7298],
    [300, 0.24010, 0.34308, -2.0637], [325, 0.24702, 0.34655, -2.4681],
    [350, 0.25591, 0.34951, -2.9641], [375, 0.26400, 0.35200, -3.5814],
    [400, 0.27218, 0.35407, -4.3633], [425, 0.28039, 0.35577, -5.3762],
    [450, 0.28863, 0.35714, -6.7262], [475, 0.29685, 0.35823, -8.5955],
    [500, 0.30505, 0.35907, -11.324], [525, 0.31320, 0.35968, -15.628],
    [550, 0.32129, 0.36011, -23.325], [575, 0.32931, 0.36038, -40.770],
    [600, 0.33724, 0.36051, -116.45],
])
_TINT_SCALE = -3000.0


def illuminant_temperature(light_source) -> float | None:
    """Temperature (K) the DNG SDK assigns to an EXIF LightSource code
    (CalibrationIlluminant1/2); ``None`` for unknown codes.

    >>> illuminant_temperature(17), illuminant_temperature(21)
    (2850.0, 6500.0)
    """
    try:
        return _LIGHT_SOURCE_K.get(int(light_source))
    except (TypeError, ValueError):
        return None


def xy_to_xyz(xy, Y: float = 1.0) -> np.ndarray:
    x, y = float(xy[0]), float(xy[1])
    return np.array([x * Y / y, Y, (1.0 - x - y) * Y / y])


def xyz_to_xy(xyz) -> np.ndarray:
    v = np.asarray(xyz, float)
    s = v.sum()
    return v[:2] / s if s != 0 else np.array(D50_XY)


def xy_to_temperature_tint(xy) -> tuple[float, float]:
    """Adobe's temperature (K) and tint of a chromaticity (DNG SDK
    ``dng_temperature::Set_xy_coord``): Robertson's method between the two
    isotemperature lines that bracket the point; tint is the distance from
    the locus along the interpolated line, times -3000.

    >>> t, tint = xy_to_temperature_tint(D65_XY)
    >>> round(t), round(tint, 1)
    (6504, 9.8)
    """
    x, y = float(xy[0]), float(xy[1])
    d = 1.5 - x + 6.0 * y
    u, v = 2.0 * x / d, 3.0 * y / d
    last_dt = last_du = last_dv = 0.0
    for i in range(1, len(_ROBERTSON)):
        r1, u1, v1, t1 = _ROBERTSON[i]
        n = np.hypot(1.0, t1)
        du, dv = 1.0 / n, t1 / n
        dt = -(u - u1) * dv + (v - v1) * du
        if dt <= 0.0 or i == len(_ROBERTSON) - 1:
            dt = -min(dt, 0.0)
            f = 0.0 if i == 1 else dt / (last_dt + dt)
            r0, u0, v0, _ = _ROBERTSON[i - 1]
            temperature = 1.0e6 / (r0 * f + r1 * (1.0 - f))
            uu = u - (u0 * f + u1 * (1.0 - f))
            vv = v - (v0 * f + v1 * (1.0 - f))
            du, dv = du * (1.0 - f) + last_du * f, dv * (1.0 - f) + last_dv * f
            n = np.hypot(du, dv)
            return float(temperature), float((uu * du + vv * dv) / n * _TINT_SCALE)
        last_dt, last_du, last_dv = dt, du, dv
    raise AssertionError("unreachable")


def temperature_tint_to_xy(temperature: float, tint: float = 0.0) -> np.ndarray:
    """Inverse of :func:`xy_to_temperature_tint` (``Get_xy_coord``).

    >>> xy = temperature_tint_to_xy(*xy_to_temperature_tint((0.40, 0.39)))
    >>> [round(float(v), 6) for v in xy]
    [0.4, 0.39]
    """
    r = 1.0e6 / float(temperature)
    off = float(tint) / _TINT_SCALE
    tab = _ROBERTSON
    i = int(np.clip(np.searchsorted(tab[:, 0], r, side="right") - 1, 0, len(tab) - 2))
    f = (tab[i + 1, 0] - r) / (tab[i + 1, 0] - tab[i, 0])
    u = tab[i, 1] * f + tab[i + 1, 1] * (1.0 - f)
    v = tab[i, 2] * f + tab[i + 1, 2] * (1.0 - f)
    d1 = np.array([1.0, tab[i, 3]]) / np.hypot(1.0, tab[i, 3])
    d2 = np.array([1.0, tab[i + 1, 3]]) / np.hypot(1.0, tab[i + 1, 3])
    d = d1 * f + d2 * (1.0 - f)
    d /= np.linalg.norm(d)
    u, v = u + d[0] * off, v + d[1] * off
    return np.array([1.5 * u / (u - 4.0 * v + 2.0), v / (u - 4.0 * v + 2.0)])


def bradford(src_xy, dst_xy) -> np.ndarray:
    """Linearised Bradford adaptation XYZ(src white) -> XYZ(dst white)
    (DNG SDK ``MapWhiteMatrix``, cone gains clamped to [0.1, 10])."""
    w1 = BRADFORD @ xy_to_xyz(src_xy)
    w2 = BRADFORD @ xy_to_xyz(dst_xy)
    gain = np.clip(w2 / np.where(w1 > 0, w1, 1e-10), 0.1, 10.0)
    return np.linalg.solve(BRADFORD, np.diag(gain) @ BRADFORD)


def rgb_to_xyz_matrix(space: str = "sRGB") -> np.ndarray:
    """Linear RGB -> XYZ of an output space from its primaries and white
    (white RGB (1, 1, 1) -> white XYZ with Y = 1)."""
    prim, white = PRIMARIES[space]
    P = np.stack([xy_to_xyz(p) for p in prim], axis=1)
    s = np.linalg.solve(P, xy_to_xyz(white))
    return P * s


@dataclass
class ColorProfile:
    """The colour tags of a DNG (or LibRaw's matrix for another RAW).

    Matrices are 3x3 (3-channel cameras). ``illuminant1/2`` are EXIF
    LightSource codes; ``temperature1/2`` their temperatures. ``source`` says
    where the matrices came from (``"DNG tags"`` or ``"LibRaw"``).
    """

    color_matrix1: np.ndarray
    color_matrix2: np.ndarray | None = None
    forward_matrix1: np.ndarray | None = None
    forward_matrix2: np.ndarray | None = None
    camera_calibration1: np.ndarray | None = None
    camera_calibration2: np.ndarray | None = None
    analog_balance: np.ndarray | None = None
    illuminant1: int | None = None
    illuminant2: int | None = None
    baseline_exposure: float = 0.0
    as_shot_neutral: np.ndarray | None = None
    as_shot_white_xy: np.ndarray | None = None
    default_crop: tuple | None = None        # (top, left, height, width) in the active area
    source: str = "DNG tags"
    notes: list = field(default_factory=list)

    @classmethod
    def from_matrix(cls, xyz_to_camera, source: str = "LibRaw") -> "ColorProfile":
        """A one-illuminant profile from an XYZ(D65) -> camera matrix."""
        return cls(np.asarray(xyz_to_camera, float)[:3, :3], illuminant1=21, source=source)

    # -- the SDK's preparation (dng_color_spec constructor) -----------------
    def _prepared(self):
        """``(T1, T2, CM1, CM2, FM1, FM2, CC1, CC2)`` with ``AB * CC`` folded
        into the colour matrices, forward matrices normalised, ordered so
        ``T1 <= T2``; one illuminant repeats."""
        I3 = np.eye(3)
        AB = np.diag(self.analog_balance) if self.analog_balance is not None else I3
        cc1 = self.camera_calibration1 if self.camera_calibration1 is not None else I3
        cc2 = self.camera_calibration2 if self.camera_calibration2 is not None else I3
        fm1 = _normalize_forward(self.forward_matrix1)
        fm2 = _normalize_forward(self.forward_matrix2)
        t1 = illuminant_temperature(self.illuminant1) or 0.0
        t2 = illuminant_temperature(self.illuminant2) or 0.0
        cm1 = AB @ cc1 @ self.color_matrix1
        if self.color_matrix2 is None or t1 <= 0 or t2 <= 0 or t1 == t2:
            return (5000.0, 5000.0, cm1, cm1, fm1, fm1, cc1, cc1)
        cm2 = AB @ cc2 @ self.color_matrix2
        if fm2 is None:
            fm2 = fm1
        if t1 > t2:
            return (t2, t1, cm2, cm1, fm2, fm1, cc2, cc1)
        return (t1, t2, cm1, cm2, fm1, fm2, cc1, cc2)


def _normalize_forward(fm):
    """Rows scaled so ``FM @ (1, 1, 1)`` is the D50 white (``NormalizeForwardMatrix``)."""
    if fm is None:
        return None
    fm = np.asarray(fm, float)
    s = fm @ np.ones(3)
    return np.diag(xy_to_xyz(D50_XY) / s) @ fm


def _weight(profile_prep, white_xy) -> float:
    t1, t2 = profile_prep[0], profile_prep[1]
    if t1 == t2:
        return 1.0
    temp, _ = xy_to_temperature_tint(white_xy)
    if temp <= t1:
        return 1.0
    if temp >= t2:
        return 0.0
    return (1.0 / temp - 1.0 / t2) / (1.0 / t1 - 1.0 / t2)


def xyz_to_camera(profile: ColorProfile, white_xy, _prep=None):
    """``(XYZtoCamera, ForwardMatrix or None, CameraCalibration, g)`` for a
    white (DNG SDK ``FindXYZtoCamera``); ``g`` is the weight of the lower-
    temperature calibration."""
    p = _prep or profile._prepared()
    g = _weight(p, white_xy)
    cm = g * p[2] + (1.0 - g) * p[3]
    fm = None if p[4] is None else g * p[4] + (1.0 - g) * p[5]
    cc = g * p[6] + (1.0 - g) * p[7]
    return cm, fm, cc, g


def neutral_to_xy(profile: ColorProfile, neutral) -> np.ndarray:
    """The white's xy from a camera neutral (DNG SDK ``NeutralToXY``)."""
    n = np.asarray(neutral, float)
    prep = profile._prepared()
    last = np.array(D50_XY, float)
    for k in range(30):
        cm, *_ = xyz_to_camera(profile, last, prep)
        nxt = xyz_to_xy(np.linalg.solve(cm, n))
        if abs(nxt[0] - last[0]) + abs(nxt[1] - last[1]) < 1e-7:
            return nxt
        if k == 29:
            nxt = 0.5 * (last + nxt)
        last = nxt
    return last


def xy_to_neutral(profile: ColorProfile, white_xy) -> np.ndarray:
    """The camera neutral of a white chromaticity (DNG SDK ``SetWhiteXY``;
    DNG specification 1.6, "Mapping Camera Color Space to CIE XYZ Space"):
    ``XYZtoCamera * XYZ(white_xy)`` with the colour matrix interpolated for
    that white's temperature (:func:`xyz_to_camera`), scaled to a largest
    channel of 1 and clipped to [0.001, 1] as the SDK does. The inverse of
    :func:`neutral_to_xy`; what a DNG's AsShotWhiteXY means as an
    AsShotNeutral.

    >>> p = ColorProfile(np.eye(3))
    >>> [round(float(v), 4) for v in xy_to_neutral(p, (1 / 3, 1 / 3))]
    [1.0, 1.0, 1.0]

    Raises
    ------
    ValueError
        ``white_xy`` is not a chromaticity (two finite numbers, each
        positive, summing to less than 1), or the neutral is not positive.
    """
    v = np.asarray(white_xy, dtype=np.float64).ravel()
    if v.size != 2 or not np.all(np.isfinite(v)) or not np.all(v > 0) or v.sum() >= 1.0:
        raise ValueError(f"white_xy must be a chromaticity (x > 0, y > 0, x + y < 1), got {white_xy!r}")
    cm, *_ = xyz_to_camera(profile, v)
    n = cm @ xy_to_xyz(v)
    if not np.all(np.isfinite(n)) or n.max() <= 0:
        raise ValueError(f"the colour matrix gives no positive camera neutral for white_xy {tuple(v)}")
    return np.clip(n / n.max(), 0.001, 1.0)


def camera_to_xyz_d50(profile: ColorProfile, neutral) -> tuple[np.ndarray, dict]:
    """Camera RGB (1.0 = saturation) -> XYZ relative to D50, white-balanced
    for ``neutral`` (DNG spec chapter 6): the neutral scaled to a largest
    channel of 1 maps to the D50 white with Y = 1. No BaselineExposure.

    Returns the matrix and ``info`` (white ``xy``, ``temperature``,
    ``tint``, the interpolation weight ``g``, ``forward_matrix`` used)."""
    n = np.asarray(neutral, float)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.all(n > 0):
        raise ValueError(f"camera neutral must be three positive numbers, got {n}")
    prep = profile._prepared()
    xy = neutral_to_xy(profile, n)
    cm, fm, cc, g = xyz_to_camera(profile, xy, prep)
    # the SDK recomputes the neutral from xy (SetWhiteXY), scaled to max 1
    white = cm @ xy_to_xyz(xy)
    white = np.clip(white / white.max(), 0.001, 1.0)
    if fm is not None:
        AB = np.diag(profile.analog_balance) if profile.analog_balance is not None else np.eye(3)
        to_ref = np.linalg.inv(AB @ cc)
        ref_white = to_ref @ white
        M = fm @ np.diag(1.0 / ref_white) @ to_ref
    else:
        pcs_to_camera = cm @ bradford(D50_XY, xy)
        scale = np.max(pcs_to_camera @ xy_to_xyz(D50_XY))
        M = np.linalg.inv(pcs_to_camera / scale)
    T, tint = xy_to_temperature_tint(xy)
    return M, {"white_xy": [float(xy[0]), float(xy[1])], "temperature": T, "tint": tint,
               "calibration_weight": float(g), "forward_matrix": fm is not None,
               "camera_white": white.tolist()}


def camera_to_output(profile: ColorProfile, neutral, space: str = "sRGB", white_xy=None,
                     baseline_exposure: bool = True) -> tuple[np.ndarray, dict]:
    """Camera RGB -> linear output RGB (``space`` in :data:`PRIMARIES`).

    XYZ D50 is adapted (Bradford) to ``white_xy`` (default: the output
    space's white, i.e. the neutral renders as display white; pass another
    xy to render the scene as under that light) and converted with the
    space's primaries; ``2 ** BaselineExposure`` applied when asked.
    """
    M, info = camera_to_xyz_d50(profile, neutral)
    wxy = PRIMARIES[space][1] if white_xy is None else white_xy
    out = np.linalg.solve(rgb_to_xyz_matrix(space), bradford(D50_XY, wxy) @ M)
    gain = 2.0 ** float(profile.baseline_exposure) if baseline_exposure else 1.0
    info.update(exposure_gain=gain, baseline_exposure=float(profile.baseline_exposure) if baseline_exposure else 0.0,
                output_white_xy=[float(wxy[0]), float(wxy[1])])
    return out * gain, info
