"""Spectral synthesis with a chosen wavelength sampling: reflectance cubes
and lists of spectra rendered to a display under one light.

The tristimulus values of the colour signal ``E(l) S(l)`` are (Wandell 1985,
[docs/references.md#seed-002], eq. 1-4 and 22-23; Meyer 1988 [docs/references.md#seed-000], eq. 1)

    T_k = k_w sum_l E(l) S(l) xbar_k(l) dl ,   k_w = 1 / sum_l E(l) ybar(l) dl ,

so a perfect white reflector under the light has Y = 1. A sampling rule
(:mod:`models.sampling`) replaces ``S`` by ``n`` coefficients ``c = A S`` and
the integral by ``c @ M`` with one ``(n, 3)`` matrix per light
(:meth:`models.sampling.SpectralRule.tristimulus_matrix`). Everything after
the coefficients is linear too (resampling onto the analysis grid, the
display's Gamma^-1 of Wandell's eq. 23-24, an optional von Kries adaptation),
so the whole calculation is one ``(N_in, 3)`` matrix ``K`` applied to every
pixel's spectrum. A point or quadrature rule has few non-zero rows in ``K``:
only the bands next to its nodes are ever read (Kment 2011 [docs/references.md#seed-001],
sec. 3.1: point sampling; Borges 1992 [docs/references.md#seed-004], eq. 3: shared
abscissas), which is where its speed comes from.

``strategy="auto"`` picks the rule that reads the fewest bands while the mean
CIEDE2000 against the full calculation, measured on a pixel sample of the
data at hand, stays within a stated bound (default 1, tested as the sample
mean plus two standard errors); spiky (fluorescent) lights are
detected and then kept exact in ``K`` instead of being sampled (model only
what the scene requires: the surfaces are smooth, the light is not).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from models import DEFAULT_WAVELENGTHS, observer, wavelength_step
from models.grid import resample, resample_box
from models.sampling import LIGHT_AWARE, STRATEGIES, strategy_names

from .errors import InputError

__all__ = [
    "SpectralRender",
    "render_strategies",
    "render_spectra",
    "cached_rule",
    "light_on_grid",
    "light_spikiness",
    "band_matrix",
    "apply_band_matrix",
    "ciede2000_between",
    "ciede2000",
    "lab_from_xyz",
    "AUTO_BOUND",
]

#: Default bound of ``strategy="auto"``: mean CIEDE2000 against the full
#: calculation on the pixel sample. One unit is about a just-noticeable
#: difference for side-by-side patches (CIE 142-2001).
AUTO_BOUND = 1.0
#: Spikiness (fraction of the light's power in narrow lines, see
#: :func:`light_spikiness`) above which a light counts as spiky. The CIE D
#: series, A, C and E are below 0.01 on colour-science's data, every FL light
#: above 0.06.
SPIKY_THRESHOLD = 0.04
#: Values per chunk (pixels x bands read): 2^17 float32 is 0.5 MB (fits
#: L2), so 4096 pixels of a full 31-band product and 16384 pixels of a 5-band
#: one. Small enough that OpenBLAS runs the skinny product on one thread:
#: larger chunks made it spin threads against each other on a loaded 2-core
#: machine (10-50x slower; measured while writing ``benchmarks.spectral``).
CHUNK_VALUES = 1 << 17
_XYZ = "CIE 1931 2 Degree Standard Observer"
#: n tried by ``auto`` for strategies that take a size.
AUTO_SIZES = tuple(range(3, 17))
#: Option sets ``auto`` tries for strategies whose size is implied by an option
#: (Borges' degree sequence gives n = sum of degrees; Meyer's XYZ rule is his
#: A, C1, C2 orders with close nodes merged, 4 wavelengths for 3, 2, 1).
AUTO_OPTIONS = {
    "quasi-gauss-xyz": [{"degrees": (1, 1, 1)}, {"degrees": (2, 2, 2)}, {"degrees": (3, 3, 3)}],
    "gauss-ac1c2": [{"channel": "XYZ", "orders": o} for o in ((3, 2, 1), (4, 2, 1), (5, 2, 2), (6, 4, 2))],
}


def _size_implied(opts: dict) -> bool:
    """True when the options fix the rule's size (``n`` is then not given)."""
    return "degrees" in opts or opts.get("channel") == "XYZ"


@dataclass
class SpectralRender:
    """What :func:`render_spectra` returns: ``image`` (``(H, W, 3)`` or
    ``(M, 3)`` float32) and ``report`` (a dict of plain numbers and strings).
    Unpacks as ``image, report``."""

    image: np.ndarray
    report: dict = field(default_factory=dict)

    def __iter__(self):
        return iter((self.image, self.report))


