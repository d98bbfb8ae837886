"""Illuminant estimators on arrays: the literal Maloney-Wandell method and
the classical peers (gray world, white patch, shades of gray, gray edge).

Each estimator returns the camera response to the light (any scale); the
Maloney-Wandell estimator also returns the light's weights in its linear
model.

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 29-35 (Maloney-Wandell).
Buchsbaum (1980) gray world; Land & McCann (1971) white patch (max-RGB);
Finlayson & Trezzi (2004) shades of gray (Minkowski p-norm);
van de Weijer, Gevers & Gijsenij (2007) gray edge (p-norm of Gaussian
derivatives). The peers are the development benchmark's baselines
(``docs/DESIGN.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import imfilters

from .errors import InsufficientSurfaceVariation
from .subspace import light_weights, subspace_normal

__all__ = [
    "gray_world",
    "white_patch",
    "shades_of_gray",
    "gray_edge",
    "bright_pixels",
    "PEERS",
    "MWResult",
    "maloney_wandell_pixels",
]


def _masked(image: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    c = image.shape[-1]
    px = image.reshape(-1, c)
    if mask is not None:
        px = px[mask.reshape(-1)]
    if px.shape[0] == 0:
        raise InsufficientSurfaceVariation("no usable pixels (all masked as dark, saturated or non-finite)")
    return px.astype(np.float64, copy=False)


def gray_world(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Mean of each channel over the usable pixels (Buchsbaum 1980)."""
    return _masked(image, mask).mean(axis=0)


def white_patch(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Maximum of each channel over the usable pixels (max-RGB)."""
    return _masked(image, mask).max(axis=0)


def _underflowed(out: np.ndarray, px: np.ndarray, p: float, scale: float = 1.0) -> np.ndarray:
    """``out``, the Minkowski p-norms ``top * mean((px / top) ** p) ** (1 / p)``
    of the channels for the common maximum ``top`` (times ``scale``), with a
    channel whose mean underflowed to 0 (a large ``p`` and a channel below the
    common maximum: p=1e6 gave 0, then infinite white-balance multipliers)
    normalised by its own maximum instead: the same norm without the
    underflow. Other channels, and every channel at usual ``p``, unchanged."""
    own = px.max(axis=0)
    for k in np.flatnonzero((out <= 0) & (own > 0)):
        out[k] = scale * own[k] * np.mean((px[:, k] / own[k]) ** p) ** (1.0 / p)
    return out


def shades_of_gray(image: np.ndarray, mask: np.ndarray | None = None, p: float = 6.0) -> np.ndarray:
    """Minkowski p-norm of each channel (Finlayson & Trezzi 2004); p=1 is
    gray world, p=inf white patch."""
    px = _masked(image, mask)
    m = px.max()
    if m <= 0:
        return px.mean(axis=0)
    if np.isinf(p):
        return px.max(axis=0)
    return _underflowed(m * np.mean((px / m) ** p, axis=0) ** (1.0 / p), px, p)


def gray_edge(image: np.ndarray, mask: np.ndarray | None = None, p: float = 6.0,
              sigma: float = 1.0, order: int = 1) -> np.ndarray:
    """Gray edge (van de Weijer, Gevers & Gijsenij 2007): the Minkowski
    p-norm of each Gaussian-smoothed channel's derivative magnitude, of the
    first order (gradient, ``sqrt(gx^2 + gy^2)``) or the second
    (``sqrt(gxx^2 + gyy^2 + 2 gxy^2)``). Edges touching masked pixels are
    left out."""
    if order not in (1, 2):
        raise ValueError(f"gray edge order must be 1 or 2, got {order}")
    img = np.asarray(image, dtype=np.float64)
    scale = np.max(img[np.isfinite(img)]) if np.any(np.isfinite(img)) else 1.0
    img = np.where(np.isfinite(img), img, 0.0) / (scale or 1.0)
    h, w, c = img.shape
    mags = np.empty_like(img)
    for k in range(c):
        if order == 1:
            gx = imfilters.gaussian_filter(img[..., k], sigma, (0, 1), "nearest")
            gy = imfilters.gaussian_filter(img[..., k], sigma, (1, 0), "nearest")
            mags[..., k] = np.hypot(gx, gy)
        else:
            gxx = imfilters.gaussian_filter(img[..., k], sigma, (0, 2), "nearest")
            gyy = imfilters.gaussian_filter(img[..., k], sigma, (2, 0), "nearest")
            gxy = imfilters.gaussian_filter(img[..., k], sigma, (1, 1), "nearest")
            mags[..., k] = np.sqrt(gxx ** 2 + gyy ** 2 + 2 * gxy ** 2)
    # the image is scaled to a maximum of 1, so the rounding of the filter sums
    # is under 1e-14 (a flat image gives OpenCV ~1e-18 where scipy's order of
    # summation gave 0): a smaller magnitude is no edge
    mags[mags < 1e-12] = 0.0
    m = None
    if mask is not None:
        m = imfilters.binary_erosion(mask, max(1, int(np.ceil(2 * sigma))))
        if not m.any():
            m = mask
    px = _masked(mags, m)
    if np.all(px == 0):
        raise InsufficientSurfaceVariation("gray edge: the image has no edges")
    top = px.max()
    if np.isinf(p):
        return scale * px.max(axis=0)
    return _underflowed(scale * top * np.mean((px / top) ** p, axis=0) ** (1.0 / p), px, p, scale)


def bright_pixels(image: np.ndarray, mask: np.ndarray | None = None, fraction: float = 0.02) -> np.ndarray:
    """Mean of the brightest ``fraction`` of the usable pixels, by
    ``r + g + b`` (Cheng, Prasad & Brown 2014, bright pixels)."""
    px = _masked(image, mask)
    k = max(1, int(fraction * px.shape[0]))
    return px[np.argpartition(px.sum(axis=1), -k)[-k:]].mean(axis=0)


#: Name -> function(image, mask) -> camera rgb.
PEERS = {
    "gray-world": gray_world,
    "white-patch": white_patch,
    "shades-of-gray": shades_of_gray,
    "gray-edge": gray_edge,
}


@dataclass
class MWResult:
    """Outcome of the literal method on one set of pixels."""

    weights: np.ndarray
    fit_ratio: float
    variation_ratio: float
    null_ratio: float
    data_singular_values: np.ndarray
    pi_singular_values: np.ndarray
    n_pixels: int
    extra: dict = field(default_factory=dict)


def maloney_wandell_pixels(pixels: np.ndarray, tensor: np.ndarray, light_basis: np.ndarray,
                           surface_dim: int, min_variation: float = 0.0) -> MWResult:
    """The literal method on a region's sensor vectors (eq. 30 then eq. 35).

    Parameters
    ----------
    pixels : (P, C) sensor vectors, rows of Delta
    tensor : (D(E), C, D(S)) lighting tensor (eq. 21)
    light_basis : (N, D(E))
    surface_dim : D(S)
    min_variation : minimum s_D(S)/s_1 for the region to be used

    Raises
    ------
    InsufficientSurfaceVariation
    """
    fit = subspace_normal(pixels, surface_dim, min_variation)
    sol = light_weights(fit.normals, tensor, light_basis)
    return MWResult(sol.weights, fit.fit_ratio, fit.variation_ratio, sol.null_ratio,
                    fit.singular_values, sol.singular_values, fit.n_pixels)
