"""A PNG or JPEG of the corrected image made strip by strip from the RAW's
mosaic (issue 19): each strip of rows is demosaicked, corrected and encoded
on one thread, so the full-resolution 16-bit image (6 bytes a pixel, 144 MB
for 24 megapixels) never exists.

For the 8-bit outputs that image was made only to be read once by the
correction and dropped: its memory had to be handed out new for every
image (the slowest and least predictable step on the shared machine: 23 ms
to 0.5 s for the same demosaic) and it was streamed through the memory
three times (demosaic, correction, encoder). Here a strip's 16-bit rows are
a few chunks of :data:`service.correction.CHUNK_PIXELS` and stay in the
cache between the demosaic and the correction, and the encoder reads the
8-bit rows its own thread just wrote.

The pixels are those of the whole-image path exactly:

* OpenCV's edge-aware Bayer interpolation looks at two rows either side at
  most, so a strip demosaicked with :data:`MARGIN` rows of the mosaic on
  each side (starting on an even row: the same colour-filter phase) gives
  the rows of the whole image's demosaic bit for bit (a test checks); RCD
  (the default, :mod:`recovery.demosaic`) takes its own margin
  (:data:`recovery.demosaic.MARGIN`) and is bit for bit the same too;
* the correction works on chunks of whole rows and what it does to a chunk
  depends on that chunk's pixels only (:class:`service.correction.Correction`),
  so the strips are cut on the whole-image path's chunk bounds
  (``row_multiple`` of the encoders) and each chunk is the same.

Only for a kept, scaled 2x2 Bayer mosaic (:func:`service.decode.raw._decode_raw`
with ``keep_mosaic``) without a rotation, and for a LinearRaw DNG read from
its own samples (:func:`linear_rows`: its strips or tiles decoded as the
output's strips need them) without a rotation; anything else takes the
whole-image path (:func:`service.pipeline.render_corrected`).
"""

from __future__ import annotations

import numpy as np

#: mosaic rows demosaicked on each side of a strip (even: the filter phase)
MARGIN = 4
#: rows of a strip demosaicked at a time (then corrected while in the cache):
#: this many chunks of the correction
CHUNKS_PER_PIECE = 4


class MosaicRows:
    """Rows ``r0:r1`` of the oriented, DefaultCropped full-resolution linear
    image of a decoded RAW, demosaicked from its kept mosaic on demand
    (uint16, 65535 = saturation, as ``decoded.full_linear("uint16")``) by
    ``method``: ``fast`` (OpenCV's edge-aware interpolation, ``code`` its
    conversion) or ``rcd`` (:func:`recovery.demosaic.rcd_rows`, ``pattern``
    the 2x2 cell)."""

    def __init__(self, mosaic: np.ndarray, code: int, bounds, method: str = "fast", pattern: str | None = None):
        self.mosaic, self.code, self.method, self.pattern = mosaic, code, method, pattern
        H, W = mosaic.shape
        self.r0, self.r1, self.c0, self.c1 = bounds if bounds is not None else (0, H, 0, W)
        self.shape = (self.r1 - self.r0, self.c1 - self.c0)
        #: rows worth demosaicking at a time: RCD demosaics its context of
        #: MARGIN rows either side again for each call
        self.min_rows = RCD_MIN_ROWS if method == "rcd" else 1

    def __call__(self, r0: int, r1: int) -> np.ndarray:
        """Rows ``r0:r1`` of the image (a view of a new strip)."""
        if self.method == "rcd":
            from recovery.demosaic import rcd_rows

            return rcd_rows(self.mosaic, self.pattern, self.r0 + r0, self.r0 + r1, c0=self.c0, c1=self.c1)
        import cv2

        H = self.mosaic.shape[0]
        a0, a1 = self.r0 + r0, self.r0 + r1                 # rows of the mosaic
        s0 = max(0, a0 - MARGIN)
        s0 -= s0 % 2                                        # the same filter phase as the whole mosaic
        s1 = min(H, a1 + MARGIN)
        rgb = cv2.cvtColor(self.mosaic[s0:s1], self.code)
        return rgb[a0 - s0:a1 - s0, self.c0:self.c1]


