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
    "PRIOR_SHRINKAGE", "PRIOR_LENGTH_NM", "PRIOR_NOISE", "PRIOR_INFLATION", "CAMERA_SHRINKAGE",
    "MATRIX_TOLERANCE", "SurfacePrior", "learn_prior", "default_prior", "lighting_operator", "wiener_gain",
    "wiener_estimate", "pinv_estimate", "exposure_scale", "light_samples", "camera_prior",
    "matrix_operator", "camera_posterior", "generic_camera_samples", "surface_estimates", "surface_estimates_per_point", "SurfaceEstimates",
]

#: Weight of the smooth covariance in the shrunk prior covariance
#: ``(1 - a) S + a v K``; chosen by leave-one-set-out cross-validation over
#: the five shipped reflectance sets (``python -m benchmarks.surfaces --cv``).
PRIOR_SHRINKAGE = 0.05
#: Correlation length (nm) of the smooth covariance ``K``.
PRIOR_LENGTH_NM = 40.0
#: Relative noise :math:`\sigma` of the observation (same cross-validation).
PRIOR_NOISE = 0.01
#: Factor on the prior covariance that makes the bands hold the truth at
#: their stated rate on reflectance sets left out (same cross-validation).
PRIOR_INFLATION = 1.0
#: Shrinkage of the 47 cameras' covariance toward a smooth one.
CAMERA_SHRINKAGE = 0.05
#: Relative tolerance of the colour-matrix constraint: how far a real
#: camera's published matrix is from the least-squares matrix of its
#: measured sensitivities (measured in ``benchmarks.surfaces``).
MATRIX_TOLERANCE = 0.18


# --------------------------------------------------------------------------- the prior
@dataclass(frozen=True)
class SurfacePrior:
    """A Gaussian over reflectances on a wavelength grid.

    Attributes
    ----------
    wavelengths : (N,) nm
    mean : (N,)
    cov : (N, N) symmetric positive definite
    name : str, what it was learnt from
    noise : float, relative observation noise :math:`\\sigma`
    """

    wavelengths: np.ndarray
    mean: np.ndarray
    cov: np.ndarray
    name: str = "custom"
    noise: float = PRIOR_NOISE


def smooth_kernel(wavelengths, length_nm: float) -> np.ndarray:
    """Squared-exponential correlation ``exp(-(l_i - l_j)^2 / (2 length^2))``, ``(N, N)``."""
    wl = np.asarray(wavelengths, float)
    return np.exp(-0.5 * ((wl[:, None] - wl[None, :]) / float(length_nm)) ** 2)


def learn_prior(reflectances, wavelengths, *, shrinkage: float = PRIOR_SHRINKAGE,
                length_nm: float = PRIOR_LENGTH_NM, inflation: float = PRIOR_INFLATION,
                noise: float = PRIOR_NOISE, name: str = "custom") -> SurfacePrior:
    """Mean and shrunk covariance of measured reflectances.

    :math:`\\Sigma = \\gamma\\,[(1 - a) S + a\\,\\bar v K_\\ell]` with ``S``
    the sample covariance, :math:`\\bar v = \\mathrm{tr}\\,S / N` and
    :math:`K_\\ell` the squared-exponential correlation of length ``length_nm``
    (a shrinkage target in the sense of Ledoit & Wolf 2004 that keeps the
    covariance full rank and smooth).

    Parameters
    ----------
    reflectances : (M, N) array_like
    wavelengths : (N,) array_like
    shrinkage, length_nm, inflation, noise : float
        ``a``, :math:`\\ell`, :math:`\\gamma`, :math:`\\sigma`.
    name : str

    Returns
    -------
    SurfacePrior

    Examples
    --------
    >>> R = np.random.default_rng(0).uniform(0, 1, (50, 31))
    >>> p = learn_prior(R, np.linspace(400, 700, 31))
    >>> bool(np.all(np.linalg.eigvalsh(p.cov) > 0))
    True
    """
    R = np.asarray(reflectances, float)
    wl = np.asarray(wavelengths, float)
    if R.ndim != 2 or R.shape[1] != wl.size or R.shape[0] < 2:
        raise ValueError(f"reflectances must be (M >= 2, N={wl.size}), got {R.shape}")
    mu = R.mean(axis=0)
    S = np.cov(R, rowvar=False)
    v = float(np.trace(S)) / wl.size
    cov = float(inflation) * ((1.0 - shrinkage) * S + shrinkage * v * smooth_kernel(wl, length_nm))
    return SurfacePrior(wl, mu, 0.5 * (cov + cov.T), name, float(noise))


