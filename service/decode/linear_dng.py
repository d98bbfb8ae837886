"""The estimation image of a LinearRaw (demosaiced) DNG, read tile by tile.

A DNG whose raw IFD is PhotometricInterpretation 34892 (LinearRaw: three
samples per pixel, what Adobe DNG Converter writes for demosaiced, HDR or
merged images) is not a 2x2 mosaic, and LibRaw decodes it at full size
whatever ``half_size`` says: its float or integer buffer, its four-channel
16-bit image and the postprocessed copy, then our float copy, some 35-42 MiB
per megapixel (issue 28: a 48 MP float+deflate DNG of 5.5 MB took +1.66 GB
on ``/v1/analyze``; 120 MP in 13.7 MB +4.1 GB).

:func:`linear_dng_estimation` reads the raw IFD's strips or tiles one at a
time (``tifffile``, one decoding thread) and block-averages them straight
into the estimation image, as the Bayer path bins CFA cells
(:func:`service.decode.raw._bin_bayer_area`): each sample scaled
``(v - black_c) / (white_c - black_c)`` (DNG specification 1.4, chapter 5,
"Linearization" to "White level"), an ``f x f`` block mean with ``f`` the
smallest integer bringing the image to ``estimation_pixels``, a block
saturated when any of its samples reaches 98 % of the range (or is not a
finite number). Memory: the estimation image and one decoded segment.

Only the plain layout is read here: 8/16/32-bit unsigned or 32-bit float
samples, three of them per pixel, chunky; BlackLevel with a 1x1 repeat (one
value, or one per sample) and no BlackLevelDeltaH/V; WhiteLevel one value or
one per sample; a LinearizationTable for integer samples; no ActiveArea
margin, no DefaultScale stretch; an image of the size LibRaw reports. Any
other file returns ``None`` and is decoded by LibRaw as before. The full-
resolution image (``/v1/white-balance``) is still LibRaw's.
"""

from __future__ import annotations

import io
import math

import numpy as np

__all__ = ["linear_dng_estimation", "SATURATION_FRACTION"]

#: as service.decode.raw: a sample at or above this fraction of its range is saturated
SATURATION_FRACTION = 0.98

LINEAR_RAW = 34892

#: largest tile (pixels) decoded here; DNG writers use 256x256 or 512x512 (a larger one goes to LibRaw)
MAX_TILE_PIXELS = 4096 * 4096


def _values(page, code):
    t = page.tags.get(code)
    if t is None:
        return None
    v = np.asarray(t.value, dtype=np.float64).ravel()
    if t.dtype in (5, 10) and v.size % 2 == 0:           # (S)RATIONAL pairs as tifffile gives them
        num, den = v[0::2], v[1::2]
        if np.any(den == 0):
            return np.array([np.nan])
        v = num / den
    return v


def _raw_page(tf):
    """The main-image IFD (NewSubfileType 0) among IFD0 and its SubIFDs."""
    from .tags import _iter_ifds

    for page in _iter_ifds(tf.pages):
        if int(getattr(page, "subfiletype", 0) or 0) == 0 and int(getattr(page, "photometric", 0) or 0) == LINEAR_RAW:
            return page
    return None


def _levels(page, spp: int, dtype):
    """(black, white) per sample, or None for a layout not read here."""
    rep = _values(page, 50713)
    if rep is not None and not (rep.size == 2 and rep[0] == 1 and rep[1] == 1):
        return None
    if page.tags.get(50715) is not None or page.tags.get(50716) is not None:     # BlackLevelDeltaH/V
        return None
    black = _values(page, 50714)
    black = np.zeros(spp) if black is None else black
    if black.size == 1:
        black = np.repeat(black, spp)
    white = _values(page, 50717)
    if white is None:
        white = np.array([1.0 if np.dtype(dtype).kind == "f" else float(np.iinfo(dtype).max)])
    if white.size == 1:
        white = np.repeat(white, spp)
    if black.size != spp or white.size != spp or not (np.all(np.isfinite(black)) and np.all(np.isfinite(white))):
        return None
    if not np.all(white > black):
        return None
    return black, white


