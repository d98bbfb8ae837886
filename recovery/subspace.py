"""The Maloney-Wandell subspace method: normal, light weights, surfaces.

References
----------
Wandell (1985) [docs/references.md#seed-002], section "The recovery method":

* eq. 29: under one light the sensor vectors lie in a D(S)-dimensional
  subspace of the C-dimensional sensor space when D(S) < C;
* eq. 30: :math:`\\Delta\\pi = 0`, the normal :math:`\\pi` is the right singular
  vector of the smallest singular value of the data matrix :math:`\\Delta`;
* eq. 31-35: :math:`\\pi^t \\Lambda_{S_j} \\epsilon = 0` for each surface basis
  function, stacked as :math:`\\Pi\\epsilon = 0`, :math:`D(E) \\le D(S) + 1`;
* eq. 36: :math:`\\sigma^x = \\Lambda_E^{+} \\rho^x`.

With C > D(S) + 1 sensors (e.g. a 6-channel camera) the orthogonal
complement of the data has C - D(S) dimensions; every normal in it gives
D(S) rows of :math:`\\Pi`, the direct generalisation of eq. 34.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .errors import InsufficientSurfaceVariation, ModelDimensionError

__all__ = [
    "check_dimensions",
    "tall_svd",
    "SubspaceFit",
    "subspace_normal",
    "LightSolution",
    "light_weights",
    "surface_weights",
]


def check_dimensions(channels: int, surface_dim: int, light_dim: int) -> None:
    """Refuse model sizes the method cannot support.

    Raises
    ------
    ModelDimensionError
        If ``D(S) >= C`` (Wandell 1985, 'A condition on the number of color
        sensors': the surface dimension must be strictly less than the number
        of sensor classes) or ``D(E) > D(S) + 1`` (eq. 35: Pi has D(S) rows
        per normal and its null space must be one-dimensional).
    """
    if surface_dim < 1 or light_dim < 1:
        raise ModelDimensionError(f"D(S) and D(E) must be >= 1, got D(S)={surface_dim}, D(E)={light_dim}")
    if surface_dim >= channels:
        raise ModelDimensionError(
            f"rule D(S) < C violated: D(S)={surface_dim} with C={channels} sensor classes "
            "(Wandell 1985: analysis needs a surface dimension strictly less than the number "
            "of sensors)")
    if light_dim > surface_dim + 1:
        raise ModelDimensionError(
            f"rule D(E) <= D(S) + 1 violated: D(E)={light_dim}, D(S)={surface_dim} "
            "(Wandell 1985, eq. 35)")


def tall_svd(data: np.ndarray, block: int = 65536) -> tuple[np.ndarray, np.ndarray]:
    """Singular values and right singular vectors of a tall ``(P, C)`` matrix.

    Small inputs go straight to LAPACK's SVD. Tall inputs are reduced by a
    blockwise QR (TSQR): the R factor of the stacked blocks has the same
    singular values and right singular vectors, without ever forming the
    Gram matrix (which would square the condition number).

    Returns
    -------
    s : (C,) singular values, descending
    vt : (C, C) right singular vectors as rows
    """
    x = np.asarray(data, dtype=np.float64)
    if x.shape[0] > block:
        rs = [np.linalg.qr(x[i:i + block], mode="r") for i in range(0, x.shape[0], block)]
        x = np.linalg.qr(np.vstack(rs), mode="r")
    # full U only when P < C (then vt must still be C x C); never a P x P U
    _, s, vt = np.linalg.svd(x, full_matrices=x.shape[0] < x.shape[1])
    if s.size < vt.shape[0]:
        s = np.concatenate([s, np.zeros(vt.shape[0] - s.size)])
    return s, vt


@dataclass
class SubspaceFit:
    """The data subspace of one region (eq. 29-30).

    Attributes
    ----------
    normals : (C, C - D(S)) orthonormal columns spanning the complement
    singular_values : (C,) of the data matrix, scaled by the largest
    fit_ratio : float
        :math:`s_{D(S)+1} / s_{D(S)}`, the smallest kept-out singular value
        over the last kept one. Near 0: the data sit in a D(S)-subspace.
        Near 1: they fill the sensor space (the paper's first failure mode).
    variation_ratio : float
        :math:`s_{D(S)} / s_1`: how well the region's surfaces span D(S)
        dimensions (enough surface variation).
    n_pixels : int
    """

    normals: np.ndarray
    singular_values: np.ndarray
    fit_ratio: float
    variation_ratio: float
    n_pixels: int


def subspace_normal(data: np.ndarray, surface_dim: int, min_variation: float = 0.0) -> SubspaceFit:
    """Normals to the sensor data by SVD (eq. 30).

    Parameters
    ----------
    data : (P, C)
        Sensor vectors of a region as rows (the matrix Delta).
    surface_dim : int
        D(S).
    min_variation : float
        Minimum :math:`s_{D(S)}/s_1`; below it the region has fewer than
        D(S) independent surfaces and :class:`InsufficientSurfaceVariation`
        is raised.
    """
    x = np.asarray(data, dtype=np.float64)
    p, c = x.shape
    if p < surface_dim:
        raise InsufficientSurfaceVariation(
            f"{p} pixels cannot span D(S)={surface_dim} dimensions")
    scale = np.max(np.abs(x))
    if not np.isfinite(scale) or scale == 0:
        raise InsufficientSurfaceVariation("no signal: all sensor vectors are zero")
    s, vt = tall_svd(x / scale)
    s = s / s[0]
    variation = float(s[surface_dim - 1])
    fit = float(s[surface_dim] / s[surface_dim - 1]) if s[surface_dim - 1] > 0 else float("inf")
    if not variation > max(min_variation, 64 * np.finfo(float).eps):
        raise InsufficientSurfaceVariation(
            f"surface variation too small: s_{surface_dim}/s_1 = {variation:.3g} "
            f"(need > {max(min_variation, 64 * np.finfo(float).eps):.3g}); the region holds fewer "
            f"than D(S)={surface_dim} independent surfaces")
    return SubspaceFit(vt[surface_dim:].T.copy(), s, fit, variation, p)


@dataclass
class LightSolution:
    """Solution of :math:`\\Pi\\epsilon = 0` (eq. 35).

    Attributes
    ----------
    weights : (D(E),) light weights, sign fixed so the light is positive on
        average, scaled so the spectrum has unit mean power
    Pi : the stacked equations
    singular_values : of Pi, scaled by the largest
    null_ratio : :math:`s_{min}/s_{next}` of Pi; near 0 means a clean
        one-dimensional null space, near 1 an ambiguous light
    """

    weights: np.ndarray
    Pi: np.ndarray
    singular_values: np.ndarray
    null_ratio: float


def light_weights(normals: np.ndarray, tensor: np.ndarray, light_basis: np.ndarray) -> LightSolution:
    """Light weights from the subspace normals (eq. 31-35).

    Rows of :math:`\\Pi` are :math:`\\pi_m^t \\Lambda_{S_j}` for every normal
    :math:`\\pi_m` and surface basis function j; :math:`\\epsilon` is the right
    singular vector of the smallest singular value.

    Parameters
    ----------
    normals : (C, M)
    tensor : (D(E), C, D(S)) from :func:`recovery.lighting.lighting_tensor`
    light_basis : (N, D(E)), only to fix sign and scale
    """
    # Pi[(m, j), i] = sum_k normals[k, m] T[i, k, j]
    Pi = np.einsum("km,ikj->mji", normals, tensor).reshape(-1, tensor.shape[0])
    d_e = tensor.shape[0]
    scale = np.max(np.abs(Pi)) or 1.0
    _, s, vt = np.linalg.svd(Pi / scale, full_matrices=True)
    s_full = np.zeros(d_e)
    s_full[: s.size] = s
    eps = vt[-1]
    spectrum = np.asarray(light_basis, float) @ eps
    mean = spectrum.mean()
    if mean < 0:
        eps, mean = -eps, -mean
    if mean > 0:
        eps = eps / mean
    s_sorted = np.sort(s_full)
    if d_e == 1:
        null_ratio = 0.0
    else:
        null_ratio = float(s_sorted[0] / s_sorted[1]) if s_sorted[1] > 0 else 1.0
    return LightSolution(eps, Pi, s_full / (s_full[0] or 1.0), null_ratio)


def surface_weights(lighting: np.ndarray, data: np.ndarray) -> tuple[np.ndarray, float]:
    """Surface weights by pseudo-inverse (eq. 36).

    Parameters
    ----------
    lighting : (C, D(S)) :math:`\\Lambda_E`
    data : (..., C) sensor vectors

    Returns
    -------
    sigma : (..., D(S))
    condition : float, 2-norm condition number of :math:`\\Lambda_E`
        (``inf`` when it is not one to one: the paper's second failure mode)
    """
    L = np.asarray(lighting, float)
    s = np.linalg.svd(L, compute_uv=False)
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    pinv = np.linalg.pinv(L)
    return np.asarray(data, float) @ pinv.T, cond
