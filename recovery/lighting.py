"""Lighting matrices and the display matrix.

References
----------
Wandell (1985) [docs/references.md#seed-002]:

* eq. 17: :math:`(\\Lambda_E)_{kj} = \\sum_n E(\\lambda_n) S_j(\\lambda_n) R_k(\\lambda_n)`
* eq. 20-21: :math:`\\Lambda_E = \\sum_i \\epsilon_i \\Lambda_i`,
  :math:`(\\Lambda_i)_{kj} = \\sum_n E_i S_j R_k`
* eq. 32-33: :math:`\\Lambda_E \\sigma = \\Lambda_S \\epsilon`,
  :math:`(\\Lambda_S)_{ki} = \\sum_n E_i S R_k`
* eq. 2-4: :math:`(\\Gamma)_{kj} = \\sum_n G_j(\\lambda_n) R'_k(\\lambda_n)`

All sums carry the quadrature weight :math:`\\Delta\\lambda_n`, so results do
not depend on the sampling interval.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "lighting_tensor",
    "lighting_matrix",
    "surface_lighting_matrix",
    "lighting_matrix_from_spectrum",
    "display_matrix",
]


def lighting_tensor(light_basis: np.ndarray, surface_basis: np.ndarray, sensors: np.ndarray,
                    dlambda: np.ndarray) -> np.ndarray:
    """The primitive lighting matrices :math:`\\Lambda_i` stacked, ``(D(E), C, D(S))``.

    ``T[i, k, j] = sum_n E_i(l_n) S_j(l_n) R_k(l_n) dl_n`` (eq. 21). The same
    tensor read along its last axis gives the :math:`\\Lambda_{S_j}` of eq. 33:
    ``Lambda_{S_j} = T[:, :, j].T``.

    Parameters
    ----------
    light_basis : (N, D(E))
    surface_basis : (N, D(S))
    sensors : (N, C)
    dlambda : (N,)
    """
    E = np.asarray(light_basis, float)
    S = np.asarray(surface_basis, float)
    R = np.asarray(sensors, float)
    w = np.asarray(dlambda, float)
    return np.einsum("ni,nj,nk,n->ikj", E, S, R, w, optimize=True)


def lighting_matrix(light_weights: np.ndarray, tensor: np.ndarray) -> np.ndarray:
    """:math:`\\Lambda_E = \\sum_i \\epsilon_i \\Lambda_i` (eq. 20), ``(C, D(S))``."""
    return np.tensordot(np.asarray(light_weights, float), tensor, axes=(0, 0))


def surface_lighting_matrix(surface_weights: np.ndarray, tensor: np.ndarray) -> np.ndarray:
    """:math:`\\Lambda_S` for a surface with weights :math:`\\sigma`, ``(C, D(E))``,
    such that :math:`\\Lambda_E \\sigma = \\Lambda_S \\epsilon` (eq. 32-33)."""
    return np.tensordot(tensor, np.asarray(surface_weights, float), axes=(2, 0)).T


def lighting_matrix_from_spectrum(spectrum: np.ndarray, surface_basis: np.ndarray,
                                  sensors: np.ndarray, dlambda: np.ndarray) -> np.ndarray:
    """:math:`\\Lambda_E` for a light given as a spectrum (eq. 17), ``(C, D(S))``.

    Also accepts a stack of spectra ``(..., N)`` and returns ``(..., C, D(S))``.
    """
    E = np.asarray(spectrum, float)
    S = np.asarray(surface_basis, float)
    R = np.asarray(sensors, float)
    w = np.asarray(dlambda, float)
    return np.einsum("...n,nj,nk,n->...kj", E, S, R, w, optimize=True)


def display_matrix(guns: np.ndarray, observer: np.ndarray, dlambda: np.ndarray) -> np.ndarray:
    """:math:`\\Gamma`, ``(K, 3)``: observer response to unit gun intensities
    (eq. 2-4), ``Gamma[k, j] = sum_n G_j(l_n) R'_k(l_n) dl_n``."""
    G = np.asarray(guns, float)
    R = np.asarray(observer, float)
    w = np.asarray(dlambda, float)
    return np.einsum("nj,nk,n->kj", G, R, w, optimize=True)
