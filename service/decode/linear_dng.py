"""The estimation and full-resolution images of a LinearRaw (demosaiced)
DNG, read from its own samples tile by tile (or strip by strip).

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

:func:`linear_dng_full` reads the same samples, segment by segment, into
the full-resolution image of :meth:`service.decode.DecodedImage.full_linear`
(uint16, ``65535 (v - black_c) / (white_c - black_c)`` rounded and clipped,
oriented as LibRaw orients it), written straight into its place in the
oriented image: memory is that image (6 bytes a pixel) and one decoded
segment with a few rows of float32 temporaries, where LibRaw's full decode
took about 24 MiB per megapixel and failed on (16-bit integer + deflate) or
misread (float + deflate) some of these files. :class:`LinearRawRows`
gives the rows of that image on demand, for a PNG or JPEG made strip by
strip (:mod:`service.strips`).

Only the plain layout is read here: 8/16/32-bit unsigned or 16/32-bit float
samples, three of them per pixel, chunky, uncompressed or deflate
(compression 8 or 32946, with or without a predictor) or another codec
tifffile decodes; BlackLevel with a 1x1 repeat (one
value, or one per sample) and no BlackLevelDeltaH/V; WhiteLevel one value or
one per sample; a LinearizationTable for integer samples; no ActiveArea
margin, no DefaultScale stretch; an image of the size LibRaw reports. Any
other file returns ``None`` and is decoded by LibRaw as before. A segment
that cannot be decoded in a file of this layout (a damaged deflate stream,
a truncated strip) is a 422 ``corrupt_file`` naming it, never LibRaw's
guess.
"""

from __future__ import annotations

import math
import weakref

import numpy as np

from .tiffbytes import tiff_file

__all__ = ["linear_dng_estimation", "linear_dng_full", "LinearRawRows", "SATURATION_FRACTION"]

#: as service.decode.raw: a sample at or above this fraction of its range is saturated
SATURATION_FRACTION = 0.98

LINEAR_RAW = 34892

#: compressions whose decoding failure is the file's fault (a 422), not a codec
#: this build lacks (then LibRaw decides): none, LZW, Adobe deflate, deflate
OWN_CODECS = frozenset({1, 5, 8, 32946})

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


class _Layout:
    """What both readers need of a LinearRaw DNG in the plain layout."""

    def __init__(self, page, H, W, dtype, black, white, lut, neutral):
        self.page, self.H, self.W, self.dtype = page, H, W, dtype
        self.black, self.white, self.lut, self.neutral = black, white, lut, neutral


