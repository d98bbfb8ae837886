"""Analysis resolution: block averaging of linear images.

Averaging ``f x f`` blocks is exact for the linear models: a mixture of
surfaces under one light is a surface in the same D(S)-dimensional model,
so averaged pixels stay in the subspace of Wandell (1985, eq. 29). It
lowers noise and cost; it removes the edges the gray-edge family needs.
"""

from __future__ import annotations

import numpy as np

__all__ = ["area_resize", "block_average", "block_factor"]


def block_factor(shape: tuple[int, int], max_pixels: int | None) -> int:
    """Smallest integer ``f`` with ``(H // f) * (W // f) <= max_pixels``."""
    h, w = shape[:2]
    if not max_pixels or h * w <= max_pixels:
        return 1
    f = int(np.ceil(np.sqrt(h * w / max_pixels)))
    while (h // f) * (w // f) > max_pixels:
        f += 1
    return max(1, min(f, h, w))


def area_resize(src: np.ndarray, width: int, height: int) -> np.ndarray:
    """OpenCV's area resampling of an ``(H, W, C)`` image to ``(height, width, C)``, any ``C`` (OpenCV
    takes at most 4 channels at once: more are resized one by one).

    >>> area_resize(np.ones((4, 6, 6), np.float32), 3, 2).shape
    (2, 3, 6)
    """
    import cv2

    src = np.ascontiguousarray(src)
    c = src.shape[2]
    if c <= 4:
        return cv2.resize(src, (width, height), interpolation=cv2.INTER_AREA).reshape(height, width, c)
    return np.stack([cv2.resize(np.ascontiguousarray(src[..., k]), (width, height), interpolation=cv2.INTER_AREA)
                     for k in range(c)], axis=2)


def block_average(img: np.ndarray, mask: np.ndarray | None, max_pixels: int | None):
    """Average ``f x f`` blocks so the image has at most ``max_pixels``.

    OpenCV's area resampling is the exact block mean for an integer factor.
    Non-finite values are zeroed and their blocks masked. A block is masked
    out if any of its pixels is.

    Returns
    -------
    image : (H // f, W // f, C) float32, float64 for float64 input (the
        input itself when ``f == 1``)
    mask : (H // f, W // f) bool or None
    f : int

    Examples
    --------
    >>> x = np.arange(16, dtype=np.float32).reshape(4, 4, 1).repeat(3, 2)
    >>> y, m, f = block_average(x, None, 4)
    >>> f, y[..., 0].tolist()
    (2, [[2.5, 4.5], [10.5, 12.5]])
    """
    import cv2

    f = block_factor(img.shape, max_pixels)
    if f == 1:
        return img, mask, 1
    h, w = img.shape[:2]
    hh, ww = h // f, w // f
    arr = np.asarray(img[: hh * f, : ww * f])
    dtype = np.float64 if arr.dtype == np.float64 else np.float32  # no float32 overflow of float64 data
    src = arr.astype(dtype, copy=False)
    if not np.isfinite(src).all():  # the fast whole-array test first
        finite = np.isfinite(src).all(axis=2)
        src = np.where(finite[..., None], src, 0.0).astype(dtype)
        mask = finite if mask is None else (np.asarray(mask)[: hh * f, : ww * f] & finite)
    out = area_resize(src, ww, hh)
    m = None
    if mask is not None:
        mk = np.ascontiguousarray(np.asarray(mask)[: hh * f, : ww * f], dtype=np.float32)
        m = cv2.resize(mk, (ww, hh), interpolation=cv2.INTER_AREA) > 1 - 1e-6
    return out, m, f
