"""Clipped highlights: white balance that never turns a clipped pixel into a
colour cast.

A sensor channel at saturation records "at least this much". White balance
multiplies the channels by different gains, so a pixel clipped in every
channel (a sun glint) comes out of the gains as the *inverse* of the light's
colour (magenta under a green-heavy camera neutral), and a pixel clipped in
one or two channels keeps a cast its true colour need not have.

The treatment here, per pixel, on camera RGB ``c`` (1.0 = saturation) and the
light's camera neutral ``n`` scaled so ``max(n) = 1``:

1. white balance ``w = c / n`` (a neutral surface becomes ``w_1 = w_2 = w_3``);
2. clip ``w`` at 1, the level at which the light's strongest channel
   saturates (dcraw/LibRaw's ``highlight_mode=clip``: a pixel saturated in
   every channel becomes exactly neutral);
3. blend towards neutral ``(L, L, L)``, ``L = max_k w_k``, with weight
   ``t = clip((max_k c_k - start) / (full - start), 0, 1)``: 0 below
   ``start`` of saturation, 1 at ``full`` (the service's saturation
   threshold), so any pixel with a clipped channel renders neutral and the
   transition is smooth.

The result is in white-balanced camera space: the caller's matrix maps
``(1, 1, 1)`` to the display white.
"""

from __future__ import annotations

import numpy as np

__all__ = ["balance_highlights", "highlight_shoulder", "blend_to_neutral", "shoulder_at", "shoulder_ratio", "HIGHLIGHT_START", "HIGHLIGHT_FULL", "SHOULDER_KNEE"]

#: Fraction of saturation where the blend to neutral starts, and where it is complete
#: (the same 0.98 that flags saturated cells in :mod:`service.rawio`).
HIGHLIGHT_START = 0.90
HIGHLIGHT_FULL = 0.98


def balance_highlights(camera_rgb: np.ndarray, neutral, start: float = HIGHLIGHT_START,
                       full: float = HIGHLIGHT_FULL, out: np.ndarray | None = None,
                       white=None) -> np.ndarray:
    """White-balanced camera RGB with clipped pixels made neutral.

    Parameters
    ----------
    camera_rgb : (..., 3) float
        Linear camera RGB, 1.0 = saturation of each channel.
    neutral : (3,)
        Camera RGB of the light (any scale; the largest channel is set to 1).
    start, full : float
        The blend to neutral runs from ``start`` to ``full`` of saturation
        in the pixel's largest channel.
    out : array like ``camera_rgb`` (float32), optional
    white : (3,), optional
        The white-balanced colour that renders as display white (default
        ``(1, 1, 1)``, exact for the DNG rendering; the spectral synthesis
        maps the light to a white a little off neutral, so its caller gives
        the vector its matrix sends to display white). Clipped pixels blend
        to ``L * white / max(white)``.

    Returns
    -------
    (..., 3) float32, white-balanced, at most 1.

    Examples
    --------
    >>> n = np.array([0.45, 1.0, 0.53])
    >>> balance_highlights(np.array([[1.0, 0.99, 1.0]]), n).tolist()   # a glint
    [[1.0, 1.0, 1.0]]
    >>> balance_highlights(np.array([[0.225, 0.5, 0.265]]), n).round(4).tolist()  # grey, unclipped
    [[0.5, 0.5, 0.5]]
    """
    n = np.asarray(neutral, np.float64)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not np.all(n > 0):
        raise ValueError(f"neutral must be three positive numbers, got {neutral}")
    n = n / n.max()
    c = np.asarray(camera_rgb, np.float32)
    w = np.multiply(c, (1.0 / n).astype(np.float32), out=out)
    np.minimum(w, np.float32(1.0), out=w)
    c2 = c.reshape(-1, 3)
    w2 = w.reshape(-1, 3) if w.flags.c_contiguous else np.ascontiguousarray(w).reshape(-1, 3)
    # the largest channel per pixel from the three channel planes (a reduction
    # over a length-3 axis is several times slower), then only the pixels the
    # blend touches (usually few) are gathered
    peak = np.maximum(np.maximum(c2[:, 0], c2[:, 1]), c2[:, 2])
    idx = np.flatnonzero(peak > np.float32(start))
    blend_to_neutral(w2, idx, peak[idx], start, full, white)
    if not np.shares_memory(w2, w):
        w[...] = w2.reshape(w.shape)
    return w