@functools.lru_cache(maxsize=16)
def _default_prior(wl: tuple, exclude: tuple) -> SurfacePrior:
    from models.surface_data import SURFACE_SETS, surface_sets

    sets = [s for s in SURFACE_SETS if s not in exclude]
    R, _ = surface_sets(np.array(wl), sets)
    return learn_prior(R, np.array(wl), name="Gaussian prior of " + " + ".join(sets) + f" ({len(R)} surfaces)")


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
    (exposure 1): :math:`\\hat r = \\mu + K(\\rho - A\\mu)`.

    Examples
    --------
    >>> wl = np.linspace(400, 700, 31)
    >>> p = learn_prior(np.random.default_rng(1).uniform(0, 1, (40, 31)), wl)
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
    G = A @ prior.cov @ A.T + _noise_var(prior, A, noise) * np.eye(A.shape[0])
    Gi = np.linalg.inv(G)
    a = float(np.einsum("pi,ij,pj->", rho, Gi, rho))
    b = float(np.sum(rho @ Gi @ (A @ prior.mean)))
    n = rho.size
    if not (a > 0 and np.isfinite(a)):
        return 1.0
    u = (b + np.sqrt(b * b + 4.0 * a * n)) / (2.0 * a)
    return c * float(1.0 / u) if u > 0 and np.isfinite(u) else c


# --------------------------------------------------------------------------- the light's uncertainty
def light_samples(spectrum, sensitivities, dlambda, region90_deg: float, n: int, seed: int = 0) -> np.ndarray:
    """Lights whose camera response falls in the estimate's 90 % region, ``(n, N)``.

    The region is read as an isotropic Gaussian on the sphere of camera
    responses around the estimate with angular radius ``region90_deg`` at
    90 % (for a 2-D Gaussian :math:`r_{90} = \\sigma\\sqrt{-2\\ln 0.1}`). For
    each drawn response :math:`\\rho'` the estimated spectrum is modulated by
    a smooth factor, :math:`E' = E\\,(b_0 + b_1 t + b_2 t^2)` with :math:`t`
    the wavelength mapped to [-1, 1], solved so the camera response is
    :math:`\\rho'` (least squares for C > 3), clipped at 0 and scaled to the
    estimate's total response.

    Parameters
    ----------
    spectrum : (N,)
    sensitivities : (N, C)
    dlambda : (N,)
    region90_deg : float
    n : int
    seed : int

    Returns
    -------
    (n, N) spectra; ``n`` copies of ``spectrum`` when the radius is 0.
    """
    E = np.asarray(spectrum, float)
    R = np.asarray(sensitivities, float)
    w = np.asarray(dlambda, float)
    if not (region90_deg and region90_deg > 0 and np.isfinite(region90_deg)) or n < 1:
        return np.broadcast_to(E, (max(n, 1), E.size)).copy()
    rho0 = R.T @ (E * w)
    d0 = rho0 / np.linalg.norm(rho0)
    sigma = np.deg2rad(float(region90_deg)) / np.sqrt(-2.0 * np.log(0.1))
    rng = np.random.default_rng(seed)
    z = rng.standard_normal((n, d0.size))
    z -= np.outer(z @ d0, d0)                                     # tangent plane
    dirs = d0 + sigma * z
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    targets = dirs * np.linalg.norm(rho0)
    wl = np.arange(E.size, dtype=float)
    t = 2.0 * wl / max(E.size - 1, 1) - 1.0
    B = np.stack([np.ones_like(t), t, t * t], 1)                  # (N, 3)
    M = R.T @ (B * (E * w)[:, None])                              # (C, 3)
    coef = np.linalg.lstsq(M, targets.T, rcond=None)[0].T          # (n, 3)
    out = np.clip(E[None] * (coef @ B.T), 0.0, None)
    tot = (out @ (R * w[:, None])).sum(axis=1)
    ok = tot > 0
    out[ok] *= (rho0.sum() / tot[ok])[:, None]
    out[~ok] = E
    return out


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
                     tolerance: float = MATRIX_TOLERANCE) -> tuple[np.ndarray, np.ndarray]:
    """Sensitivities consistent with an XYZ -> camera colour matrix.

    The 47 measured cameras give a Gaussian over sensitivities
    (:func:`camera_prior`); the matrix constrains it linearly,
    :math:`H x = m` with :math:`H = \\mathrm{blockdiag}(Q^T, Q^T, Q^T)`
    (:func:`matrix_operator`), up to a tolerance :math:`\\tau` relative to the
    matrix's size (a published matrix is not exactly the least-squares one).
    Gaussian conditioning: :math:`\\hat x = \\mu + C H^T(HCH^T + \\tau^2
    I)^{-1}(m - H\\mu)`, :math:`C' = C - C H^T(HCH^T + \\tau^2 I)^{-1}HC`.

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
    CH = C @ H.T
    G = H @ CH + tau2 * np.eye(9)
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
    """

    mean: np.ndarray
    std: np.ndarray
    expected_rmse: np.ndarray
    exposure: float
    samples: int