def _layout(tf, height: int, width: int, need_neutral: bool = True) -> _Layout | None:
    """The raw IFD of ``tf`` and its levels when it is in the plain layout
    (module docstring) and of ``height x width`` pixels, else ``None``.
    Without a usable AsShotNeutral it is ``None`` when ``need_neutral`` (a
    file LibRaw opens: LibRaw decodes it), else read with ``neutral``
    ``None`` (a file LibRaw does not open, whose samples are read only here;
    one whose AsShotWhiteXY gives the neutral, :mod:`service.decode.tags`;
    the full image, which needs no neutral)."""
    page = _raw_page(tf)
    if page is None:
        return None
    spp = int(page.samplesperpixel)
    dtype = np.dtype(page.dtype) if page.dtype is not None else None
    if (spp != 3 or dtype is None or int(page.planarconfig) != 1 or page.imagedepth != 1
            or (dtype.kind == "u" and dtype.itemsize > 4) or (dtype.kind == "f" and dtype.itemsize not in (2, 4))
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
        if need_neutral:
            return None                             # LibRaw decodes it
        asn = None
    lut = _values(page, 50712)
    if lut is not None:
        if dtype.kind == "f" or lut.size < 2 or not np.all(np.isfinite(lut)):
            return None
        lut = lut.astype(np.float64)
    return _Layout(page, H, W, dtype, black, white, lut, None if asn is None else asn / asn[1])


def _segments(page):
    """``(rows array (h, w, 3) of raw samples, r0, c0)`` of each decoded strip
    or tile of ``page`` in file order; a segment that cannot be decoded
    raises :class:`_Damaged` (naming it) when its codec is one of
    :data:`OWN_CODECS`, else :class:`_Unread` (LibRaw then decides); one
    without data raises :class:`_Damaged` (the structure check,
    :mod:`service.decode.structure`, refuses such files first)."""
    n = 0
    it = page.segments(maxworkers=1)
    while True:
        try:
            seg, index, shape = next(it)
        except StopIteration:
            return
        except Exception as exc:  # noqa: BLE001 - tifffile/imagecodecs raise their own kinds
            if int(page.compression) in OWN_CODECS:
                raise _Damaged(_describe_segment(page, n, exc)) from None
            raise _Unread() from None
        if seg is None:        # no data (offset or byte count 0): never left as uninitialised pixels
            raise _Damaged(_describe_segment(page, n, "it has no data"))
        n += 1
        a = np.asarray(seg).reshape(shape[1], shape[2], -1)[:, :, :3]
        yield a, int(index[2]), int(index[3])


class _Damaged(Exception):
    """A segment of a plain-layout LinearRaw DNG could not be decoded."""


class _Unread(Exception):
    """A codec tifffile could not decode: LibRaw decides."""


def _describe_segment(page, n: int, exc) -> str:
    what = {8: "Adobe deflate", 32946: "deflate", 5: "LZW", 1: "uncompressed"}.get(int(page.compression),
                                                                                   str(int(page.compression)))
    if page.is_tiled:
        tl, tw = int(page.tilelength), int(page.tilewidth)
        across = -(-int(page.imagewidth) // tw)
        r, c = divmod(n, across)
        where = f"tile {n} (rows {r * tl}-{r * tl + tl - 1}, columns {c * tw}-{c * tw + tw - 1})"
    else:
        rps = int(page.rowsperstrip or page.imagelength)
        where = f"strip {n} (rows {n * rps}-{min(int(page.imagelength), (n + 1) * rps) - 1})"
    msg = str(exc).strip() or type(exc).__name__
    return (f"the raw image's {where} ({what} data) cannot be decoded: {msg[:200]}; "
            "the file is damaged or truncated")


def _corrupt(label: str | None, why: str):
    from ..errors import ServiceError

    return ServiceError(422, "corrupt_file", f"{label or 'the upload'}: {why}")


def linear_dng_estimation(data: bytes, height: int, width: int, estimation_pixels: int | None,
                          label: str | None = None, need_neutral: bool = True):
    """``(estimation image (h, w, 3) float32, saturated (h, w) bool, f,
    as-shot neutral (3,) with green 1 or None, black (3,), white (3,))`` of a
    LinearRaw DNG of ``height x width`` pixels (unoriented, as LibRaw
    reports them), block-averaged by ``f``; ``None`` when the file is not in
    the plain layout read here, or has no AsShotNeutral and ``need_neutral``
    (LibRaw then decodes it; a file LibRaw does not open, or whose
    AsShotWhiteXY gives the neutral, is read with ``need_neutral=False``).

    Raises
    ------
    ServiceError
        422 ``corrupt_file`` naming the strip or tile of a plain-layout
        file that cannot be decoded (``label``: the upload's name).
    """
    try:
        tf = tiff_file(data)
    except Exception:  # noqa: BLE001 - LibRaw read it; it decides
        return None
    with tf:
        lay = _layout(tf, height, width, need_neutral)
        if lay is None:
            return None
        H, W, black, white, lut, neutral = lay.H, lay.W, lay.black, lay.white, lay.lut, lay.neutral
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
            for a, r0, c0 in _segments(lay.page):
                step = max(1, (1 << 18) // max(1, a.shape[1]))       # ~256 K pixels of float64 at a time
                for k in range(0, a.shape[0], step):
                    add(a[k:k + step], r0 + k, c0)
        except _Damaged as exc:
            raise _corrupt(label, str(exc)) from None
        except _Unread:
            return None
    sums /= float(f * f)
    est = sums.astype(np.float32)
    return est, sat, f, neutral, black, white


#: flip code whose operation undoes FLIP_OPS[code] (5 and 6 are the two quarter turns)
_INVERSE_FLIP = {0: 0, 1: 1, 2: 2, 3: 3, 4: 4, 5: 6, 6: 5, 7: 7}

#: samples scaled at a time (float32 temporaries of a segment's rows)
_CHUNK_PIXELS = 1 << 17


class _Scale:
    """A layout's samples to the 16-bit scale: ``65535 (lut(v) - black_c) /
    (white_c - black_c)`` clipped to [0, 65535] and rounded (half up), a
    sample that is not a number 0; in float32, :data:`_CHUNK_PIXELS` at a
    time."""

    def __init__(self, lay: _Layout):
        self.black = lay.black.astype(np.float32)
        self.k = (65535.0 / (lay.white - lay.black)).astype(np.float32)
        self.lut = None if lay.lut is None else lay.lut.astype(np.float32)

    def into(self, dst: np.ndarray, src: np.ndarray) -> None:
        """Write ``src`` (raw samples, (h, w, 3)) scaled into ``dst`` (uint16, same shape, any strides)."""
        lut = self.lut
        step = max(1, _CHUNK_PIXELS // max(1, src.shape[1]))
        for s0 in range(0, src.shape[0], step):
            part = src[s0:s0 + step]
            v = lut[np.minimum(part, lut.size - 1)] if lut is not None else part.astype(np.float32)
            v -= self.black
            v *= self.k
            np.nan_to_num(v, copy=False, nan=0.0, posinf=65535.0, neginf=0.0)
            np.clip(v, 0.0, 65535.0, out=v)
            v += np.float32(0.5)
            dst[s0:s0 + v.shape[0]] = v          # truncation: the rounding


def linear_dng_full(data: bytes, height: int, width: int, flip: int, label: str | None = None) -> np.ndarray:
    """The full-resolution image of a LinearRaw DNG in the plain layout:
    ``(H', W', 3)`` uint16, each sample ``v`` (through the
    LinearizationTable when there is one) scaled to
    ``65535 (v - black_c) / (white_c - black_c)``, clipped to [0, 65535]
    and rounded (a sample that is not a number: 0), oriented by LibRaw's
    ``flip`` code (:data:`service.decode.image.FLIP_OPS`).

    The strips or tiles are decoded one at a time (``tifffile``) and each
    is written straight into its place in the oriented image (a view of it
    in the file's orientation): the memory is the image, one decoded
    segment and :data:`_CHUNK_PIXELS` of float32 temporaries.

    Parameters
    ----------
    data : bytes
        The DNG.
    height, width : int
        The raw image's size as LibRaw reports it (unoriented).
    flip : int
        LibRaw's ``sizes.flip`` (0 for none).
    label : str, optional
        The upload's name, for the error message.

    Returns
    -------
    numpy.ndarray
        uint16, 65535 = the white level: the scale of
        :meth:`service.decode.DecodedImage.full_linear`.

    Raises
    ------
    ServiceError
        422 ``corrupt_file`` when the file is not (any longer) in the plain
        layout or one of its segments cannot be decoded (named).

    References
    ----------
    Adobe, *Digital Negative (DNG) Specification* 1.4.0.0 (2012), chapter 5
    ("Linearization", "Black Subtraction", "Rescaling"); LibRaw's
    ``scale_colors`` does the same scaling for these files.
    """
    from .image import FLIP_OPS

    try:
        tf = tiff_file(data)
    except Exception as exc:  # noqa: BLE001
        raise _corrupt(label, f"the DNG cannot be read again ({type(exc).__name__})") from None
    with tf:
        lay = _layout(tf, height, width, need_neutral=False)      # the full image needs no neutral
        if lay is None:
            raise _corrupt(label, "the LinearRaw image is no longer in the layout read before")
        H, W = lay.H, lay.W
        flip = flip if flip in FLIP_OPS else 0
        oh, ow = (W, H) if flip & 4 else (H, W)
        out = np.empty((oh, ow, 3), np.uint16)
        view = FLIP_OPS[_INVERSE_FLIP[flip]](out)          # ``out`` in the file's orientation
        assert view.shape == (H, W, 3)
        scale = _Scale(lay)
        try:
            for a, r0, c0 in _segments(lay.page):
                h, w = min(a.shape[0], H - r0), min(a.shape[1], W - c0)
                if h > 0 and w > 0:
                    scale.into(view[r0:r0 + h, c0:c0 + w], a[:h, :w])
        except _Damaged as exc:
            raise _corrupt(label, str(exc)) from None
        except _Unread:
            raise _corrupt(label, "the LinearRaw image's codec cannot be decoded any longer") from None
    return out


#: the tallest strip or tile :class:`LinearRawRows` reads for a strip of the output (a taller
#: one, e.g. a whole image in one strip, would be decoded again for every strip)
MAX_ROWS_SEGMENT = 512


class LinearRawRows:
    """Rows ``r0:r1`` of the full-resolution image of a plain-layout
    LinearRaw DNG without rotation, within ``bounds`` (the DefaultCrop:
    ``(r0, r1, c0, c1)`` or ``None``), on demand: uint16 on the scale of
    :func:`linear_dng_full` (the same numbers), for
    :func:`service.strips.encode_strips` (a PNG or JPEG made strip by
    strip, the full image never held). Each call decodes the strips or
    tiles its rows touch (:attr:`min_rows` is their height, so a segment is
    decoded at most twice); callable from several threads at once.

    Build it with :meth:`of`, which answers ``None`` when the image is
    rotated or its segments are taller than :data:`MAX_ROWS_SEGMENT`."""

    def __init__(self, tf, lay: _Layout, data: bytes, bounds, label):
        page = lay.page
        self._tf, self._data, self._label = tf, data, label       # the TiffFile kept open for page.decode
        # closed when these rows are dropped: tifffile's pages and the file form a cycle that would keep
        # the stream, and through it the upload, until the cyclic collector ran (docs/limits.md)
        weakref.finalize(self, tf.close)
        self._decode = page.decode
        self._offsets = [int(v) for v in page.dataoffsets]
        self._counts = [int(v) for v in page.databytecounts]
        self._page = page
        self._scale = _Scale(lay)
        self.H, self.W = lay.H, lay.W
        if page.is_tiled:
            self.seg_h, self.seg_w = int(page.tilelength), int(page.tilewidth)
        else:
            self.seg_h, self.seg_w = min(int(page.rowsperstrip or lay.H), lay.H), lay.W
        self.across = -(-lay.W // self.seg_w)
        self.r0, self.r1, self.c0, self.c1 = bounds if bounds is not None else (0, lay.H, 0, lay.W)
        self.shape = (self.r1 - self.r0, self.c1 - self.c0)
        self.min_rows = self.seg_h

    @classmethod
    def of(cls, data: bytes, height: int, width: int, flip: int, bounds_of, label: str | None = None):
        """The rows of the DNG ``data`` (``height x width`` as LibRaw reports
        it, LibRaw's ``flip``), cropped to ``bounds_of((height, width))``,
        or ``None`` (rotated, segments too tall, not the plain layout)."""
        if flip:
            return None
        try:
            tf = tiff_file(data)
        except Exception:  # noqa: BLE001 - the whole-image path reports it
            return None
        lay = _layout(tf, height, width, need_neutral=False)
        tall = lay is not None and (int(lay.page.tilelength) if lay.page.is_tiled else
                                    min(int(lay.page.rowsperstrip or lay.H), lay.H)) > MAX_ROWS_SEGMENT
        if lay is None or tall or len(lay.page.dataoffsets) != len(lay.page.databytecounts):
            tf.close()
            return None
        return cls(tf, lay, data, bounds_of((lay.H, lay.W)), label)

    def _segment(self, n: int):
        off, cnt = self._offsets[n], self._counts[n]
        if cnt <= 0 or off <= 0 or off + cnt > len(self._data):
            raise _corrupt(self._label, _describe_segment(self._page, n, "it has no data"))
        try:
            seg, index, shape = self._decode(self._data[off:off + cnt], n,
                                             jpegtables=getattr(self._page, "jpegtables", None))
        except Exception as exc:  # noqa: BLE001 - tifffile/imagecodecs raise their own kinds
            raise _corrupt(self._label, _describe_segment(self._page, n, exc)) from None
        if seg is None:
            raise _corrupt(self._label, _describe_segment(self._page, n, "it has no data"))
        return np.asarray(seg).reshape(shape[1], shape[2], -1)[:, :, :3], int(index[2]), int(index[3])

    def __call__(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` of the (cropped) image, a new (r1 - r0, width, 3) uint16 array."""
        R0, R1 = self.r0 + r0, self.r0 + r1
        out = np.empty((R1 - R0, self.c1 - self.c0, 3), np.uint16)
        for band in range(R0 // self.seg_h, (R1 - 1) // self.seg_h + 1):
            for col in range(self.c0 // self.seg_w, (self.c1 - 1) // self.seg_w + 1):
                a, ar, ac = self._segment(band * self.across + col)
                a0, a1 = max(R0, ar), min(R1, ar + a.shape[0], self.H)
                b0, b1 = max(self.c0, ac), min(self.c1, ac + a.shape[1], self.W)
                if a1 > a0 and b1 > b0:
                    self._scale.into(out[a0 - R0:a1 - R0, b0 - self.c0:b1 - self.c0],
                                     a[a0 - ar:a1 - ar, b0 - ac:b1 - ac])
        return out