# --- the light --------------------------------------------------------------------


def light_spikiness(values, wavelengths) -> float:
    """Fraction of a light's power in narrow emission lines.

    The light minus its running median over 40 nm, positive part, integrated
    and divided by the light's integral over 380-780 nm. Smooth lights
    (blackbodies, CIE daylight) score below 0.01 on colour-science's data;
    the FL series 0.06-0.5 (FL11, three-band, 0.5). This is the test that
    decides whether a light is 'spiky' in Kment's sense (2011 [docs/references.md#seed-001],
    ch. 5: fluorescent lights need composite or filtered representations).

    Examples
    --------
    >>> import colour
    >>> fl = colour.SDS_ILLUMINANTS["FL11"]
    >>> light_spikiness(fl.values, fl.wavelengths) > 0.3
    True
    >>> d = colour.SDS_ILLUMINANTS["D65"]
    >>> light_spikiness(d.values, d.wavelengths) < 0.02
    True
    """
    from scipy.ndimage import median_filter

    v = np.asarray(values, float)
    wl = np.asarray(wavelengths, float)
    keep = (wl >= 380) & (wl <= 780)
    if keep.sum() >= 3:
        v, wl = v[keep], wl[keep]
    if v.size < 3:
        return 0.0
    step = float(np.median(np.diff(wl)))
    width = max(3, int(round(40.0 / step)) | 1)
    smooth = median_filter(v, size=width, mode="nearest")
    total = float(np.sum(np.abs(v)))
    return float(np.sum(np.maximum(v - smooth, 0.0)) / total) if total > 0 else 0.0


@lru_cache(maxsize=256)
def _named_spikiness(name: str):
    """Spikiness of a colour-science illuminant on its own sampling, or None."""
    import colour

    if name not in colour.SDS_ILLUMINANTS:
        return None
    sd = colour.SDS_ILLUMINANTS[name]
    return light_spikiness(sd.values, sd.wavelengths)


def light_on_grid(light, grid=None, light_wavelengths=None) -> tuple[np.ndarray, dict]:
    """A light as ``(N,)`` values on the analysis grid, plus what is known of it.

    Parameters
    ----------
    light : str or array_like
        A name :func:`models.illuminant` knows (``"D65"``, ``"FL11"``,
        ``"D5000"``, ``"BB3200"``) or relative spectral power values.
    light_wavelengths : array_like, optional
        Wavelengths of an array light; default: the analysis grid.

    Returns
    -------
    values : ndarray (N,)
        On a grid coarser than the data the light is box-averaged
        (:func:`models.grid.resample_box`: narrow lines keep their energy).
    info : dict
        ``name``, ``spikiness`` (on the light's own sampling), ``spiky``.
    """
    from models import illuminant

    grid = DEFAULT_WAVELENGTHS if grid is None else np.asarray(grid, float)
    if isinstance(light, str):
        try:
            values = illuminant(light, grid)
        except KeyError as e:
            raise InputError(str(e).strip("'\"")) from None
        spk = _named_spikiness(light)
        if spk is None:
            spk = light_spikiness(values, grid)
        name = light
    else:
        v = np.asarray(light, dtype=float)
        lw = grid if light_wavelengths is None else np.asarray(light_wavelengths, float)
        if v.ndim != 1 or v.size != lw.size:
            raise InputError(f"light has {v.size} values for {lw.size} wavelengths")
        if lw.size < 2 or not np.all(np.isfinite(lw)) or np.any(np.diff(lw) <= 0):
            raise InputError("light wavelengths must be finite and strictly increasing")
        if not np.all(np.isfinite(v)) or np.any(v < 0):
            raise InputError("light values must be finite and non-negative")
        spk = light_spikiness(v, lw)
        if lw.size == grid.size and np.allclose(lw, grid):
            values = v
        elif float(np.min(np.diff(grid))) > float(np.min(np.diff(lw))) * 1.01:
            values = resample_box(lw, v, grid)
        else:
            values = resample(lw, v, grid)
        name = "uploaded"
    if not np.any(values > 0):
        raise InputError("the light has no power on the analysis grid "
                         f"({grid[0]:g}-{grid[-1]:g} nm)")
    return np.asarray(values, float), {"name": name, "spikiness": round(spk, 4),
                                       "spiky": bool(spk > SPIKY_THRESHOLD)}


# --- the matrices -----------------------------------------------------------------


def _output_transform(output: str, grid: np.ndarray, white_xyz: np.ndarray, adapt: bool):
    return _output_transform_cached(output, tuple(np.asarray(grid, float).tolist()),
                                    tuple(np.asarray(white_xyz, float).tolist()), bool(adapt))