def surface_estimates(prior: SurfacePrior, rho, sensitivities, spectra, dlambda, *, exposure: float | None = None,
                      scene_rho=None, noise: float | None = None) -> SurfaceEstimates:
    """Posterior mean and band of surfaces over sampled lights and cameras.

    With samples :math:`s = 1..S` of (light, camera), each a Gaussian
    posterior :math:`N(m_s, P_s)`, the estimate is the mixture's mean
    :math:`\\bar m = \\frac1S\\sum_s m_s` and its variance per wavelength
    :math:`\\frac1S\\sum_s (\\mathrm{diag}P_s + m_s^2) - \\bar m^2` (law of
    total variance).

    Parameters
    ----------
    prior : SurfacePrior
    rho : (P, C) camera responses of the surfaces
    sensitivities : (N, C) or (S, N, C)
        The camera, or samples of it; sample 0 (or the single one) is used
        for the exposure.
    spectra : (N,) or (S, N)
        The light, or samples of it (broadcast against the cameras).
    dlambda : (N,)
    exposure : float, optional
        :math:`k`; default :func:`exposure_scale` of ``scene_rho`` (default ``rho``).
    scene_rho : (Q, C), optional
        Responses of the whole scene for the exposure.
    noise : float, optional

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
    rho = np.atleast_2d(np.asarray(rho, float))
    if exposure is None:
        exposure = exposure_scale(prior, A[0], rho if scene_rho is None else scene_rho, noise)
    y = rho / float(exposure)
    K, P = wiener_gain(prior, A, noise)                                   # (S, N, C), (S, N, N)
    off = prior.mean - np.einsum("snc,sc->sn", K, A @ prior.mean)          # (S, N)
    S = A.shape[0]
    if S == 1:
        mean = off[0] + y @ K[0].T
        var = np.broadcast_to(np.diagonal(P[0]), mean.shape)
    else:
        ms = off[:, None, :] + np.einsum("snc,pc->spn", K, y, optimize=True)      # (S, P, N)
        mean = ms.mean(axis=0)
        var = np.diagonal(P, axis1=1, axis2=2).mean(axis=0) + (ms * ms).mean(axis=0) - mean * mean
    std = np.sqrt(np.clip(var, 0.0, None))
    return SurfaceEstimates(mean, std, np.sqrt(np.mean(std * std, axis=1)), float(exposure), S)


def surface_estimates_per_point(prior: SurfacePrior, rho, sensitivities, spectra, dlambda, exposure: float,
                                noise: float | None = None) -> SurfaceEstimates:
    """:func:`surface_estimates` with one light per surface (a light map):
    ``spectra`` ``(P, N)`` and ``rho`` ``(P, C)``; only the diagonal of each
    posterior covariance is formed (``diag P = diag Sigma - sum_c K_nc (Sigma A^T)_nc``)."""
    A = lighting_operator(np.asarray(sensitivities, float), np.asarray(spectra, float), dlambda)   # (P, C, N)
    rho = np.atleast_2d(np.asarray(rho, float))
    SA = np.einsum("nm,pcm->pnc", prior.cov, A, optimize=True)
    G = A @ SA + _noise_var(prior, A, noise)[:, None, None] * np.eye(A.shape[1])
    K = np.swapaxes(np.linalg.solve(G, np.swapaxes(SA, 1, 2)), 1, 2)                # (P, N, C)
    innov = rho / float(exposure) - A @ prior.mean
    mean = prior.mean + np.einsum("pnc,pc->pn", K, innov)
    var = np.diagonal(prior.cov)[None] - np.einsum("pnc,pnc->pn", K, SA)
    std = np.sqrt(np.clip(var, 0.0, None))
    return SurfaceEstimates(mean, std, np.sqrt(np.mean(std * std, axis=1)), float(exposure), 1)
