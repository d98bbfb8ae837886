"""Surface reflectances from a prior over measured surfaces, with error bars (issue 31).

Wandell (1985) recovers a surface by the pseudo-inverse of the lighting
matrix in a model of at most C terms (eq. 36): exact inside the model, and
silent about the rest. Three sensors do not determine a reflectance: every
reflectance that gives the same camera response under the light (the
*metamer set*, Finlayson & Morovic 2005) is as consistent with the data. The
answer has to come from what real surfaces are like, and must say how
uncertain it is.

The model here is Gaussian (Brainard & Freeman 1997, the Gaussian case of
their Bayesian decision theory; Shimano 2006, Wiener estimation of
reflectance):

* prior: :math:`r \\sim N(\\mu, \\Sigma)` learnt from measured reflectance
  sets (:func:`learn_prior`, :func:`default_prior`), the sample covariance
  shrunk toward a smooth covariance (:data:`PRIOR_SHRINKAGE`,
  :data:`PRIOR_LENGTH_NM`) and scaled by :data:`PRIOR_INFLATION`;
* observation: :math:`\\rho = k\\,(A r + n)`, :math:`A_{cn} = R_c(\\lambda_n)
  E(\\lambda_n)\\Delta\\lambda_n` (Wandell eq. 12/17 without a surface basis),
  :math:`n \\sim N(0, \\sigma^2 \\bar s^2 I)` with :math:`\\bar s^2 =
  \\|A\\mu\\|^2 / C` (a noise *relative* to the signal, :data:`PRIOR_NOISE`:
  camera noise and what the linear image model leaves out), and an unknown
  exposure :math:`k` (:func:`exposure_scale`: maximum marginal likelihood);
* posterior (:func:`wiener_gain`):
  :math:`\\hat r = \\mu + K(\\rho/k - A\\mu)`, :math:`K = \\Sigma A^T(A\\Sigma
  A^T + N)^{-1}`, :math:`P = \\Sigma - K A \\Sigma`; the band of a surface is
  :math:`\\sqrt{\\mathrm{diag}\\,P}` per wavelength and its one-number trust
  the expected RMS error :math:`\\sqrt{\\mathrm{tr}\\,P / N}`.

As the prior flattens (:math:`\\mu = 0`, :math:`\\Sigma = s^2 B B^T` for a
C-term basis B, :math:`s \\to \\infty`) :math:`\\hat r \\to B (A B)^{-1}\\rho`,
Wandell's eq. 36 (tested); :func:`pinv_estimate` is that literal method.

What is uncertain besides the surface enters by sampling
(:func:`surface_estimates`, law of total variance over the samples):

* the light: lights whose camera response lies in the estimate's 90 % region
  (``region90_deg``) (:func:`light_samples`);
* the camera: a RAW gives an XYZ -> camera colour matrix, not sensitivities;
  :func:`camera_posterior` is the Gaussian over sensitivities learnt from 47
  measured cameras, conditioned on the matrix (a linear constraint), and
  :func:`generic_camera_samples` the same without a matrix.

The posterior band of this model does not hold the truth at its stated
rate on real surfaces (the prior is learnt from few sets, and the light and
camera samples are approximations): :func:`calibration_factors` learns a
factor per wavelength from errors on reflectance sets left out, and
:func:`calibrate_band` applies it (per kind of camera and light,
:func:`band_kind`; the shipped factors: :func:`band_scale`).

All functions are pure functions on arrays.

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 12, 17 and 36.
D. H. Brainard, W. T. Freeman, "Bayesian color constancy", JOSA A 14(7),
1393-1411, 1997 (Gaussian priors over surfaces, the posterior mean).
N. Shimano, "Recovery of spectral reflectances of objects being imaged
without prior knowledge", IEEE Trans. Image Processing 15(7), 1848-1856,
2006 (Wiener estimation of reflectance; the noise variance as its
regulariser).
G. D. Finlayson, P. Morovic, "Metamer sets", JOSA A 22(5), 810-819, 2005.
O. Ledoit, M. Wolf, "A well-conditioned estimator for large-dimensional
covariance matrices", J. Multivariate Analysis 88, 365-411, 2004 (shrinkage).
J. Jiang, D. Liu, J. Gu, S. Süsstrunk, "What is the space of spectral
sensitivity functions for digital color cameras?", WACV 2013 (camera
sensitivities lie in a low-dimensional space: a prior over cameras).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

__all__ = [
    "PRIOR_SHRINKAGE", "PRIOR_LENGTH_NM", "PRIOR_NOISE", "PRIOR_INFLATION", "PRIOR_BANDWIDTH",
    "gaussian_prior", "smooth_kernel", "CAMERA_SHRINKAGE",
    "MATRIX_TOLERANCE", "MATRIX_GAIN_TOLERANCE", "SurfacePrior", "learn_prior", "default_prior", "lighting_operator", "wiener_gain",
    "wiener_estimate", "pinv_estimate", "exposure_scale", "light_samples", "fit_light", "light_directions", "camera_prior",
    "matrix_operator", "camera_posterior", "generic_camera_samples", "surface_estimates", "surface_estimates_per_point", "sample_widening", "SurfaceEstimates",
    "typicality", "typicality_factor", "TYPICALITY_FLOOR", "BAND_LEVEL", "BAND_Z", "band_kind", "band_scale", "calibrate_band", "calibration_factors",
]

#: The stated band: mean +- BAND_Z std holds the truth at BAND_LEVEL.
BAND_LEVEL = 0.90
BAND_Z = 1.6448536269514722

#: Weight of the smooth covariance in the shrunk prior covariance
#: ``(1 - a) S + a v K``; chosen by leave-one-set-out cross-validation over
#: the five shipped reflectance sets, near-copies of the left-out set removed
#: from training (``python -m benchmarks.surfaces --cv``).
PRIOR_SHRINKAGE = 0.05
#: Correlation length (nm) of the smooth covariance ``K``.
PRIOR_LENGTH_NM = 40.0
#: Relative noise :math:`\sigma` of the observation (same cross-validation).
PRIOR_NOISE = 0.003
#: Factor on the prior covariance. It moves the estimate too (the ratio of
#: prior to noise), so it is no longer used to widen the bands (that took
#: the cross-validated median RMSE from 0.031 to 0.033): the bands are
#: calibrated afterwards, per wavelength (:func:`calibrate_band`).
PRIOR_INFLATION = 1.0
#: Kernel bandwidth ``h`` of the prior (components ``N(r_i, h^2 Sigma)``;
#: ``None`` for one Gaussian); same cross-validation.
PRIOR_BANDWIDTH = 0.3
#: Shrinkage of the 47 cameras' covariance toward a smooth one.
CAMERA_SHRINKAGE = 0.05
#: Tolerances of the colour-matrix constraint: how far a real camera's
#: published matrix (LibRaw/Adobe) is from the least-squares matrix of its
#: measured sensitivities, measured on the three models both hold (Canon
#: EOS-1Ds Mark III, EOS 600D, Nikon D810; ``benchmarks.surfaces`` prints
#: it): per-channel gains off by 3-31 % (RMS 0.16), and after them 7-12 %
#: of the matrix (RMS 0.09).
MATRIX_TOLERANCE = 0.09
MATRIX_GAIN_TOLERANCE = 0.16


# --------------------------------------------------------------------------- the prior
@dataclass(frozen=True)
class SurfacePrior:
    """A prior over reflectances on a wavelength grid: a mixture of Gaussians
    with one shared covariance, centred on ``atoms`` with equal weights (a
    kernel density estimate, Silverman 1986), or one Gaussian (``atoms`` of
    one row, the mean).

    Attributes
    ----------
    wavelengths : (N,) nm
    mean : (N,) the prior's mean
    cov : (N, N) each component's covariance (symmetric positive definite)
    atoms : (M, N) the components' centres
    marginal_cov : (N, N) the prior's whole covariance
    name : str, what it was learnt from
    noise : float, relative observation noise :math:`\sigma`
    """

    wavelengths: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    atoms: np.ndarray
    marginal_cov: np.ndarray
    name: str = "custom"
    noise: float = PRIOR_NOISE

    @property
    def kind(self) -> str:
        """``"gaussian"`` or ``"kernel"``."""
        return "gaussian" if self.atoms.shape[0] == 1 else "kernel"


def gaussian_prior(mean, cov, wavelengths, noise: float = PRIOR_NOISE, name: str = "custom") -> SurfacePrior:
    """One Gaussian :math:`N(\mu, \Sigma)` as a :class:`SurfacePrior`."""
    mu = np.asarray(mean, float)
    C = np.asarray(cov, float)
    return SurfacePrior(np.asarray(wavelengths, float), mu, C, mu[None].copy(), C, name, float(noise))


def smooth_kernel(wavelengths, length_nm: float) -> np.ndarray:
    """Squared-exponential correlation ``exp(-(l_i - l_j)^2 / (2 length^2))``, ``(N, N)``."""
    wl = np.asarray(wavelengths, float)
    return np.exp(-0.5 * ((wl[:, None] - wl[None, :]) / float(length_nm)) ** 2)


def learn_prior(reflectances, wavelengths, *, bandwidth: float | None = PRIOR_BANDWIDTH,
                shrinkage: float = PRIOR_SHRINKAGE, length_nm: float = PRIOR_LENGTH_NM,
                inflation: float = PRIOR_INFLATION, noise: float = PRIOR_NOISE, name: str = "custom") -> SurfacePrior:
    """A prior learnt from measured reflectances.

    The shrunk sample covariance :math:`\Sigma = (1 - a) S + a\,\bar v
    K_\ell` (``S`` the sample covariance, :math:`\bar v = \mathrm{tr}\,S /
    N`, :math:`K_\ell` the squared-exponential correlation of length
    ``length_nm``: a shrinkage target in the sense of Ledoit & Wolf 2004 that
    keeps it full rank and smooth), then

    * ``bandwidth=None``: one Gaussian :math:`N(\bar r, \gamma\Sigma)`;
    * ``bandwidth=h``: the kernel density estimate :math:`\frac1M\sum_i
      N(r_i, \gamma h^2\Sigma)` (Silverman 1986): a density that follows
      the measured surfaces where they cluster instead of one ellipsoid.

    Parameters
    ----------
    reflectances : (M, N) array_like
    wavelengths : (N,) array_like
    bandwidth, shrinkage, length_nm, inflation, noise : float
        ``h``, ``a``, :math:`\ell`, :math:`\gamma` (on the component
        covariance), :math:`\sigma`.
    name : str

    Returns
    -------
    SurfacePrior

    Examples
    --------
    >>> R = np.random.default_rng(0).uniform(0, 1, (50, 31))
    >>> p = learn_prior(R, np.linspace(400, 700, 31), bandwidth=None)
    >>> p.kind, bool(np.all(np.linalg.eigvalsh(p.cov) > 0))
    ('gaussian', True)
    >>> learn_prior(R, np.linspace(400, 700, 31), bandwidth=0.3).atoms.shape
    (50, 31)
    """
    R = np.asarray(reflectances, float)
    wl = np.asarray(wavelengths, float)
    if R.ndim != 2 or R.shape[1] != wl.size or R.shape[0] < 2:
        raise ValueError(f"reflectances must be (M >= 2, N={wl.size}), got {R.shape}")
    mu = R.mean(axis=0)
    S = np.cov(R, rowvar=False)
    v = float(np.trace(S)) / wl.size
    cov = (1.0 - shrinkage) * S + shrinkage * v * smooth_kernel(wl, length_nm)
    cov = 0.5 * (cov + cov.T)
    if bandwidth is None:
        return gaussian_prior(mu, float(inflation) * cov, wl, noise, name)
    comp = float(inflation) * float(bandwidth) ** 2 * cov
    D = R - mu
    return SurfacePrior(wl, mu, comp, R.copy(), D.T @ D / R.shape[0] + comp, name, float(noise))


@functools.lru_cache(maxsize=16)
def _default_prior(wl: tuple, exclude: tuple) -> SurfacePrior:
    from models.surface_data import SURFACE_SETS, surface_sets

    sets = [s for s in SURFACE_SETS if s not in exclude]
    R, _ = surface_sets(np.array(wl), sets)
    return learn_prior(R, np.array(wl), name=f"kernel prior (h = {PRIOR_BANDWIDTH}) of " + " + ".join(sets)
                       + f" ({len(R)} measured surfaces)")


def default_prior(wavelengths=None, exclude=()) -> SurfacePrior:
    """The shipped prior: every set of :data:`models.surface_data.SURFACE_SETS`
    (274 measured surfaces) with the cross-validated hyper-parameters;
    ``exclude`` leaves sets out (cross-validation).

    Examples
    --------
    >>> default_prior().mean.shape
    (31,)
    """
    from models import DEFAULT_WAVELENGTHS

    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return _default_prior(tuple(float(x) for x in wl), tuple(sorted(exclude)))


# --------------------------------------------------------------------------- one camera, one light
def lighting_operator(sensitivities, spectrum, dlambda) -> np.ndarray:
    """:math:`A_{cn} = R_c(\\lambda_n) E(\\lambda_n) \\Delta\\lambda_n`: camera
    response to a reflectance under the light, ``(..., C, N)`` (Wandell eq. 12
    and 17 with the identity as surface basis). Broadcasts over leading
    axes of ``sensitivities`` ``(..., N, C)`` and ``spectrum`` ``(..., N)``."""
    R = np.asarray(sensitivities, float)
    E = np.asarray(spectrum, float)
    w = np.asarray(dlambda, float)
    return np.swapaxes(R, -1, -2) * (E * w)[..., None, :]


def _noise_var(prior: SurfacePrior, A: np.ndarray, noise: float | None) -> np.ndarray:
    s = prior.noise if noise is None else float(noise)
    Am = A @ prior.mean
    return (s * s) * np.sum(Am * Am, axis=-1) / A.shape[-2]


def wiener_gain(prior: SurfacePrior, A, noise: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gain and posterior covariance of the Wiener / Gaussian-Bayes estimate.

    :math:`K = \\Sigma A^T (A \\Sigma A^T + \\sigma^2 \\bar s^2 I)^{-1}`,
    :math:`P = \\Sigma - K A \\Sigma` (Brainard & Freeman 1997; Shimano 2006).

    Parameters
    ----------
    prior : SurfacePrior
    A : (..., C, N) lighting operator (:func:`lighting_operator`)
    noise : float, optional
        Relative noise :math:`\\sigma` (default the prior's).

    Returns
    -------
    K : (..., N, C)
    P : (..., N, N)
    """
    A = np.asarray(A, float)
    SA = prior.cov @ np.swapaxes(A, -1, -2)                      # (..., N, C)
    G = A @ SA                                                   # (..., C, C)
    C = A.shape[-2]
    G = G + _noise_var(prior, A, noise)[..., None, None] * np.eye(C)
    K = np.swapaxes(np.linalg.solve(G, np.swapaxes(SA, -1, -2)), -1, -2)
    P = prior.cov - K @ np.swapaxes(SA, -1, -2)
    return K, 0.5 * (P + np.swapaxes(P, -1, -2))


