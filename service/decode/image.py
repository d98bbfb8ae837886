"""The decoded image (:class:`DecodedImage`): the estimation image, its mask, the metadata that
says which camera took it, and the full-resolution image on demand; the orientation table
(:data:`FLIP_OPS`) and the saturation rule. The scale of both images is in :mod:`service.decode`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


#: A CFA sample at or above this fraction of ``white - black`` (above its
#: channel's black) marks its 2x2 cell as saturated.
SATURATION_FRACTION = 0.98

#: File extensions that promise a RAW or TIFF; an unreadable file so named is
#: reported as corrupt (422) rather than as an unknown format (415).
RAW_EXTENSIONS = frozenset({
    ".dng", ".nef", ".nrw", ".cr2", ".cr3", ".crw", ".arw", ".srf", ".sr2", ".raf", ".orf",
    ".rw2", ".rwl", ".pef", ".srw", ".x3f", ".3fr", ".fff", ".iiq", ".mos", ".mef", ".mrw",
    ".erf", ".kdc", ".dcr", ".raw", ".gpr", ".tif", ".tiff",
})

#: An as-shot neutral is used when each of its channels is within this factor
#: of green (either way): LibRaw drops a DNG neutral under 0.001 (a multiplier
#: over 1000); real cameras' whites stay within a factor of about 5. Past it
#: the "white balance" would multiply a channel by thousands (probe round 8b).
MAX_NEUTRAL_RATIO = 1000.0


def as_shot_problem(neutral, tag: str = "AsShotNeutral") -> str | None:
    """Why ``neutral`` (camera RGB of the as-shot white, as the file records
    it) is not a usable white, or ``None`` when it is.

    >>> as_shot_problem([0.5, 1.0, 0.6]) is None
    True
    >>> as_shot_problem([1e-6, 1.0, 1e6])
    'the file records an as-shot white (AsShotNeutral 1e-06, 1, 1e+06) that is not a usable white: its channels must be positive and within a factor of 1000 of green'
    """
    v = np.asarray(neutral, dtype=np.float64).ravel()
    ok = v.size == 3 and bool(np.all(np.isfinite(v))) and bool(np.all(v > 0))
    if ok:
        r = v / v[1]
        ok = bool(np.all(r <= MAX_NEUTRAL_RATIO) and np.all(r >= 1.0 / MAX_NEUTRAL_RATIO))
    if ok:
        return None
    shown = ", ".join(f"{x:.6g}" for x in v)
    return (f"the file records an as-shot white ({tag} {shown}) that is not a usable white: its channels "
            f"must be positive and within a factor of {MAX_NEUTRAL_RATIO:.0f} of green")


#: Orientation LibRaw applies for each ``sizes.flip`` code (EXIF Orientation
#: 1..8 -> flip 0, 1, 3, 2, 4, 6, 7, 5), as numpy operations on (H, W, ...)
#: arrays; measured against LibRaw's own output in ``tests/test_rawio.py``.
FLIP_OPS = {
    0: lambda a: a,
    1: lambda a: a[:, ::-1],
    2: lambda a: a[::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: np.swapaxes(a, 0, 1),
    5: lambda a: np.rot90(a, 1),
    6: lambda a: np.rot90(a, 3),
    7: lambda a: np.swapaxes(a[::-1, ::-1], 0, 1),
}

# ---------------------------------------------------------------------------
# The decoded image
# ---------------------------------------------------------------------------

@dataclass
class DecodedImage:
    """An upload decoded to linear camera RGB, with its camera metadata.

    Attributes
    ----------
    kind : {"raw", "tiff", "png"}
    estimation : (h, w, 3) float32
        Linear camera RGB, black subtracted, 1.0 = saturation. RAW: half size,
        each 2x2 CFA cell binned (red, mean of the greens, blue), no
        demosaic; may dip slightly below 0 in the dark (noise around black is
        kept, not clipped). TIFF/PNG: the image itself, full size.
    saturated : (h, w) bool
        RAW: a CFA sample of the cell at or above
        :data:`SATURATION_FRACTION` of its channel's range; 16-bit TIFF/PNG:
        a channel at 65535; float TIFF: a channel at or above 1.0.
    full_shape : (H, W)
        Shape of :meth:`full_linear` (the file's orientation applied, as it
        is to ``estimation``).
    make, model : str or None
        TIFF tags 271/272 (RAWs with a TIFF structure: DNG, NEF, CR2, ARW...).
    color_matrix : (3, 3) float64 or None
        XYZ -> camera: the DNG's ColorMatrix (the D65-calibrated one when
        the file has two), else LibRaw's built-in matrix for the camera.
    as_shot_neutral : (3,) float64 or None
        Camera RGB of the as-shot white, green = 1 (``1 / camera_whitebalance``);
        ``None`` when the file records none, or one :func:`as_shot_problem` refuses.
    as_shot_problem : str or None
        Why the as-shot white the file records is not used (``as_shot_neutral``
        is then ``None``): e.g. "AsShotNeutral (1e-06, 1, 1e+06) ...".
    black_level, white_level : float or None
        Mean of the per-channel black levels, and the white level, in
        digital numbers (0 and 65535, or 0 and 1.0, for TIFF/PNG).
    warnings : list of str
        Things the user should know about the decode.
    encoding : dict or None
        TIFF/PNG with colour tags: what its ICC profile or PNG chunks say
        (:meth:`service.decode.icc.Encoding.describe`: source, name, linear,
        the tone curves); ``estimation`` holds the values linearised through
        them when ``linear`` is false.
    """

    kind: str
    estimation: np.ndarray
    saturated: np.ndarray
    full_shape: tuple
    make: str | None = None
    model: str | None = None
    color_matrix: np.ndarray | None = None
    as_shot_neutral: np.ndarray | None = None
    as_shot_problem: str | None = None
    black_level: float | None = None
    white_level: float | None = None
    warnings: list = field(default_factory=list)
    encoding: dict | None = None
    #: RAW: the file's bytes, to demosaic again on demand (never the pixels).
    _source: bytes | None = field(default=None, repr=False, compare=False)
    #: RAW (plain Bayer, square pixels), when the caller renders next
    #: (``keep_mosaic``): the sensor mosaic as the first decode unpacked it,
    #: with what scaling it needs, so the full-resolution image does not
    #: open and unpack the file a second time; taken (and dropped) by it.
    _mosaic: dict | None = field(default=None, repr=False, compare=False)
    #: RAW: LibRaw postprocessing parameters giving the estimation scale.
    _postprocess: dict = field(default_factory=dict, repr=False, compare=False)
    #: RAW: the demosaic :meth:`full_linear` uses when it is given none
    #: (``None``: :data:`service.decode.raw.DEMOSAIC_DEFAULT`; the pipeline
    #: sets it from the ``quality`` preset, :func:`service.decode.raw.demosaic_for`).
    demosaic: str | None = field(default=None, repr=False, compare=False)
    #: RAW: a LinearRaw DNG in the plain layout (:mod:`service.decode.linear_dng`),
    #: its raw image's (height, width) unoriented: :meth:`full_linear` reads its
    #: samples tile by tile instead of LibRaw's full decode.
    _linear_raw: tuple | None = field(default=None, repr=False, compare=False)

    @property
    def binning(self) -> float:
        """Full-resolution pixels per estimation pixel along a side (2 for
        a Bayer RAW, 1 for TIFF/PNG)."""
        return self.full_shape[0] / max(1, self.estimation.shape[0])

    def full_linear(self, out: str = "uint16", *, demosaic: str | None = None) -> np.ndarray:
        """The full-resolution linear camera RGB image on the estimation scale.

        RAW: a LinearRaw DNG's own samples read segment by segment
        (:func:`service.decode.linear_dng.linear_dng_full`, the same scale);
        any other RAW demosaiced by LibRaw from the file's bytes (the handle is closed
        before returning, so only the result stays in memory) with a linear
        curve, no auto-brightening, no white balance or colour conversion
        (``output_color=raw``), the file's orientation, the data maximum not
        adjusted and per-channel gains such that ``value / 65535`` equals
        the estimation image's :math:`(d - b_c)/(w - b_c)` (clipped to
        [0, 65535] by LibRaw). TIFF/PNG: the input, scaled the same way.

        Parameters
        ----------
        out : {"uint16", "float32"}
            ``uint16``: 65535 = saturation. ``float32``: 1.0 = saturation
            (for float TIFF input, values outside [0, 1] are kept).
        demosaic : str, optional
            ``"rcd"`` (the default: ratio-corrected demosaicing of the Bayer
            mosaic, :mod:`recovery.demosaic`), ``"fast"`` (OpenCV's
            edge-aware bilinear interpolation, ``quality=fast``) or a
            ``rawpy.DemosaicAlgorithm`` name (``AHD``, ``DHT``, ``AAHD``,
            ``LINEAR``, ``DCB``, ``PPG``, ``VNG``...). RAW only; without
            it, :attr:`demosaic`.

        Returns
        -------
        numpy.ndarray
            ``(H, W, 3)`` of ``full_shape``; a new array on every call.

        Raises
        ------
        ServiceError
            422 ``corrupt_file`` if LibRaw fails on the pixels.
        """
        if out not in ("uint16", "float32"):
            raise ValueError(f"out must be 'uint16' or 'float32', not {out!r}")
        if self.kind == "raw":
            from .raw import _raw_full_linear   # here: the RAW decoder imports this module

            rgb = _raw_full_linear(self, demosaic or self.demosaic)
            if out == "uint16":
                return rgb
            return _uint16_to_unit_float(rgb)
        est = self.estimation
        if out == "float32":
            return est.copy()
        res = np.empty(est.shape, np.uint16)
        for r in range(0, est.shape[0], 256):
            chunk = est[r:r + 256] * np.float32(65535.0)
            np.clip(chunk, 0.0, 65535.0, out=chunk)
            res[r:r + 256] = np.rint(chunk)
        return res


def _uint16_to_unit_float(rgb: np.ndarray) -> np.ndarray:
    res = np.empty(rgb.shape, np.float32)
    inv = np.float32(1.0 / 65535.0)
    for r in range(0, rgb.shape[0], 256):
        np.multiply(rgb[r:r + 256], inv, out=res[r:r + 256], dtype=np.float32)
    return res