@lru_cache(maxsize=128)
def _output_transform_cached(output: str, grid: tuple, white_xyz: tuple, adapt: bool):
    """``(3, 3)`` matrix ``C`` (row vectors: ``out = xyz @ C``) and the
    encoding, for an output name of :func:`recovery.synthesis.output_space`.

    Display values are ``Gamma^-1 T`` (Wandell 1985, eq. 23-24). With
    ``adapt`` the XYZ are first taken from the light's white to the output's
    white by a CAT02 von Kries transform (colour-science's
    ``matrix_chromatic_adaptation_VonKries``); without it the colour signal's
    own tristimulus values are shown.
    """
    from .synthesis import output_space

    grid, white_xyz = np.asarray(grid), np.asarray(white_xyz)
    try:
        space = output_space(output, grid)
    except (ValueError, KeyError) as e:
        raise InputError(str(e)) from None
    C = np.eye(3)
    if adapt:
        import colour

        target = (space.Gamma @ np.ones(3)) if space.Gamma is not None and space.Gamma.shape == (3, 3) \
            else np.asarray(colour.xy_to_XYZ(colour.CCS_ILLUMINANTS[_XYZ]["D65"]))
        target = target / target[1]
        C = np.asarray(colour.adaptation.matrix_chromatic_adaptation_VonKries(white_xyz, target, "CAT02")).T
    if space.Gamma is not None:
        C = C @ np.linalg.inv(space.Gamma).T
    return C, space.encoding


def render_strategies() -> list[str]:
    """Strategies :func:`render_spectra` accepts besides ``auto`` and ``full``:
    every strategy of :data:`models.sampling.STRATEGIES`, the light-aware ones
    (:data:`models.sampling.LIGHT_AWARE`, which model surfaces only: the light
    is always kept exact) included."""
    return strategy_names(light_aware=True)


def _accepts(strategy: str, param: str) -> bool:
    """Whether the strategy's builder takes ``param`` (e.g. ``light``: a
    rule built for the light at hand, such as a composite one)."""
    import inspect

    try:
        return param in inspect.signature(STRATEGIES[strategy]).parameters
    except (KeyError, AttributeError, ImportError, TypeError, ValueError):
        return False


def _key(v):
    if isinstance(v, np.ndarray):
        return ("__array__", v.shape, tuple(np.asarray(v, float).ravel().tolist()))
    if isinstance(v, list):
        return tuple(v)
    return v


def _unkey(v):
    if isinstance(v, tuple) and len(v) == 3 and v[0] == "__array__":
        return np.asarray(v[2], float).reshape(v[1])
    return v


@lru_cache(maxsize=256)
def _rule_cached(strategy: str, n, wl: tuple, options: tuple):
    return STRATEGIES[strategy](n, np.asarray(wl), **{k: _unkey(v) for k, v in options})


def cached_rule(strategy, n, grid, options, light=None, cmfs=None):
    """The rule ``strategy`` of size ``n`` on ``grid`` (cached). Builders
    that take the light (or the observer) get them: their rules are made
    for the scene's light (bands chosen for it, spikes kept)."""
    opts = dict(options)
    for name, value in (("light", light), ("cmfs", cmfs)):
        if value is not None and name not in opts and _accepts(strategy, name):
            opts[name] = np.asarray(value, float)
    key = tuple(sorted((k, _key(v)) for k, v in opts.items()))
    return _rule_cached(strategy, None if n is None else int(n), tuple(np.asarray(grid, float).tolist()), key)


def band_matrix(rule, light: np.ndarray, cmfs: np.ndarray, represent_light: bool,
                grid=None) -> np.ndarray:
    """``(N, 3)`` matrix from a spectrum on the rule's grid to tristimulus
    values: ``analysis.T @ tristimulus_matrix`` (Meyer 1988, eq. 1 with the
    rule's nodes and weights; Wandell 1985, eq. 22). ``rule=None`` is the
    full calculation ``cmfs * light * dl`` on ``grid`` (default the analysis
    grid). Not normalised to white."""
    light = np.asarray(light, float)
    if rule is None:
        g = DEFAULT_WAVELENGTHS if grid is None else np.asarray(grid, float)
        return np.asarray(cmfs, float) * (light * wavelength_step(g))[:, None]
    M = rule.tristimulus_matrix(light, cmfs, represent_light=represent_light)
    return np.asarray(rule.analysis, float).T @ np.asarray(M, float)