def blend_to_neutral(w2: np.ndarray, idx: np.ndarray, peak: np.ndarray, start: float = HIGHLIGHT_START,
                     full: float = HIGHLIGHT_FULL, white=None) -> None:
    """Step 3 of :func:`balance_highlights`, in place on the pixels ``idx``
    of the white-balanced, clipped ``w2`` (N, 3) float32, whose largest
    camera channel is ``peak`` (float32, one per index; pixels with
    ``peak <= start`` are left as they are). The fused renderer
    (:func:`service.pipeline.apply_matrix_inplace`) finds ``idx`` its own
    way and calls this on them only."""
    if idx.size == 0:
        return
    t = (np.asarray(peak, np.float32) - np.float32(start)) * np.float32(1.0 / (full - start))
    np.clip(t, 0.0, 1.0, out=t)
    keep = t > 0
    if not keep.all():
        idx, t = idx[keep], t[keep]
        if idx.size == 0:
            return
    wh = w2[idx]
    L = np.maximum(np.maximum(wh[:, 0], wh[:, 1]), wh[:, 2])[:, None]
    th = t[:, None]
    goal = L if white is None else L * (np.asarray(white, np.float32) / np.float32(np.max(white)))
    w2[idx] = wh + th * (goal - wh)


#: Display-linear luminance above which :func:`highlight_shoulder` compresses.
SHOULDER_KNEE = 0.75


def highlight_shoulder(rgb: np.ndarray, luminance_weights, knee: float = SHOULDER_KNEE,
                       peak: float = 4.0, white: float = 1.0) -> np.ndarray:
    """Compress display-linear highlights from ``[knee, peak]`` into
    ``[knee, white]``, in place, hue-preserving (the three channels of a
    pixel scaled by one factor).

    With ``x = (Y - knee) / (peak - knee)`` for luminance ``Y > knee``
    (``Y = luminance_weights . rgb``, all relative to ``white``):
    ``Y' = knee + (1 - knee) (1 + a) x / (1 + a x)``,
    ``a = (peak - knee) / (1 - knee) - 1``, so the curve has slope 1 at the
    knee (no kink), is concave, and reaches white exactly at ``peak`` (the
    brightest value the sensor can record after the exposure gain, e.g.
    ``2 ** BaselineExposure``): highlights keep their gradation instead of
    clipping flat, and nothing below the knee changes. Channels still above
    ``white`` afterwards (saturated colours) are clipped by the caller.

    Examples
    --------
    >>> v = np.array([[0.2, 0.2, 0.2], [4.0, 4.0, 4.0], [1.0, 1.0, 1.0]], np.float32)
    >>> highlight_shoulder(v, [0.2126, 0.7152, 0.0722], knee=0.4, peak=4.0).round(3).tolist()
    [[0.2, 0.2, 0.2], [1.0, 1.0, 1.0], [0.727, 0.727, 0.727]]
    """
    w = np.asarray(luminance_weights, np.float32).reshape(3)
    k = float(knee)
    pk = max(float(peak), 1.0 + 1e-6)
    if pk <= 1.0 + 1e-6 or k >= 1.0:
        return rgb
    Y = rgb @ w
    flat = rgb.reshape(-1, 3) if rgb.flags.c_contiguous else np.ascontiguousarray(rgb).reshape(-1, 3)
    shoulder_at(flat, Y.reshape(-1), knee, peak, white)
    if not np.shares_memory(flat, rgb):
        rgb[...] = flat.reshape(rgb.shape)
    return rgb


def shoulder_at(rgb2: np.ndarray, Y: np.ndarray, knee: float = SHOULDER_KNEE, peak: float = 4.0,
                white: float = 1.0, idx: np.ndarray | None = None) -> None:
    """:func:`highlight_shoulder` on ``rgb2`` (N, 3) float32 in place, given
    its luminance ``Y`` (N,) (``idx``: the pixels with ``Y > knee * white``
    when the caller has them already; otherwise found here)."""
    k = float(knee)
    pk = max(float(peak), 1.0 + 1e-6)
    if pk <= 1.0 + 1e-6 or k >= 1.0:
        return
    if idx is None:
        idx = np.flatnonzero(Y > k * white)
    if idx.size == 0:
        return
    rgb2[idx] *= shoulder_ratio(Y[idx], k, pk, white)[:, None]


def shoulder_ratio(Y: np.ndarray, knee: float, peak: float, white: float = 1.0) -> np.ndarray:
    """The factor :func:`highlight_shoulder` scales a pixel of luminance
    ``Y > knee * white`` by (``Y' / Y``), for ``peak > 1``, ``knee < 1``.
    The fused renderer (:func:`service.pipeline.apply_matrix_inplace`)
    gathers the luminance of the pixels above the knee (one
    ``cv2.transform``) and multiplies by these factors as it rounds to
    integers."""
    k, pk = float(knee), float(peak)
    a = (pk - k) / (1.0 - k) - 1.0
    x = (Y / white - k) / (pk - k)
    Yn = (k + (1.0 - k) * (1.0 + a) * x / (1.0 + a * x)) * white
    return Yn / Y