def wiener_estimate(prior: SurfacePrior, A, rho, noise: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Posterior mean ``(P, N)`` and covariance ``(N, N)`` for responses ``rho`` ``(P, C)``
    (exposure 1) under a Gaussian prior: :math:`\\hat r = \\mu + K(\\rho - A\\mu)`.

    Examples
    --------
    >>> wl = np.linspace(400, 700, 31)
    >>> p = learn_prior(np.random.default_rng(1).uniform(0, 1, (40, 31)), wl, bandwidth=None)
    >>> A = np.random.default_rng(2).uniform(0, 1, (3, 31))
    >>> m, P = wiener_estimate(p, A, (A @ p.mean)[None])
    >>> bool(np.allclose(m[0], p.mean))
    True
    """
    A = np.asarray(A, float)
    K, P = wiener_gain(prior, A, noise)
    rho = np.atleast_2d(np.asarray(rho, float))
    return prior.mean + (rho - A @ prior.mean) @ K.T, P


def pinv_estimate(A, basis, rho) -> np.ndarray:
    """Wandell's eq. 36, the literal method: :math:`\\sigma = \\Lambda_E^{+}\\rho`,
    :math:`r = B\\sigma` with :math:`\\Lambda_E = A B` (``(C, D)``), ``(P, N)``."""
    L = np.asarray(A, float) @ np.asarray(basis, float)
    return np.atleast_2d(np.asarray(rho, float)) @ np.linalg.pinv(L).T @ np.asarray(basis, float).T


def exposure_scale(prior: SurfacePrior, A, rho, noise: float | None = None) -> float:
    """Exposure :math:`k` of the responses by maximum marginal likelihood.

    Under the prior :math:`\\rho_i / k \\sim N(A\\mu, G)` with :math:`G =
    A\\Sigma A^T + \\sigma^2\\bar s^2 I`; with :math:`u = 1/k` the
    log-likelihood :math:`PC\\log u - \\frac12\\sum_i (u\\rho_i - A\\mu)^T
    G^{-1}(u\\rho_i - A\\mu)` is maximal at :math:`u = (b + \\sqrt{b^2 +
    4aPC}) / (2a)`, :math:`a = \\sum_i \\rho_i^T G^{-1}\\rho_i`, :math:`b =
    \\sum_i \\mu^T A^T G^{-1}\\rho_i`. Scale-equivariant: ``exposure_scale(c
    rho) = c exposure_scale(rho)``.

    Returns
    -------
    float
        ``k > 0``; 1.0 when ``rho`` carries no signal.
    """
    A = np.asarray(A, float)
    rho = np.atleast_2d(np.asarray(rho, float))
    rho = rho[np.all(np.isfinite(rho), axis=1)]
    if rho.size == 0:
        return 1.0
    c = float(np.max(np.abs(rho)))
    if not (c > 0 and np.isfinite(c)):
        return 1.0
    rho = rho / c                    # any representable exposure: the sums below neither overflow nor underflow
    G = A @ prior.marginal_cov @ A.T + _noise_var(prior, A, noise) * np.eye(A.shape[0])
    Gi = np.linalg.inv(G)
    a = float(np.einsum("pi,ij,pj->", rho, Gi, rho))
    b = float(np.sum(rho @ Gi @ (A @ prior.mean)))
    n = rho.size
    if not (a > 0 and np.isfinite(a)):
        return 1.0
    u = (b + np.sqrt(b * b + 4.0 * a * n)) / (2.0 * a)
    return c * float(1.0 / u) if u > 0 and np.isfinite(u) else c


# --------------------------------------------------------------------------- the light's uncertainty
def fit_light(spectrum, sensitivities, dlambda, target, total: float | None = None) -> np.ndarray:
    """The light spectrum modulated so the camera sees it as ``target``.

    :math:`E' = E\,(b_0 + b_1 t + b_2 t^2)` with :math:`t` the wavelength
    mapped to [-1, 1], the coefficients solved so the camera response is
    proportional to ``target`` (least squares for C > 3), clipped at 0 and
    scaled so the camera's total response is ``total`` (default its total
    response to ``E``): samples of a camera then see the light as bright as
    the nominal camera does, and one exposure serves them all. What the image gives is the
    light's colour *in the camera's own space* (the estimate's ``rgb``); a
    camera known only approximately (a matrix, or nothing) then still sees
    the light as the image does, so a channel gain of the camera model that
    is off is not read as a colour of every surface.

    Parameters
    ----------
    spectrum : (N,)
    sensitivities : (N, C)
    dlambda : (N,)
    target : (C,) or (n, C)

    Returns
    -------
    (N,) or (n, N)
    """
    E = np.asarray(spectrum, float)
    R = np.asarray(sensitivities, float)
    w = np.asarray(dlambda, float)
    tg = np.atleast_2d(np.asarray(target, float))
    rho0 = R.T @ (E * w)
    tg = tg / np.linalg.norm(tg, axis=1, keepdims=True) * np.linalg.norm(rho0)
    t = np.linspace(-1.0, 1.0, E.size)
    B = np.stack([np.ones_like(t), t, t * t], 1)                  # (N, 3)
    M = R.T @ (B * (E * w)[:, None])                              # (C, 3)
    coef = np.linalg.lstsq(M, tg.T, rcond=None)[0].T               # (n, 3)
    out = np.clip(E[None] * (coef @ B.T), 0.0, None)
    tot = (out @ (R * w[:, None])).sum(axis=1)
    ok = (tot > 0) & np.all(np.isfinite(out), axis=1)
    want = rho0.sum() if total is None else float(total)
    out[ok] *= (want / tot[ok])[:, None]
    out[~ok] = E * want / rho0.sum()
    return out[0] if np.ndim(target) == 1 else out


def light_directions(rgb, region90_deg: float, n: int, seed: int = 0) -> np.ndarray:
    """Light colours in the estimate's 90 % region, ``(n, C)`` unit vectors.

    The region is read as an isotropic Gaussian on the sphere of camera
    responses around ``rgb`` with angular radius ``region90_deg`` at 90 %
    (for a 2-D Gaussian :math:`r_{90} = \sigma\sqrt{-2\ln 0.1}`); ``n``
    copies of ``rgb`` when the radius is 0."""
    d0 = np.asarray(rgb, float)
    d0 = d0 / np.linalg.norm(d0)
    if not (region90_deg and region90_deg > 0 and np.isfinite(region90_deg)) or n < 1:
        return np.broadcast_to(d0, (max(n, 1), d0.size)).copy()
    sigma = np.deg2rad(float(region90_deg)) / np.sqrt(-2.0 * np.log(0.1))
    z = np.random.default_rng(seed).standard_normal((n, d0.size))
    z -= np.outer(z @ d0, d0)                                     # the tangent plane
    dirs = d0 + sigma * z
    return dirs / np.linalg.norm(dirs, axis=1, keepdims=True)


def light_samples(spectrum, sensitivities, dlambda, region90_deg: float, n: int, seed: int = 0,
                  rgb=None) -> np.ndarray:
    """Lights whose camera response falls in the estimate's 90 % region, ``(n, N)``:
    :func:`light_directions` around ``rgb`` (default the camera's response to
    ``spectrum``), each made a spectrum by :func:`fit_light`."""
    E = np.asarray(spectrum, float)
    R = np.asarray(sensitivities, float)
    centre = R.T @ (E * np.asarray(dlambda, float)) if rgb is None else rgb
    return fit_light(E, R, dlambda, light_directions(centre, region90_deg, n, seed))


# --------------------------------------------------------------------------- the camera's uncertainty
@functools.lru_cache(maxsize=16)
def _camera_prior(wl: tuple, exclude: tuple, shrinkage: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    from models.surface_data import camera_set

    wlv = np.array(wl)
    names, S = camera_set(wlv)                                   # (K, N, 3)
    keep = [i for i, nm in enumerate(names) if nm not in exclude]
    S = S[keep]
    X = _normalise_cameras(S, wlv)
    flat = np.swapaxes(X, 1, 2).reshape(len(X), -1)               # channel blocks: [R; G; B]
    mu = flat.mean(axis=0)
    cov = np.cov(flat, rowvar=False)
    N = wlv.size
    Kb = smooth_kernel(wlv, 20.0)
    target = np.zeros_like(cov)
    for c in range(3):
        blk = slice(c * N, (c + 1) * N)
        v = float(np.trace(cov[blk, blk])) / N
        target[blk, blk] = v * Kb
    cov = (1 - shrinkage) * cov + shrinkage * target
    return mu, 0.5 * (cov + cov.T), X


def _d65_weights(wavelengths) -> np.ndarray:
    from models import illuminant, wavelength_step

    wl = np.asarray(wavelengths, float)
    E = illuminant("D65", wl)
    return E / E.mean() * wavelength_step(wl)


def _normalise_cameras(S, wavelengths) -> np.ndarray:
    """Sensitivities ``(..., N, 3)`` scaled so the green response to D65 is 1."""
    w = _d65_weights(wavelengths)
    g = np.einsum("...n,n->...", np.asarray(S, float)[..., 1], w)
    return np.asarray(S, float) / g[..., None, None]


def camera_prior(wavelengths, exclude=(), shrinkage: float = CAMERA_SHRINKAGE) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(3N,)`` and covariance ``(3N, 3N)`` of the 47 measured cameras'
    sensitivities, stacked by channel (``[R; G; B]``), each camera scaled so
    its green response to D65 is 1, the covariance shrunk toward a smooth
    block-diagonal one (Jiang et al. 2013: camera sensitivities span a small
    space). ``exclude`` leaves cameras out by name (cross-validation)."""
    mu, cov, _ = _camera_prior(tuple(float(x) for x in np.asarray(wavelengths, float)), tuple(sorted(exclude)),
                               float(shrinkage))
    return mu, cov


@functools.lru_cache(maxsize=16)
def _matrix_fit(wl: tuple) -> np.ndarray:
    from models import observer
    from models.surface_data import surface_sets

    wlv = np.array(wl)
    Ssurf, _ = surface_sets(wlv)
    w = _d65_weights(wlv)
    X = (Ssurf * w) @ observer("CIE 1931 2 Degree Standard Observer", wlv)      # (m, 3)
    return np.linalg.solve(X.T @ X, X.T @ (Ssurf * w))                         # (3, N): M[k] = Q^T R[:, k]


def matrix_operator(wavelengths) -> np.ndarray:
    """``Q^T`` ``(3, N)``: the least-squares XYZ -> camera matrix of a camera
    under D65 over the shipped reflectances is linear in its sensitivities,
    :math:`M_{k\\cdot} = Q^T R_{\\cdot k}` (:math:`Q^T = (X^TX)^{-1}X^T S
    \\mathrm{diag}(E\\Delta\\lambda)`, X the surfaces' XYZ)."""
    return _matrix_fit(tuple(float(x) for x in np.asarray(wavelengths, float)))


def normalise_matrix(color_matrix, wavelengths) -> np.ndarray:
    """An XYZ -> camera matrix scaled so the green response to D65's white is 1
    (the cameras' normalisation of :func:`camera_prior`)."""
    from models import observer

    M = np.asarray(color_matrix, float)
    wl = np.asarray(wavelengths, float)
    xyz = _d65_weights(wl) @ observer("CIE 1931 2 Degree Standard Observer", wl)
    g = float((M @ xyz)[1])
    if not (abs(g) > 0 and np.isfinite(g)):
        raise ValueError("the colour matrix gives no green response to D65")
    return M / g


def camera_posterior(color_matrix, wavelengths, n: int = 32, seed: int = 0, exclude=(),
                     tolerance: float = MATRIX_TOLERANCE,
                     gain_tolerance: float = MATRIX_GAIN_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """Sensitivities consistent with an XYZ -> camera colour matrix.

    The 47 measured cameras give a Gaussian over sensitivities
    (:func:`camera_prior`); the matrix constrains it linearly,
    :math:`H x = m` with :math:`H = \\mathrm{blockdiag}(Q^T, Q^T, Q^T)`
    (:func:`matrix_operator`), up to a tolerance: a published matrix is not
    the least-squares matrix of the measured sensitivities, mostly by a gain
    per channel. The constraint's noise covariance is :math:`T = \\tau^2
    \\bar m^2 I + \\tau_g^2\\,\\mathrm{blockdiag}(m_c m_c^T)` (a relative
    error :math:`\\tau`, and a gain error :math:`\\tau_g` per channel c).
    Gaussian conditioning: :math:`\\hat x = \\mu + C H^T(HCH^T +
    T)^{-1}(m - H\\mu)`, :math:`C' = C - C H^T(HCH^T + T)^{-1}HC`.

    Parameters
    ----------
    color_matrix : (3, 3) XYZ -> camera (rows R, G, B), any scale
    wavelengths : (N,)
    n : int
        Samples to draw (negative values clipped to 0).
    seed : int
    exclude : camera names left out of the prior (cross-validation)
    tolerance : float

    Returns
    -------
    mean : (N, 3) posterior mean sensitivities, scaled so the green response to D65 is 1
    samples : (n, N, 3)
    """
    wl = np.asarray(wavelengths, float)
    N = wl.size
    mu, C = camera_prior(wl, exclude)
    Qt = matrix_operator(wl)
    H = np.zeros((9, 3 * N))
    for c in range(3):
        H[3 * c:3 * c + 3, c * N:(c + 1) * N] = Qt
    m = normalise_matrix(color_matrix, wl).reshape(-1)              # rows: channel c's 3 coefficients
    tau2 = (float(tolerance) * np.sqrt(np.mean(m * m))) ** 2
    Nc = tau2 * np.eye(9)
    for c in range(3):                                            # a channel's gain: m_c -> (1 + g) m_c
        mc = m[3 * c:3 * c + 3]
        Nc[3 * c:3 * c + 3, 3 * c:3 * c + 3] += float(gain_tolerance) ** 2 * np.outer(mc, mc)
    CH = C @ H.T
    G = H @ CH + Nc
    Kg = np.linalg.solve(G, CH.T).T
    xm = mu + Kg @ (m - H @ mu)
    Cp = C - Kg @ CH.T
    Cp = 0.5 * (Cp + Cp.T)
    return _to_sens(xm, N), _draw(xm, Cp, N, n, seed)


def generic_camera_samples(wavelengths, n: int = 32, seed: int = 0, exclude=()) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``(N, 3)`` and samples ``(n, N, 3)`` of the 47 cameras' Gaussian
    (no matrix known: a generic camera)."""
    wl = np.asarray(wavelengths, float)
    mu, C = camera_prior(wl, exclude)
    return _to_sens(mu, wl.size), _draw(mu, C, wl.size, n, seed)


def _to_sens(x, N) -> np.ndarray:
    return np.clip(np.asarray(x, float).reshape(3, N).T, 0.0, None)


def _draw(mean, cov, N, n, seed) -> np.ndarray:
    vals, vecs = np.linalg.eigh(cov)
    L = vecs * np.sqrt(np.clip(vals, 0.0, None))
    z = np.random.default_rng(seed).standard_normal((n, mean.size))
    x = mean + z @ L.T
    return np.clip(np.swapaxes(x.reshape(n, 3, N), 1, 2), 0.0, None)


# --------------------------------------------------------------------------- estimates with bands
@dataclass
class SurfaceEstimates:
    """Estimates of surfaces with their uncertainty.

    Attributes
    ----------
    mean : (P, N) posterior mean reflectance
    std : (P, N) posterior standard deviation per wavelength (the band)
    expected_rmse : (P,) :math:`\\sqrt{\\mathrm{mean}_\\lambda\\,\\mathrm{std}^2}`,
        the RMS error the model expects
    exposure : float, the exposure :math:`k` the responses were divided by
    samples : int, lights x cameras drawn (1: light and camera taken as known)
    typicality : (P,) or None
        How unlike the prior's surfaces the response is: :func:`typicality`
        under the nominal light and camera (``None`` where not computed).
    excluded : (P,) bool or None
        True where the point's pixel was left out of the analysis (outside
        the mask given, saturated or dark: ``AnalysisResult.usable``): its
        response is clipped or noise, so its estimate cannot be trusted
        (``None`` where not known: responses without pixels).
    """

    mean: np.ndarray
    std: np.ndarray
    expected_rmse: np.ndarray
    exposure: float
    samples: int
    typicality: np.ndarray | None = None
    excluded: np.ndarray | None = None


def _mixture_moments(prior: SurfacePrior, A, y, noise) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The posterior for one lighting operator ``A`` ``(C, N)``: its mean,
    the components' weighted mean ``sum_i w_i r_i`` and the spread of the
    components' posterior means, each ``(P, N)``, and the responses'
    :func:`typicality` ``(P,)``.

    Each component i gives the Gaussian posterior :math:`N(r_i + K(y - A r_i),
    P)` with the shared gain and covariance of :func:`wiener_gain`, and the
    weight :math:`w_i \propto N(y; A r_i, G)`, :math:`G = A\Sigma A^T +
    \sigma^2\bar s^2 I`; with :math:`c_i = r_i - K A r_i` the mean is
    :math:`\sum_i w_i c_i + K y` and the variance :math:`\mathrm{diag}P +
    \sum_i w_i c_i^2 - (\sum_i w_i c_i)^2`."""
    K, P = wiener_gain(prior, A, noise)
    AR = prior.atoms @ A.T                                            # (M, C)
    Ky = y @ K.T                                                      # (P, N)
    c = prior.atoms - AR @ K.T                                        # (M, N)
    G = A @ prior.cov @ A.T + _noise_var(prior, A, noise) * np.eye(A.shape[0])
    Gi = np.linalg.inv(G)
    yGy = np.einsum("pc,cd,pd->p", y, Gi, y)
    ll = (y @ Gi) @ AR.T - 0.5 * np.einsum("mc,cd,md->m", AR, Gi, AR)[None]   # (P, M); y'G^-1 y left out
    top = ll.max(axis=1, keepdims=True)
    W = np.exp(ll - top)
    sw = W.sum(axis=1, keepdims=True)
    typ = _typicality(yGy, top[:, 0] + np.log(sw[:, 0]), AR.shape[0], A.shape[0])
    if prior.atoms.shape[0] == 1:
        return c[0] + Ky, np.broadcast_to(prior.atoms[0], Ky.shape), np.zeros_like(Ky), typ
    W /= sw
    N = c.shape[1]
    both = W @ np.concatenate([prior.atoms, c, c * c], axis=1)         # one product: (P, 3N)
    Wa, Wc, Wc2 = both[:, :N], both[:, N:2 * N], both[:, 2 * N:]
    return Wc + Ky, Wa, np.clip(Wc2 - Wc * Wc, 0.0, None), typ


def _typicality(yGy, lse, M: int, C: int) -> np.ndarray:
    """:func:`typicality` from ``y'G^-1 y`` ``(P,)`` and ``log sum_i exp(y'G^-1 A r_i - r_i'A'G^-1 A r_i / 2)``."""
    return np.clip((yGy - 2.0 * lse + 2.0 * np.log(M)) / C, 0.0, None)


def typicality(prior: SurfacePrior, A, y, noise: float | None = None) -> np.ndarray:
    """How unlike the prior's surfaces a response is: the mixture's squared
    Mahalanobis distance per channel, ``(P,)``.

    With :math:`q_i = (y - A r_i)^T G^{-1} (y - A r_i)`, :math:`G = A\Sigma
    A^T + \sigma^2\bar s^2 I` (the covariance of one component's predictive
    density), :math:`t = -\frac{2}{C}\log\frac1M\sum_i e^{-q_i/2}`: minus
    twice the log predictive likelihood of ``y`` under the prior's mixture up
    to its normalising constant, per channel. For one Gaussian it is the
    squared Mahalanobis distance of ``y`` from :math:`A\mu` over ``C`` (mean 1
    under the prior); for a kernel prior it grows with the distance of ``y``
    from the nearest atoms' responses, in units of a component's spread. A
    band that widens with it (:func:`typicality_factor`) widens for responses
    unlike the surfaces the prior was learnt from.

    Parameters
    ----------
    prior : SurfacePrior
    A : (C, N) lighting operator
    y : (P, C) responses (divided by the exposure)
    noise : float, optional

    Returns
    -------
    (P,) non-negative

    Examples
    --------
    >>> wl = np.linspace(400, 700, 31)
    >>> p = learn_prior(np.random.default_rng(1).uniform(0, 1, (40, 31)), wl, bandwidth=None)
    >>> A = np.random.default_rng(2).uniform(0, 1, (3, 31))
    >>> float(typicality(p, A, (A @ p.mean)[None])[0])
    0.0
    """
    return _mixture_moments(prior, np.asarray(A, float), np.atleast_2d(np.asarray(y, float)), noise)[3]


def surface_estimates(prior: SurfacePrior, rho, sensitivities, spectra, dlambda, *, exposure: float | None = None,
                      scene_rho=None, noise: float | None = None, nominal: bool = False) -> SurfaceEstimates:
    """Posterior mean and band of surfaces, over sampled lights and cameras.

    For one light and camera the posterior under the prior's mixture is a
    mixture of Gaussians (:func:`_mixture_moments`): mean and variance are
    exact. With samples :math:`s = 1..S` of (light, camera) the estimate is
    the mean over samples and its variance the mean second moment minus the
    squared mean (law of total variance); to keep this at the cost of one
    pass over the prior's atoms, the components' weights are those of the
    mean lighting operator :math:`\bar A` for every sample (a sample moves
    the likelihood of an atom little): sample s's mean is :math:`\sum_i w_i
    r_i + K_s(y - A_s \sum_i w_i r_i)` and its spread across components is
    taken as :math:`\bar A`'s.

    Parameters
    ----------
    prior : SurfacePrior
    rho : (P, C) camera responses of the surfaces
    sensitivities : (N, C) or (S, N, C)
        The camera, or samples of it.
    spectra : (N,) or (S, N)
        The light, or samples of it (broadcast against the cameras).
    dlambda : (N,)
    exposure : float, optional
        :math:`k`; default :func:`exposure_scale` of ``scene_rho`` (default
        ``rho``) under :math:`\bar A`.
    scene_rho : (Q, C), optional
        Responses of the whole scene for the exposure.
    noise : float, optional
    nominal : bool
        Sample 0 is the nominal (light, camera): the estimate is its
        posterior mean, and the other samples only widen the band, by their
        mean squared deviation from it (averaging posterior means over
        cameras blurs the estimate: measured in ``benchmarks.surfaces``).

    Returns
    -------
    SurfaceEstimates
    """
    R = np.asarray(sensitivities, float)
    E = np.asarray(spectra, float)
    A = lighting_operator(R, E, dlambda)
    if A.ndim == 2:
        A = A[None]
    A = A.reshape(-1, A.shape[-2], A.shape[-1])
    A0 = A[0] if nominal else A.mean(axis=0)
    rho = np.atleast_2d(np.asarray(rho, float))
    if exposure is None:
        exposure = exposure_scale(prior, A0, rho if scene_rho is None else scene_rho, noise)
    y = rho / float(exposure)
    mean0, Wa, spread, typ = _mixture_moments(prior, A0, y, noise)
    if A.shape[0] == 1:
        var = np.diagonal(wiener_gain(prior, A0, noise)[1])[None] + spread
        mean = mean0
    else:
        K, P = wiener_gain(prior, A, noise)                                         # (S, N, C), (S, N, N)
        innov = y[None] - np.einsum("pn,scn->spc", Wa, A, optimize=True)           # (S, P, C)
        ms = Wa[None] + np.einsum("spc,snc->spn", innov, K, optimize=True)         # (S, P, N)
        if nominal:
            mean = mean0
            dev = ms[1:] - mean0[None]
            var = (np.diagonal(P, axis1=1, axis2=2).mean(axis=0)[None] + spread + (dev * dev).mean(axis=0))
        else:
            mean = ms.mean(axis=0)
            var = (np.diagonal(P, axis1=1, axis2=2).mean(axis=0)[None] + spread + (ms * ms).mean(axis=0)
                   - mean * mean)
    std = np.sqrt(np.clip(var, 0.0, None))
    return SurfaceEstimates(mean, std, np.sqrt(np.mean(std * std, axis=1)), float(exposure), int(A.shape[0]), typ)


def sample_widening(prior: SurfacePrior, rho, sensitivities, spectra, dlambda, exposure: float,
                    noise: float | None = None) -> np.ndarray:
    """What sampling the light and camera changes in the variance, ``(P, N)``:
    :func:`surface_estimates` with ``nominal=True`` over all samples
    (sample 0 the nominal light and camera) minus the same with the nominal
    sample alone, at exposure ``exposure``. Mostly positive (the samples'
    means scatter about the nominal's), but it may be negative at a
    wavelength where the other samples' posteriors are narrower than the
    nominal's: a caller adds it to a variance and clips the sum at 0."""
    A = lighting_operator(np.asarray(sensitivities, float), np.asarray(spectra, float), dlambda)
    A = A.reshape(-1, A.shape[-2], A.shape[-1])
    y = np.atleast_2d(np.asarray(rho, float)) / float(exposure)
    if A.shape[0] == 1:
        return np.zeros((y.shape[0], A.shape[-1]))
    # surface_estimates(..., nominal=True)'s variance over all samples minus over sample 0 alone: the
    # components' spread (A_0's in both) cancels
    mean0, Wa, _, _ = _mixture_moments(prior, A[0], y, noise)
    K, P = wiener_gain(prior, A, noise)
    innov = y[None] - np.einsum("pn,scn->spc", Wa, A, optimize=True)
    dev = Wa[None] + np.einsum("spc,snc->spn", innov, K, optimize=True) - mean0[None]
    d = np.diagonal(P, axis1=1, axis2=2)
    return (d.mean(axis=0) - d[0])[None] + (dev[1:] * dev[1:]).mean(axis=0)


def surface_estimates_per_point(prior: SurfacePrior, rho, sensitivities, spectra, dlambda, exposure: float,
                                noise: float | None = None, chunk: int = 64) -> SurfaceEstimates:
    """:func:`surface_estimates` with one light per surface (a light map):
    ``spectra`` ``(P, N)`` and ``rho`` ``(P, C)``, one camera; the same
    mixture posterior as :func:`_mixture_moments`, batched over points
    (``chunk`` at a time, to bound the memory of the ``(chunk, M, N)``
    component means)."""
    R = np.asarray(sensitivities, float)
    E = np.atleast_2d(np.asarray(spectra, float))
    y_all = np.atleast_2d(np.asarray(rho, float)) / float(exposure)
    P_n = y_all.shape[0]
    N = prior.mean.size
    mean = np.zeros((P_n, N))
    var = np.zeros((P_n, N))
    typ = np.zeros(P_n)
    atoms = prior.atoms
    for s0 in range(0, P_n, chunk):
        y = y_all[s0:s0 + chunk]
        A = lighting_operator(R, E[s0:s0 + chunk], dlambda)                        # (p, C, N)
        SA = np.einsum("nm,pcm->pnc", prior.cov, A, optimize=True)                 # (p, N, C)
        G = A @ SA + _noise_var(prior, A, noise)[:, None, None] * np.eye(A.shape[1])
        Gi = np.linalg.inv(G)
        K = SA @ Gi                                                                # (p, N, C)
        Pd = np.diagonal(prior.cov)[None] - np.einsum("pnc,pnc->pn", K, SA)
        p_, C_ = A.shape[0], A.shape[1]
        AR = (atoms @ A.transpose(2, 0, 1).reshape(N, -1)).reshape(-1, p_, C_).transpose(1, 0, 2)   # (p, M, C)
        ARG = AR @ Gi                                                              # (p, M, C)
        ll = (ARG @ y[:, :, None])[..., 0] - 0.5 * np.einsum("pmc,pmc->pm", ARG, AR)   # Gi symmetric
        top = ll.max(axis=1, keepdims=True)
        W = np.exp(ll - top)
        sw = W.sum(axis=1, keepdims=True)
        typ[s0:s0 + chunk] = _typicality(np.einsum("pc,pcd,pd->p", y, Gi, y), top[:, 0] + np.log(sw[:, 0]),
                                         atoms.shape[0], C_)
        W /= sw
        # the components' c_m = a_m - K A a_m weighted by W without the (p, M, N) tensor of them:
        # sum_m W c = W a - K (W AR), sum_m W c^2 = W a^2 - 2 K.(AR'W a) + K (AR'W AR) K' (diagonal)
        WAR = W[:, :, None] * AR                                                   # (p, M, C)
        Wa = W @ atoms                                                             # (p, N)
        Wc = Wa - np.einsum("pnc,pc->pn", K, WAR.sum(axis=1))
        cross = (WAR.transpose(0, 2, 1).reshape(-1, WAR.shape[1]) @ atoms).reshape(p_, C_, N)   # sum_m W AR a
        mom = np.matmul(WAR.transpose(0, 2, 1), AR)                                # (p, C, C): sum_m W AR AR'
        Wc2 = (W @ (atoms * atoms) - 2.0 * np.einsum("pnc,pcn->pn", K, cross)
               + np.einsum("pnc,pcd,pnd->pn", K, mom, K))
        mean[s0:s0 + chunk] = Wc + np.einsum("pnc,pc->pn", K, y)
        var[s0:s0 + chunk] = Pd + np.clip(Wc2 - Wc * Wc, 0.0, None)
    std = np.sqrt(np.clip(var, 0.0, None))
    return SurfaceEstimates(mean, std, np.sqrt(np.mean(std * std, axis=1)), float(exposure), 1, typ)


# --------------------------------------------------------------------------- calibrated bands
def band_kind(camera_source: str, has_matrix: bool, light_method: str) -> str:
    """The calibration row of a camera and light: ``"<camera>/<light>"`` with
    camera ``measured`` (measured or uploaded sensitivities), ``matrix``
    (derived from a colour matrix) or ``generic``, and light ``true`` (the
    light known: method ``"true"``) or ``estimated``."""
    cam = ("matrix" if camera_source == "matrix-derived" and has_matrix else
           "generic" if camera_source == "generic" else "measured")
    return f"{cam}/{'true' if light_method == 'true' else 'estimated'}"


def calibration_factors(z, level: float = BAND_LEVEL, weights=None) -> np.ndarray:
    """Factors per wavelength that make ``mean +- BAND_Z * factor * std`` hold the truth at ``level``.

    Parameters
    ----------
    z : (P, N) array_like
        ``|estimate - truth| / std`` of surfaces kept aside (each learnt
        without the surface's reflectance set).
    level : float
    weights : (P,) array_like, optional
        Weight of each surface (e.g. one over its set's size, so that every
        reflectance set counts the same); default equal.

    Returns
    -------
    (N,) the weighted ``level`` quantile of ``z`` per wavelength over
    :data:`BAND_Z` (the empirical quantile: on new surfaces from the same
    population the band then holds the truth at ``level`` up to sampling
    error; a conformal-prediction reading, Vovk, Gammerman & Shafer 2005).

    Examples
    --------
    >>> z = np.abs(np.random.default_rng(0).standard_normal((20000, 3))) * [1, 2, 0.5]
    >>> np.round(calibration_factors(z), 1).tolist()
    [1.0, 2.0, 0.5]
    """
    z = np.asarray(z, float)
    z = np.where(np.isfinite(z), z, np.inf)
    w = np.ones(z.shape[0]) if weights is None else np.asarray(weights, float)
    order = np.argsort(z, axis=0)
    zs = np.take_along_axis(z, order, axis=0)
    cw = np.cumsum(w[order], axis=0)
    cw /= cw[-1:]
    k = np.array([np.searchsorted(cw[:, j], float(level)) for j in range(z.shape[1])])
    return zs[np.minimum(k, z.shape[0] - 1), np.arange(z.shape[1])] / BAND_Z


#: Below this typicality the band's factor stays at its value there (an exact
#: match of an atom's response must not shrink the band to nothing).
TYPICALITY_FLOOR = 0.05


def typicality_factor(typ, exponent: float) -> np.ndarray:
    """The band's factor for the responses' :func:`typicality` ``t``:
    :math:`\max(t, t_0)^\beta` (:data:`TYPICALITY_FLOOR`); 1 for
    :math:`\beta = 0` (the band of the posterior alone)."""
    t = np.asarray(typ, float)
    if exponent == 0:
        return np.ones_like(t)
    return np.maximum(t, TYPICALITY_FLOOR) ** float(exponent)


def band_scale(kind: str, wavelengths) -> np.ndarray | None:
    """The shipped calibration factors ``(N,)`` for ``kind`` (:func:`band_kind`;
    :func:`models.surface_data.band_calibration`), ``None`` when none is shipped."""
    from models.surface_data import band_calibration

    return band_calibration(np.asarray(wavelengths, float))["scale"].get(kind)


def calibrate_band(est: SurfaceEstimates, scale, exponent: float = 0.0) -> SurfaceEstimates:
    """``est`` with its band multiplied by ``scale`` ``(N,)`` per wavelength
    and, with ``exponent`` :math:`\beta \ne 0`, by
    :func:`typicality_factor` of each surface's typicality (wider for a
    response unlike the prior's surfaces; the band's shape over wavelength is
    kept), and ``expected_rmse`` recomputed from it (unchanged when ``scale``
    is ``None``)."""
    if scale is None or est.std is None:
        return est
    std = est.std * np.asarray(scale, float)[None]
    if exponent and est.typicality is not None:
        std = std * typicality_factor(est.typicality, exponent)[:, None]
    return SurfaceEstimates(est.mean, std, np.sqrt(np.mean(std * std, axis=1)), est.exposure, est.samples,
                            est.typicality)