def linear_dng_estimation(data: bytes, height: int, width: int, estimation_pixels: int | None):
    """``(estimation image (h, w, 3) float32, saturated (h, w) bool, f,
    as-shot neutral (3,) with green 1, black (3,), white (3,))`` of a
    LinearRaw DNG of ``height x width`` pixels (unoriented, as LibRaw
    reports them), block-averaged by ``f``; ``None`` when the file is not in
    the plain layout read here or has no AsShotNeutral (LibRaw then decodes
    it)."""
    import tifffile

    try:
        tf = tifffile.TiffFile(io.BytesIO(data))
    except Exception:  # noqa: BLE001 - LibRaw read it; it decides
        return None
    with tf:
        page = _raw_page(tf)
        if page is None:
            return None
        spp = int(page.samplesperpixel)
        dtype = np.dtype(page.dtype) if page.dtype is not None else None
        if (spp != 3 or dtype is None or int(page.planarconfig) != 1 or page.imagedepth != 1
                or (dtype.kind == "u" and dtype.itemsize > 4) or (dtype.kind == "f" and dtype.itemsize != 4)
                or dtype.kind not in "uf"):
            return None
        H, W = int(page.imagelength), int(page.imagewidth)
        if (H, W) != (int(height), int(width)):
            return None
        if page.is_tiled and int(page.tilelength) * int(page.tilewidth) > MAX_TILE_PIXELS:
            return None                 # a tile is decoded whole: its declared size must stay small
        area = _values(page, 50829)                     # ActiveArea: top, left, bottom, right
        if area is not None and not (area.size == 4 and list(area) == [0, 0, H, W]):
            return None
        scale = _values(page, 50718)                    # DefaultScale
        if scale is not None and not np.allclose(scale, 1.0):
            return None
        levels = _levels(page, spp, dtype)
        if levels is None:
            return None
        black, white = levels
        p0 = tf.pages.first if hasattr(tf.pages, "first") else tf.pages[0]
        asn = _values(p0, 50728)                        # AsShotNeutral (IFD0)
        if asn is None or asn.size != 3 or not np.all(np.isfinite(asn)) or not np.all(asn > 0):
            return None                                 # LibRaw derives the neutral otherwise (AsShotWhiteXY)
        neutral = asn / asn[1]
        lut = _values(page, 50712)
        if lut is not None:
            if dtype.kind == "f" or lut.size < 2:
                return None
            lut = lut.astype(np.float64)
        f = 1
        if estimation_pixels and H * W > estimation_pixels:
            f = int(math.ceil(math.sqrt(H * W / estimation_pixels)))
        hh, ww = H // f, W // f
        if hh < 1 or ww < 1:
            return None
        sums = np.zeros((hh, ww, 3), np.float64)
        sat = np.zeros((hh, ww), bool)
        inv = (1.0 / (white - black)).astype(np.float64)
        thr = black + SATURATION_FRACTION * (white - black)

        def add(a, r0, c0):
            """Fold rows r0.., columns c0.. of the image (``a``, raw samples) into the block sums."""
            r1, c1 = min(r0 + a.shape[0], hh * f), min(c0 + a.shape[1], ww * f)
            if r1 <= r0 or c1 <= c0:
                return
            a = a[:r1 - r0, :c1 - c0]
            v = lut[np.minimum(a, lut.size - 1)] if lut is not None else a.astype(np.float64)
            bad = ~np.isfinite(v)
            hit = (bad | (v >= thr)).any(axis=2)
            v[bad] = 0.0
            v -= black
            v *= inv
            rows, cols = np.arange(r0, r1), np.arange(c0, c1)
            sr = np.flatnonzero((rows % f == 0) | (rows == r0))        # where each block starts in ``a``
            sc = np.flatnonzero((cols % f == 0) | (cols == c0))
            br, bc = (r0 + sr) // f, (c0 + sc) // f
            sums[br[:, None], bc[None, :]] += np.add.reduceat(np.add.reduceat(v, sr, axis=0), sc, axis=1)
            h8 = np.maximum.reduceat(np.maximum.reduceat(hit.view(np.uint8), sr, axis=0), sc, axis=1)
            sat[br[:, None], bc[None, :]] |= h8.astype(bool)

        try:
            for seg, index, shape in page.segments(maxworkers=1):
                if seg is None:
                    continue
                r0, c0 = int(index[2]), int(index[3])
                a = np.asarray(seg).reshape(shape[1], shape[2], -1)[:, :, :3]
                step = max(1, (1 << 18) // max(1, a.shape[1]))       # ~256 K pixels of float64 at a time
                for k in range(0, a.shape[0], step):
                    add(a[k:k + step], r0 + k, c0)
        except Exception:  # noqa: BLE001 - a codec tifffile lacks, damaged data: LibRaw decides
            return None
    sums /= float(f * f)
    est = sums.astype(np.float32)
    return est, sat, f, neutral, black, white