class FieldRows:
    """Rows of a :class:`MosaicRows` multiplied by a light map's per-pixel
    gains (:class:`service.light_field.GainField`), in the full image's
    coordinates (the crop's offset added)."""

    def __init__(self, source: MosaicRows, field):
        self.source, self.field = source, field
        self.shape = source.shape
        self.min_rows = getattr(source, "min_rows", 1)

    def __call__(self, r0: int, r1: int) -> np.ndarray:
        rows = np.ascontiguousarray(self.source(r0, r1))
        return self.field.apply(rows, self.source.r0 + r0, self.source.c0)


#: rows of the image an RCD strip demosaicks at a time (at least)
RCD_MIN_ROWS = 128


def mosaic_rows(decoded, bounds_of) -> MosaicRows | None:
    """A :class:`MosaicRows` of ``decoded`` taking its kept mosaic (which
    the whole-image path can then no longer use), or ``None`` when there is
    none, the image is rotated, the filter pattern is not a 2x2 Bayer one
    or its demosaic is LibRaw's. ``bounds_of(shape)``: the crop in the full
    image (:func:`service.pipeline.crop_bounds`)."""
    import cv2

    from .decode.raw import _OPENCV_BAYER, DEMOSAIC_DEFAULT, MOSAIC_DEMOSAICS, _pattern

    method = str(getattr(decoded, "demosaic", None) or DEMOSAIC_DEFAULT).lower()
    kept = getattr(decoded, "_mosaic", None)
    if not kept or kept.get("flip") or kept.get("scaled") is None or method not in MOSAIC_DEMOSAICS:
        return None
    pattern = _pattern(kept["sites"])
    if pattern is None:
        return None
    mosaic = kept["scaled"]
    if tuple(mosaic.shape) != tuple(decoded.full_shape):
        return None
    decoded._mosaic = None
    return MosaicRows(mosaic, getattr(cv2, _OPENCV_BAYER[pattern]), bounds_of(mosaic.shape), method, pattern)


def linear_rows(decoded, bounds_of):
    """The rows of a LinearRaw DNG read without LibRaw (``decoded._linear_raw``,
    :class:`service.decode.linear_dng.LinearRawRows`: its strips or tiles
    decoded as the strips of the output need them), or ``None`` (another
    kind of image, a rotated one, or segments too tall)."""
    shape = getattr(decoded, "_linear_raw", None)
    if shape is None or decoded._source is None:
        return None
    from .decode.linear_dng import LinearRawRows

    flip = int((decoded._postprocess or {}).get("user_flip", 0) or 0)
    return LinearRawRows.of(decoded._source, *shape, flip, bounds_of)


def encode_strips(source: MosaicRows, kernel, fmt: str, threads: int | None = None) -> bytes:
    """The image of ``source`` corrected by ``kernel``
    (:class:`service.correction.Correction`, its chunk rows the whole-image
    path's; in BGR order for a JPEG if it was made so: OpenCV's encoder takes
    that without a conversion) and encoded as ``fmt`` (``png`` or ``jpeg``;
    no metadata), strip by strip on ``threads`` threads (:mod:`service.encode`)."""
    from .encode import JPEG_QUALITY, jpeg_encode_rows, png_encode_rows

    H, W = source.shape
    step = kernel.rows
    piece = step * max(CHUNKS_PER_PIECE, -(-getattr(source, "min_rows", 1) // step))
    dtype = np.uint8 if kernel.bits == 8 else np.uint16

    def rows(r0: int, r1: int) -> np.ndarray:
        out = np.empty((r1 - r0, W, 3), dtype)
        for p in range(r0, r1, piece):
            q = min(r1, p + piece)
            kernel.rows_into(source(p, q), out[p - r0:q - r0])
        return out

    if fmt == "jpeg":
        return jpeg_encode_rows(H, W, rows, JPEG_QUALITY, threads, row_multiple=step, bgr=kernel.bgr)
    if fmt == "png":
        return png_encode_rows(H, W, dtype, rows, threads, row_multiple=step)
    raise ValueError(f"encode_strips: png or jpeg, not {fmt!r}")
