"""Gaussian derivative filters, the Laplacian and binary erosion on 2-D
arrays, through OpenCV, equal to ``scipy.ndimage``'s to rounding.

The estimators (gray edge, gray pixels) need three of ``scipy.ndimage``'s
filters on the analysis image. Importing ``scipy.ndimage`` costs about
0.1-0.2 s (it pulls in ``scipy.special`` and scipy's array-API layer), a
large part of a ``wandell analyze`` command; OpenCV is loaded anyway for
resampling. The kernels here are ``scipy.ndimage``'s own (the sampled
Gaussian of radius ``int(truncate * sigma + 0.5)``, normalised, times the
Hermite polynomial of the derivative order: ``_gaussian_kernel1d``), the
borders are the same (``nearest`` = ``BORDER_REPLICATE``, ``reflect`` =
``BORDER_REFLECT``), so the results agree with scipy's to a few units of
float64 rounding (tested against scipy by ``tests/test_imfilters.py``).

References
----------
Lindeberg (1994), Scale-space theory in computer vision, ch. 2 (sampled
Gaussian derivatives). SciPy ``scipy.ndimage.gaussian_filter``,
``laplace``, ``binary_erosion`` (their documented definitions, which these
reproduce). OpenCV ``sepFilter2D``, ``Laplacian``, ``erode``.
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

__all__ = ["gaussian_kernel1d", "gaussian_filter", "laplace", "binary_erosion"]

_BORDERS = {"nearest": cv2.BORDER_REPLICATE, "reflect": cv2.BORDER_REFLECT}


@lru_cache(maxsize=64)
def gaussian_kernel1d(sigma: float, order: int = 0, truncate: float = 4.0) -> np.ndarray:
    """The 1-D correlation kernel of a Gaussian derivative of ``order``
    (scipy's ``gaussian_filter1d``: its convolution kernel, reversed).

    The sampled Gaussian ``phi(x) = exp(-x^2 / (2 sigma^2))`` on
    ``x = -r..r``, ``r = int(truncate * sigma + 0.5)``, normalised to sum 1,
    times the polynomial ``q(x)`` with ``d^n/dx^n phi = q phi``.
    """
    if sigma <= 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    radius = int(truncate * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1)
    sigma2 = float(sigma) * float(sigma)
    phi = np.exp(-0.5 / sigma2 * x ** 2)
    phi = phi / phi.sum()
    if order == 0:
        k = phi
    else:
        exps = np.arange(order + 1)
        q = np.zeros(order + 1)
        q[0] = 1.0
        d = np.diag(exps[1:], 1)                       # q -> q'
        p = np.diag(np.ones(order) / -sigma2, -1)      # q -> q * phi'/phi
        for _ in range(order):
            q = (d + p).dot(q)
        k = (x[:, None] ** exps).dot(q) * phi
    k = np.ascontiguousarray(k[::-1], dtype=np.float64)
    k.flags.writeable = False
    return k


def gaussian_filter(image: np.ndarray, sigma: float, order=(0, 0), mode: str = "reflect",
                    truncate: float = 4.0) -> np.ndarray:
    """``scipy.ndimage.gaussian_filter(image, sigma, order, mode=mode)`` of a
    2-D float array: derivative ``order[0]`` along rows (axis 0) and
    ``order[1]`` along columns (axis 1). An (h, w, c) array of up to four
    channels is filtered channel by channel in one call (the same numbers
    as one call per channel)."""
    img = np.ascontiguousarray(image, dtype=np.float64)
    if img.ndim != 2 and not (img.ndim == 3 and 1 <= img.shape[2] <= 4):
        raise ValueError(f"gaussian_filter takes a 2-D array (or a 2-D array of up to 4 channels, each "
                         f"filtered alone), got shape {img.shape}")
    ky = gaussian_kernel1d(float(sigma), int(order[0]), truncate)
    kx = gaussian_kernel1d(float(sigma), int(order[1]), truncate)
    return cv2.sepFilter2D(img, cv2.CV_64F, kx, ky, borderType=_BORDERS[mode])


def laplace(image: np.ndarray, mode: str = "reflect") -> np.ndarray:
    """``scipy.ndimage.laplace``: the sum over both axes of the second
    difference ``[1, -2, 1]``."""
    img = np.ascontiguousarray(image, dtype=np.float64)
    return cv2.Laplacian(img, cv2.CV_64F, ksize=1, borderType=_BORDERS[mode])


_CROSS = np.array([[0, 1, 0], [1, 1, 1], [0, 1, 0]], np.uint8)


def binary_erosion(mask: np.ndarray, iterations: int = 1) -> np.ndarray:
    """``scipy.ndimage.binary_erosion(mask, iterations=n, border_value=1)``
    with the default (cross, 4-connected) structuring element."""
    m = np.ascontiguousarray(mask, dtype=np.uint8)
    out = cv2.erode(m, _CROSS, iterations=int(iterations), borderType=cv2.BORDER_CONSTANT, borderValue=1)
    return out.astype(bool)