def _sparsify(K: np.ndarray) -> np.ndarray:
    """Zero the rows of ``K`` that are round-off (below 1e-12 of the largest)."""
    K = np.array(K, dtype=float)
    scale = float(np.abs(K).max()) or 1.0
    K[np.all(np.abs(K) <= 1e-12 * scale, axis=1)] = 0.0
    return K


# --- applying the matrix ----------------------------------------------------------


def apply_band_matrix(cube: np.ndarray, K: np.ndarray, check: bool = True) -> tuple[np.ndarray, dict]:
    """``cube @ K`` for ``(..., N)`` spectra, reading only the bands where
    ``K`` has a non-zero row, in float32 chunks of :data:`CHUNK_VALUES` values (no
    ``H x W x N`` temporary).

    Band-interleaved cubes (``(H, W, N)`` C-ordered, the ``.npy`` layout)
    gather their bands per chunk; band-sequential ones (an ``(H, W, N)`` view
    of an ``(N, H, W)`` array, e.g. ``np.moveaxis(bsq, 0, -1)``) read whole
    planes, so a rule with ``k`` bands reads ``k / N`` of the data.

    With ``check`` the output is checked for non-finite values (a NaN or Inf
    in a band that is read reaches the output; checking the 3 output values
    costs a tenth of checking the N input values) (:class:`InputError`).

    Returns
    -------
    out : ndarray (..., 3) float32
    info : dict with ``bands_read`` and ``layout``
    """
    cube = np.asarray(cube)
    N = cube.shape[-1]
    lead = cube.shape[:-1]
    K = np.asarray(K)
    idx = np.flatnonzero(np.any(K != 0, axis=1))
    if idx.size == 0:
        idx = np.array([0])
    P = int(np.prod(lead)) if lead else 1
    out = np.empty((P, K.shape[1]), np.float32)
    try:
        x = np.reshape(cube, (P, N), copy=False)
    except (ValueError, TypeError):
        x = cube.reshape(P, N)
    planar = N > 1 and P > 1 and abs(x.strides[1]) > abs(x.strides[0])
    # interleaved data: gathering more than half the bands costs more than
    # multiplying the zero rows
    full = idx.size == N or (not planar and 2 * idx.size > N)
    Ks = np.ascontiguousarray(K if full else K[idx], dtype=np.float32)
    chunk_px = int(np.clip(1 << int(np.log2(CHUNK_VALUES // Ks.shape[0])), 1024, 65536))
    for s in range(0, P, chunk_px):
        e = min(P, s + chunk_px)
        if full and not planar:
            chunk = x[s:e]
        elif planar:
            chunk = x.T[idx, s:e].T
        else:
            chunk = np.take(x[s:e], idx, axis=1)
        if chunk.dtype != np.float32:
            chunk = chunk.astype(np.float32)
        np.matmul(chunk, Ks, out=out[s:e])
    if check and not np.isfinite(out).all():
        raise InputError("the spectra contain non-finite values (NaN or Inf)")
    return out.reshape(lead + (K.shape[1],)), {"bands_read": int(idx.size),
                                                "layout": "band-sequential" if planar else "band-interleaved"}


# --- errors -----------------------------------------------------------------------


def lab_from_xyz(xyz: np.ndarray, white_xyz: np.ndarray) -> np.ndarray:
    """CIELAB (CIE 015:2018, eq. 8.1-8.3) of ``(M, 3)`` XYZ relative to
    ``white_xyz`` (colour-science's ``XYZ_to_Lab``)."""
    import colour

    w = np.asarray(white_xyz, float)
    return colour.XYZ_to_Lab(np.asarray(xyz, float) / w[1], colour.XYZ_to_xy(w))


def ciede2000(lab1: np.ndarray, lab2: np.ndarray) -> np.ndarray:
    """CIEDE2000 colour difference (CIE 142-2001), ``(M,)`` for ``(M, 3)``
    CIELAB pairs, kL = kC = kH = 1 (colour-science's ``delta_E_CIE2000``;
    checked against Sharma, Wu and Dalal's 2005 test data in
    ``tests/test_spectral.py``)."""
    import colour

    return np.asarray(colour.difference.delta_E_CIE2000(np.asarray(lab1, float), np.asarray(lab2, float)))


def ciede2000_between(xyz_a: np.ndarray, xyz_b: np.ndarray, white_xyz: np.ndarray) -> np.ndarray:
    """CIEDE2000 (:func:`ciede2000`) between two sets of XYZ ``(M, 3)``
    scaled so the light's white has Y = 1, in CIELAB relative to that white."""
    d = ciede2000(lab_from_xyz(xyz_a, white_xyz), lab_from_xyz(xyz_b, white_xyz))
    return np.where(np.isfinite(d), d, np.inf)


def _stats(d: np.ndarray) -> dict:
    if d.size == 0:
        return {"mean": 0.0, "p95": 0.0, "max": 0.0}
    return {"mean": float(np.mean(d)), "p95": float(np.percentile(d, 95)), "max": float(np.max(d))}


# --- the public function ----------------------------------------------------------


def _validate(spectra, wavelengths):
    arr = np.asarray(spectra)
    if arr.dtype.kind not in "fiu":
        raise InputError(f"spectra must be a numeric array, not dtype {arr.dtype}")
    if arr.ndim not in (2, 3):
        raise InputError(f"spectra must be a cube (H, W, N) or a list of spectra (M, N); got {arr.ndim} "
                         f"dimensions {arr.shape}")
    wl = np.asarray(wavelengths, dtype=float)
    if wl.ndim != 1 or wl.size < 2:
        raise InputError("need at least two wavelengths")
    if not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
        raise InputError("wavelengths must be finite and strictly increasing")
    if arr.shape[-1] != wl.size:
        raise InputError(f"the spectra have {arr.shape[-1]} bands for {wl.size} wavelengths")
    return arr, wl


def _input_map(wl: np.ndarray, grid: np.ndarray) -> tuple[np.ndarray, list]:
    """``(N_grid, N_in)`` linear map of :func:`models.grid.resample` from the
    input wavelengths onto the analysis grid (resampling the identity: the
    interpolation is linear), plus warnings."""
    warnings = []
    if wl.size == grid.size and np.allclose(wl, grid):
        return np.eye(grid.size), warnings
    if wl[0] > grid[0] + 1e-9 or wl[-1] < grid[-1] - 1e-9:
        warnings.append(f"the data cover {wl[0]:g}-{wl[-1]:g} nm, less than the analysis grid "
                        f"{grid[0]:g}-{grid[-1]:g} nm: the ends are extrapolated as constants")
    R = resample(wl, np.eye(wl.size), grid)
    R[np.abs(R) < 1e-12] = 0.0
    return R, warnings


def _sample(x2: np.ndarray, size: int, seed: int = 0, run: int = 16) -> np.ndarray:
    """About ``size`` pixels (every pixel when there are fewer): runs of
    ``run`` neighbouring pixels at random places (fixed seed), in memory
    order. A run of 16 float32 pixels is one cache line per band plane, so a
    band-sequential cube costs ``size / 16`` line reads per band instead of
    ``size``; the runs still spread over the whole image. Band planes are
    gathered one at a time."""
    P = x2.shape[0]
    if P <= size:
        return np.asarray(x2, float), 0
    run = max(1, min(run, P // max(1, size // run)))
    starts = np.sort(np.random.default_rng(seed).integers(0, P - run + 1, max(1, size // run)))
    idx = (starts[:, None] + np.arange(run)).ravel()
    if x2.shape[1] > 1 and abs(x2.strides[1]) > abs(x2.strides[0]):
        return np.stack([np.take(x2[:, j], idx) for j in range(x2.shape[1])], 1).astype(float), run
    return np.asarray(x2[idx], float), run


def render_spectra(spectra, wavelengths, light, strategy: str = "auto", n: int | None = None,
                   output: str = "sRGB", adapt: bool = False, *, light_wavelengths=None,
                   max_error: float = AUTO_BOUND, sample_pixels: int = 4096,
                   represent_light: bool | None = None, check: bool = True,
                   **options) -> SpectralRender:
    """Render reflectance spectra under a light with a chosen wavelength sampling.

    Implements the synthesis of Wandell (1985 [docs/references.md#seed-002], eq. 22-24):
    the colour signal's own tristimulus values ``T_k = k_w sum E S xbar_k dl``
    (a perfect white reflector under the light has Y = 1), then display
    values ``Gamma^-1 T`` and the display encoding, with the integral
    evaluated by a sampling rule of :mod:`models.sampling` (Meyer 1988,
    [docs/references.md#seed-000], eq. 1-3; Borges 1992 [docs/references.md#seed-004], eq. 3; Kment 2011,
    [docs/references.md#seed-001], ch. 3). All linear steps are folded into one ``(N, 3)``
    matrix per light (:func:`band_matrix`).

    Parameters
    ----------
    spectra : array_like, (H, W, N) or (M, N)
        Reflectances (>= 0) on ``wavelengths``.
    wavelengths : array_like (N,)
        nm, strictly increasing. The analysis grid is
        :data:`models.DEFAULT_WAVELENGTHS` (400-700 nm, 10 nm); other grids are
        mapped onto it by :func:`models.grid.resample`, folded into the matrix.
    light : str or array_like
        Illuminant name (``"D65"``, ``"FL11"``, ...) or values on
        ``light_wavelengths`` (default: the analysis grid).
    strategy : str
        ``"auto"``, ``"full"`` (every band, exact) or a name of
        :func:`render_strategies`.
    n : int, optional
        Size of the rule. ``None`` with a named strategy: the smallest size of
        that strategy that keeps the bound (as ``auto`` does within it).
    output : str
        ``"sRGB"`` (encoded, clipped to [0, 1]), ``"linear-sRGB"``, ``"XYZ"``
        or a display name of :func:`recovery.synthesis.output_space`.
    adapt : bool
        CAT02 adaptation from the light's white to the output's white; off
        by default (the paper's synthesis shows the colour signal as it is).
    max_error : float
        Bound on the mean CIEDE2000 against the full calculation for
        ``auto`` (default 1), tested as sample mean plus two standard errors
        (runs of neighbouring pixels counted as single draws).
    sample_pixels : int
        Pixels sampled (fixed seed) to estimate the error.
    represent_light : bool, optional
        True: the light is held in the rule's representation too (the
        setting of Meyer, Borges and Kment). False: the exact light is folded
        into the matrix. ``None``: decided per rule; quadrature rules with
        per-channel weights (``(n, 3)``: they integrate E*S at their nodes)
        represent it for smooth lights;
        for spiky lights the light is always kept exact.
    check : bool
        Refuse non-finite values (any in a band that is read) and negative
        values (on the sampled pixels; ``POST /v1/render`` checks every
        value before rendering).
    **options
        Passed to the rule (``channel`` for ``gauss-ac1c2``, ``degrees`` for
        ``quasi-gauss-xyz``, ...).

    Returns
    -------
    SpectralRender
        ``image`` float32 ``(H, W, 3)`` or ``(M, 3)``; ``report`` with
        ``strategy``, ``n``, ``nodes_nm``, ``bands_read``, ``represent_light``,
        ``light`` (name, spikiness, spiky), ``error`` (CIEDE2000 ``mean``,
        ``p95``, ``max`` on ``pixels_sampled`` pixels against the full
        calculation), ``bound``, ``tried``, ``why``, ``timings_ms``,
        ``warnings``.

    Examples
    --------
    >>> import numpy as np
    >>> white = np.ones((2, 2, 31))
    >>> img, rep = render_spectra(white, DEFAULT_WAVELENGTHS, "D65", strategy="full", output="XYZ")
    >>> round(float(img[0, 0, 1]), 6)
    1.0
    """
    t0 = time.perf_counter()
    arr, wl = _validate(spectra, wavelengths)
    if not (np.isfinite(max_error) and max_error > 0):
        raise InputError("max_error must be a positive number")
    if strategy not in ("auto", "full") and strategy not in render_strategies():
        raise InputError(f"unknown sampling strategy {strategy!r}; accepted: auto, full, "
                         f"{', '.join(render_strategies())}")
    if n is not None and (int(n) != n or not 1 <= int(n) <= 64):
        raise InputError(f"n must be an integer in 1..64, not {n!r}")
    grid = DEFAULT_WAVELENGTHS
    E, light_info = light_on_grid(light, grid, light_wavelengths)
    cmfs = observer(_XYZ, grid)
    R, warnings = _input_map(wl, grid)
    dl = wavelength_step(grid)
    k_white = 1.0 / float(np.sum(E * cmfs[:, 1] * dl))
    white_xyz = k_white * np.sum(cmfs * (E * dl)[:, None], axis=0)
    C, encoding = _output_transform(output, grid, white_xyz, adapt)
    K_full = R.T @ (cmfs * (E * dl)[:, None]) * k_white               # (N_in, 3) XYZ

    P = int(np.prod(arr.shape[:-1]))
    try:
        flat = np.reshape(arr, (P, arr.shape[-1]), copy=False)
    except (ValueError, TypeError):
        flat = arr.reshape(P, arr.shape[-1])
    sample, run = _sample(flat, sample_pixels)
    if check and sample.size and not np.all(np.isfinite(sample)):
        raise InputError("the spectra contain non-finite values (NaN or Inf)")
    if check and sample.size and sample.min() < 0:
        raise InputError(f"the spectra contain negative values (minimum {sample.min():.4g}); reflectances are "
                         ">= 0: clip measurement noise first")
    ref = sample @ K_full

    def build(name, size, opts, rep_light):
        """The rule's matrix and the bands it reads, or None with the reason."""
        rule = cached_rule(name, size, grid, opts, E, cmfs)
        base = {"strategy": name, "n": rule.n, **_opt_json(opts)}
        if not getattr(rule, "defined", True):
            return None, {**base, "defined": False, "reason": rule.reason}
        K = _sparsify(R.T @ band_matrix(rule, E, cmfs, rep_light, grid) * k_white)
        if not np.all(np.isfinite(K)):
            return None, {**base, "reason": "non-finite matrix"}
        bands = int(np.count_nonzero(np.any(K != 0, axis=1)))
        return (rule, K, bands, dict(opts), rep_light), {**base, "represent_light": rep_light,
                                                          "bands_read": bands}

    def score(built, entry):
        d = ciede2000_between(ref, sample @ built[1], white_xyz)
        st = _stats(d)
        # standard error of the mean with each run of neighbours as one draw
        # (neighbours are correlated); zero when the sample is every pixel
        se = float(d.reshape(-1, run).mean(axis=1).std(ddof=1) / np.sqrt(d.size // run)) \
            if run and d.size >= 2 * run else 0.0
        st.update(standard_error=se, mean_upper=st["mean"] + 2 * se)
        entry.update(mean=round(st["mean"], 4), p95=round(st["p95"], 4), mean_upper=round(st["mean_upper"], 4))
        return st

    tried: list = []
    t_choose = time.perf_counter()
    spiky = light_info["spiky"]
    if strategy == "full":
        chosen = None
        why = "the full calculation was asked for"
    elif strategy != "auto" and (n is not None or _size_implied(options)):
        try:
            rep = _represent(cached_rule(strategy, n, grid, options, E, cmfs), represent_light, spiky)
            built, entry = build(strategy, n, options, rep)
        except (ValueError, TypeError, KeyError, NotImplementedError, AttributeError, ImportError) as e:
            raise InputError(f"strategy {strategy!r} with n={n} {_opt_json(options)}: {e}") from None
        tried.append(entry)
        if built is None:
            raise InputError(f"strategy {strategy!r} is undefined with n={n} {_opt_json(options)}: "
                             f"{entry.get('reason')}")
        st = score(built, entry)
        entry["chosen"] = True
        rule_, K_, _, o_, r_ = built
        chosen = (rule_, K_, st, o_, r_)
        why = "the strategy and size were asked for"
    else:
        names = render_strategies() if strategy == "auto" else [strategy]
        chosen, why = _choose(names, options, build, score, tried, flat.shape[1], max_error, spiky,
                              represent_light, strategy)
    t_chosen = time.perf_counter()

    if chosen is None:
        K_xyz, st, rule, opts_used, rep_used = K_full, {"mean": 0.0, "p95": 0.0, "max": 0.0, "standard_error": 0.0,
                                                        "mean_upper": 0.0}, None, {}, None
    else:
        rule, K_xyz, st, opts_used, rep_used = chosen
    K_out = K_xyz @ C
    image, info = apply_band_matrix(arr, K_out, check=check)
    t_int = time.perf_counter()
    if encoding is not None:
        image = _encode_inplace(image, encoding)
    t_enc = time.perf_counter()
    report = {
        "strategy": "full" if rule is None else rule.strategy,
        "n": int(wl.size) if rule is None else rule.n,
        "options": _opt_json(opts_used),
        "nodes_nm": wl.tolist() if rule is None or rule.nodes_nm is None
        else np.asarray(rule.nodes_nm, float).tolist(),
        "bands_read": info["bands_read"], "bands_total": int(wl.size), "layout": info["layout"],
        "represent_light": rep_used,
        "light": light_info,
        "error": {"reference": "full calculation on every band, same light, same sample",
                  "metric": "CIEDE2000, CIELAB relative to the light's white",
                  "pixels_sampled": int(sample.shape[0]),
                  "mean": st["mean"], "p95": st["p95"], "max": st["max"],
                  "standard_error": st["standard_error"], "mean_plus_2se": st["mean_upper"]},
        "bound": {"mean_ciede2000": float(max_error),
                  "test": "auto accepts a rule when the sample mean plus 2 standard errors is within the bound"},
        "why": why, "tried": tried, "output": output, "adapt": bool(adapt),
        "white_xyz": white_xyz.tolist(),
        "diagnostics": {} if rule is None else dict(getattr(rule, "diagnostics", {}) or {}),
        "timings_ms": {"choose": (t_chosen - t_choose) * 1e3, "integrate": (t_int - t_chosen) * 1e3,
                       "encode": (t_enc - t_int) * 1e3, "total": (t_enc - t0) * 1e3},
        "warnings": warnings,
    }
    return SpectralRender(image, report)


def _opt_json(opts: dict) -> dict:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dict(opts).items()}


def _represent(rule, represent_light, spiky) -> bool:
    """Whether the light is held in the rule's representation (see
    :func:`render_spectra`)."""
    if rule.strategy in LIGHT_AWARE:
        return False
    if represent_light is not None:
        return bool(represent_light)
    if spiky:
        return False
    return rule.weights is not None and np.ndim(rule.weights) == 2


def _choose(names, options, build, score, tried, n_in, max_error, spiky, represent_light, asked):
    """The cheapest rule (fewest bands read, then fewest coefficients) whose
    mean CIEDE2000 on the sample is within ``max_error``; ``None`` (the full
    calculation) when none that reads fewer bands than the full one does.

    Rules are built by increasing size (a rule of size ``n`` reads at least
    ``n`` bands) and scored in order of the bands they read once no rule
    still to be built can read fewer; the search stops at the first rule
    within the bound, so the cost of choosing grows with what the data need.
    """
    import heapq

    families = []
    for name in names:
        for opts in ([dict(options)] if options else AUTO_OPTIONS.get(name, [{}])):
            if name in LIGHT_AWARE:
                reps = [False]
            elif represent_light is not None:
                reps = [bool(represent_light)]
            else:
                reps = [False] if spiky else [False, True]
            families += [[name, opts, rep, True] for rep in reps]
    heap: list = []
    counter = [0]

    def add(fam, size):
        name, opts, rep, _ = fam
        try:
            built, entry = build(name, size, opts, rep)
        except Exception as e:  # noqa: BLE001 - a strategy that cannot be built is skipped, and said so
            tried.append({"strategy": name, "n": size, **_opt_json(opts), "reason": f"{type(e).__name__}: {e}"})
            if not isinstance(e, ValueError) or size is None:
                fam[3] = False       # not available at all: stop asking
            return
        tried.append(entry)
        if built is None:
            return
        if built[2] >= n_in:
            entry["reason"] = "reads every band: no cheaper than the full calculation"
            fam[3] = False           # larger sizes read every band too
            return
        counter[0] += 1
        heapq.heappush(heap, (built[2], built[0].n, counter[0], built, entry))

    if not spiky:
        light = "smooth light"
    elif represent_light:
        light = "spiky light (sampled by the rules, as asked)"
    else:
        light = "spiky light (kept exact in the matrix; only the surfaces are sampled)"
    best = None

    def drain(limit):
        nonlocal best
        while heap and heap[0][0] <= limit:
            bands, size, _, built, entry = heapq.heappop(heap)
            st = score(built, entry)
            if best is None or st["mean"] < best[1]["mean"]:
                best = (entry, st)
            if st["mean_upper"] <= max_error:
                entry["chosen"] = True
                rule, K, _, opts, rep = built
                return (rule, K, st, opts, rep), (
                    f"{light}: {entry['strategy']} n={size} reads {bands} of {n_in} bands, the fewest among "
                    f"the rules tried in order of cost whose mean CIEDE2000 on the sample plus 2 standard "
                    f"errors is <= {max_error:g} ({st['mean']:.3f} + {2 * st['standard_error']:.3f})")
            entry["reason"] = (f"mean CIEDE2000 {st['mean']:.3f} + 2 standard errors = {st['mean_upper']:.3f} "
                               f"> {max_error:g}")
        return None

    for fam in families:
        if _size_implied(fam[1]):
            add(fam, None)
            fam[3] = False
    for size in AUTO_SIZES:
        for fam in families:
            if fam[3]:
                add(fam, size)
        found = drain(size)
        if found:
            return found
    found = drain(n_in)
    if found:
        return found
    extra = f"; the best was {best[0]['strategy']} n={best[0]['n']} at {best[1]['mean']:.2f}" if best else ""
    what = "rule" if asked == "auto" else f"{asked} rule"
    return None, (f"{light}: no {what} reading fewer than {n_in} bands kept the mean CIEDE2000 (+2 SE) <= "
                  f"{max_error:g}{extra}; rendered with every band (exact)")


def _encode_inplace(image: np.ndarray, encoding: str) -> np.ndarray:
    """Display encoding (:func:`recovery.synthesis.encode`, clip to [0, 1]
    then the transfer function) in chunks, float32 kept."""
    from .synthesis import encode

    flat = image.reshape(-1, image.shape[-1])
    step = 1 << 18
    for s in range(0, flat.shape[0], step):
        flat[s:s + step] = encode(flat[s:s + step], encoding)
    return image
