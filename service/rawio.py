"""Uploaded images to linear camera RGB (decoding only; which camera took the
image is :mod:`recovery.cameras`).

:func:`decode_upload` turns the bytes of an upload into a
:class:`DecodedImage`: a half-size, black-subtracted, saturation-scaled
*estimation image* made by binning each 2x2 Bayer cell (no demosaic), a
mask of saturated cells, the metadata that says which camera took it
(Make/Model, colour matrix, as-shot neutral, black and white levels), and
a method that demosaics the full-resolution image on the same scale when
(and only when) it is needed. Every refusal is a
:class:`~service.errors.ServiceError` (413, 415 or 422).

Scale of the estimation image. For a CFA site of colour ``c`` with digital
number :math:`d`, black level :math:`b_c` and white level :math:`w`,

.. math::

    v = \\frac{d - b_c}{w - b_c},

so 1.0 is saturation in every channel; a cell's red and blue are its red and
blue sites, its green the mean of its two green sites. The full-resolution
image of :meth:`DecodedImage.full_linear` is LibRaw's demosaic of the same
numbers with ``value / 65535`` equal to :math:`v` (LibRaw subtracts the
per-channel black and scales by ``65535 / (w - min_c b_c)``; the per-channel
user white balance :math:`(w - \\min_c b_c)/(w - b_c)` makes its scale exactly
the one above).

What LibRaw 0.22 (``rawpy`` 0.28) does with our files is measured in
``tests/test_dngwriter.py`` and ``tests/test_rawio.py`` (see also
:mod:`testing.dngwriter`): ``raw.sizes`` is read without unpacking the pixels
(so the pixel-count limit is enforced before any pixel buffer exists), a
truncated file fails only when the pixels are unpacked, and a file one byte
short decodes silently from memory, which is why the strip/tile extents of a
TIFF-structured file are checked against its length here.

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 12 and Fig. 6.
Adobe, *Digital Negative (DNG) Specification* 1.4.0.0, chapter 6 (ColorMatrix
maps XYZ to the camera's reference space).
"""

from __future__ import annotations

import io
import math
import os
import struct
import zlib
from dataclasses import dataclass, field

import numpy as np

from .errors import ServiceError

__all__ = [
    "DecodedImage",
    "decode_upload",
    "SATURATION_FRACTION",
    "FLIP_OPS",
]

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
        Camera RGB of the as-shot white, green = 1 (``1 / camera_whitebalance``).
    black_level, white_level : float or None
        Mean of the per-channel black levels, and the white level, in
        digital numbers (0 and 65535, or 0 and 1.0, for TIFF/PNG).
    warnings : list of str
        Things the user should know about the decode.
    """

    kind: str
    estimation: np.ndarray
    saturated: np.ndarray
    full_shape: tuple
    make: str | None = None
    model: str | None = None
    color_matrix: np.ndarray | None = None
    as_shot_neutral: np.ndarray | None = None
    black_level: float | None = None
    white_level: float | None = None
    warnings: list = field(default_factory=list)
    #: RAW: the file's bytes, to demosaic again on demand (never the pixels).
    _source: bytes | None = field(default=None, repr=False, compare=False)
    #: RAW: LibRaw postprocessing parameters giving the estimation scale.
    _postprocess: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def binning(self) -> float:
        """Full-resolution pixels per estimation pixel along a side (2 for
        a Bayer RAW, 1 for TIFF/PNG)."""
        return self.full_shape[0] / max(1, self.estimation.shape[0])

    def full_linear(self, out: str = "uint16", *, demosaic: str | None = None) -> np.ndarray:
        """The full-resolution linear camera RGB image on the estimation scale.

        RAW: demosaiced by LibRaw from the file's bytes (the handle is closed
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
            ``"fast"`` (the default: OpenCV's edge-aware interpolation of
            the Bayer mosaic) or a ``rawpy.DemosaicAlgorithm`` name
            (``AHD``, ``LINEAR``, ``DCB``, ``PPG``, ``VNG``...). RAW only.

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
            rgb = _raw_full_linear(self, demosaic)
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


# ---------------------------------------------------------------------------
# Format sniffing
# ---------------------------------------------------------------------------

def _sniff(data: bytes) -> str:
    """Name of the format the first bytes announce (``"unknown"`` if none)."""
    head = bytes(data[:16])
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        return "TIFF"
    if head[:4] in (b"II+\x00", b"MM\x00+"):
        return "BigTIFF"
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "PNG"
    if head.startswith(b"\xff\xd8\xff"):
        return "JPEG"
    if head.startswith((b"GIF87a", b"GIF89a")):
        return "GIF"
    if head.startswith(b"BM"):
        return "BMP"
    if head[:4] == b"RIFF" and head[8:12] == b"WEBP":
        return "WebP"
    if head[4:8] == b"ftyp":
        brand = head[8:12]
        if brand == b"crx ":
            return "Canon CR3"
        if brand in (b"heic", b"heix", b"mif1", b"msf1", b"hevc"):
            return "HEIF"
        if brand in (b"avif", b"avis"):
            return "AVIF"
        return "ISO media (" + brand.decode("latin-1").strip() + ")"
    if head.startswith(b"\x00\x00\x00\x0cjP  "):
        return "JPEG 2000"
    if head.startswith(b"v/1\x01"):
        return "OpenEXR"
    if head.startswith(b"%PDF"):
        return "PDF"
    if head.startswith(b"PK\x03\x04"):
        return "ZIP"
    if head.startswith(b"\x93NUMPY"):
        return "NumPy .npy"
    if head.startswith(b"FUJIFILM"):
        return "Fujifilm RAF"
    if head[:4] in (b"IIRO", b"IIRS", b"MMOR"):
        return "Olympus ORF"
    if head[:4] == b"IIU\x00":
        return "Panasonic RW2"
    if head.startswith(b"FOVb"):
        return "Sigma X3F"
    if head[:2] == b"II" and head[6:14] == b"HEAPCCDR":
        return "Canon CRW"
    if head.startswith(b"\x00MRM"):
        return "Minolta MRW"
    if _is_text(data):
        return "text"
    return "unknown"


def _is_text(data: bytes, n: int = 4096) -> bool:
    """Whether the file starts as text (UTF-8, no NUL byte, at least 95 %
    printable or whitespace in its first ``n`` bytes, at least 16 of them,
    not starting with a TIFF byte order ``II``/``MM``): every RAW and TIFF
    starts with a binary header, so such a file is certainly not one,
    whatever its name (a header cut to a few bytes stays "damaged")."""
    head = bytes(data[:n])
    if len(head) < 16 or head[:2] in (b"II", b"MM") or b"\0" in head:
        return False
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError as e:
        if e.start < len(head) - 3:      # only a character cut at the end is forgiven
            return False
        text = head[:e.start].decode("utf-8")
    ok = sum(c.isprintable() or c in "\t\n\r\f\v" for c in text)
    return bool(text) and ok >= 0.95 * len(text)


def camera_label(make: str | None, model: str | None) -> str:
    """``make model`` for messages, the make once: LibRaw and many files
    give a model that already starts with the make ("Nikon" + "Nikon
    COOLSCAN IV ED")."""
    make, model = (make or "").strip(), (model or "").strip()
    if make and model.lower().startswith(make.lower()):
        return model
    return " ".join(x for x in (make, model) if x)


#: Formats that are certainly not RAW: refused without asking LibRaw.
_NOT_RAW = {"JPEG", "GIF", "BMP", "WebP", "HEIF", "AVIF", "JPEG 2000", "OpenEXR", "PDF", "ZIP",
            "NumPy .npy", "text"}


def _extension(filename: str | None) -> str:
    return os.path.splitext(filename or "")[1].lower()


# ---------------------------------------------------------------------------
# decode_upload
# ---------------------------------------------------------------------------

def decode_upload(data: bytes, filename: str | None, *, max_pixels: int,
                  estimation_pixels: int | None = None) -> DecodedImage:
    """Decode an uploaded RAW, 16-bit/float TIFF or 16-bit PNG.

    The format is recognised from the content (the file name only decides
    whether an unreadable file is called corrupt or of unknown format).
    Files with a TIFF structure go to LibRaw first (DNG, NEF, CR2, ARW...);
    a TIFF LibRaw does not take is read with ``tifffile`` as a linear image;
    any other content LibRaw reads (CR3, RAF, RW2, ORF...) is a RAW.

    Parameters
    ----------
    data : bytes
        The whole file.
    filename : str or None
        As uploaded (used in messages and for the extension).
    max_pixels : int
        Largest declared pixel count accepted; checked from the headers
        before any pixel buffer is allocated.
    estimation_pixels : int, optional
        For a Bayer RAW, bin ``2f x 2f`` CFA blocks (OpenCV area averaging
        of each CFA plane) with the smallest ``f`` that gives at most this
        many estimation pixels; default: half size (``f = 1``).

    Returns
    -------
    DecodedImage

    Raises
    ------
    ServiceError
        422 ``empty_file``; 415 ``unsupported_format`` (JPEG, GIF, ...,
        anything LibRaw cannot read, grey or non-RGB images, unsupported
        sample types); 415 ``not_linear`` (8-bit TIFF/PNG, which are gamma
        encoded); 413 ``too_many_pixels``; 422 ``corrupt_file`` (truncated or
        damaged); 422 ``non_finite`` (NaN/Inf in a float TIFF). Nothing else
        escapes: an unexpected failure while decoding is a 422
        ``corrupt_file``.
    """
    if data is None or len(data) == 0:
        raise ServiceError(422, "empty_file", "the uploaded file is empty")
    if not isinstance(data, bytes):
        data = bytes(data)
    max_pixels = int(max_pixels)
    fmt = _sniff(data)
    label = f"{filename!r}" if filename else "the upload"
    try:
        if fmt == "PNG":
            return _decode_png(data, max_pixels)
        if fmt in _NOT_RAW:
            named = (f" named {_extension(filename)}, but its content has no TIFF or RAW signature LibRaw "
                     "recognises" if _extension(filename) in RAW_EXTENSIONS else "")
            raise ServiceError(415, "unsupported_format",
                              f"{label} is a {fmt} file (detected from its content){named}; send a camera RAW (DNG, NEF, CR2, ARW, ...) or a "
                              "linear 16-bit/float TIFF or 16-bit PNG")
        return _decode_raw_or_tiff(data, fmt, filename, max_pixels, estimation_pixels)
    except ServiceError:
        raise
    except MemoryError:
        raise ServiceError(413, "too_many_pixels",
                          f"not enough memory to decode {label}; send a smaller image") from None
    except Exception as exc:  # malformed data must never escape as a 500
        raise ServiceError(422, "corrupt_file",
                          f"{label} ({fmt}) could not be decoded: {type(exc).__name__}: {exc}") from None


def _decode_raw_or_tiff(data: bytes, fmt: str, filename: str | None, max_pixels: int,
                        estimation_pixels: int | None = None) -> DecodedImage:
    import rawpy

    label = f"{filename!r}" if filename else "the upload"
    try:
        raw = rawpy.imread(io.BytesIO(data))
    except rawpy.LibRawFileUnsupportedError:
        if fmt in ("TIFF", "BigTIFF"):
            return _decode_tiff(data, filename, max_pixels)
        if data[:2] in (b"II", b"MM") or _extension(filename) in RAW_EXTENSIONS:
            what = "a TIFF-like header" if data[:2] in (b"II", b"MM") else f"a {_extension(filename)} name"
            raise ServiceError(422, "corrupt_file",
                              f"{label} has {what} but neither LibRaw nor tifffile can read it "
                              "(damaged or truncated header?)") from None
        raise ServiceError(415, "unsupported_format",
                          f"{label} is not a format the service reads (detected: {fmt}, first bytes "
                          f"{data[:8].hex()}); send a camera RAW LibRaw reads, or a linear 16-bit/float "
                          "TIFF or 16-bit PNG") from None
    except (rawpy.LibRawTooBigError, rawpy.LibRawUnsufficientMemoryError) as exc:
        raise ServiceError(413, "too_many_pixels", f"{label}: LibRaw refused the size ({exc})") from None
    except rawpy.LibRawError as exc:
        if fmt == "unknown" and data[:2] not in (b"II", b"MM") and _extension(filename) not in RAW_EXTENSIONS:
            raise ServiceError(415, "unsupported_format",
                              f"{label} is not a format the service reads (detected: {fmt}, first bytes "
                              f"{data[:8].hex()}); send a camera RAW LibRaw reads, or a linear 16-bit/float "
                              "TIFF or 16-bit PNG") from None
        raise ServiceError(422, "corrupt_file",
                          f"{label} could not be read as a RAW file ({type(exc).__name__}: "
                          f"{_librawmsg(exc)}); it is truncated or damaged") from None
    try:
        if _tiff_structured(data):
            _check_tiff_structure(data)
        info, info_error = None, None
        if fmt in ("TIFF", "BigTIFF"):
            try:
                info = _tiff_info(data)
            except Exception as exc:  # LibRaw read it; tifffile is only a second opinion
                info_error = exc
            if info is not None and info.plain_multisample:
                # LibRaw reads any 16-bit TIFF without camera tags as a mosaic,
                # even one of 2 or 4 samples per pixel: not a RAW
                raw.close()
                return _decode_tiff(data, filename, max_pixels)
        return _decode_raw(raw, data, fmt, filename, max_pixels, info, info_error, estimation_pixels)
    except (rawpy.LibRawTooBigError, rawpy.LibRawUnsufficientMemoryError) as exc:
        raise ServiceError(413, "too_many_pixels", f"{label}: LibRaw refused the size ({exc})") from None
    except rawpy.LibRawError as exc:
        raise ServiceError(422, "corrupt_file",
                          f"{label}: LibRaw failed on the pixel data ({type(exc).__name__}: "
                          f"{_librawmsg(exc)}); the file is truncated or damaged") from None
    finally:
        raw.close()


def _librawmsg(exc) -> str:
    msg = exc.args[0] if exc.args else ""
    return msg.decode("utf-8", "replace") if isinstance(msg, bytes) else str(msg)


# ---------------------------------------------------------------------------
# TIFF structure: tags and strip extents
# ---------------------------------------------------------------------------

@dataclass
class _TiffInfo:
    make: str | None = None
    model: str | None = None
    color_matrix: np.ndarray | None = None
    is_dng: bool = False
    grey_guess: bool = False       # a plain grey TIFF LibRaw takes for an RGGB mosaic
    plain_multisample: bool = False  # a plain TIFF of 2+ samples LibRaw misreads as a mosaic
    problem: str | None = None     # strips/tiles beyond the end of the file


def _tag(page, code):
    t = page.tags.get(code)
    return None if t is None else t.value


#: Longest string taken from a file (Make, Model, UniqueCameraModel): real
#: camera names are under 40 characters.
MAX_FILE_STRING = 64


def file_string(value, limit: int = MAX_FILE_STRING) -> str | None:
    """A string read from an uploaded file, safe to echo in a header, JSON or
    the page.

    Decoded as UTF-8 (else Latin-1) if bytes; every run of characters that are not
    printable (NUL, CR/LF and other control characters, including C1) or
    whitespace becomes one space; trimmed; cut to ``limit`` characters (the
    last three ``...`` when cut).

    Parameters
    ----------
    value : str, bytes or None
    limit : int

    Returns
    -------
    str or None
        ``None`` when nothing printable is left.

    Examples
    --------
    >>> file_string(b"A\\r\\nX-Injected: 1\\x00")
    'A X-Injected: 1'
    >>> len(file_string("M" * 65536))
    64
    """
    if value is None:
        return None
    if isinstance(value, (bytes, bytearray)):
        try:
            value = bytes(value).decode("utf-8")
        except UnicodeDecodeError:
            value = bytes(value).decode("latin-1")
    text = " ".join("".join(c if c.isprintable() and not c.isspace() else " " for c in str(value)).split())
    if len(text) > limit:
        text = text[:limit - 3].rstrip() + "..."
    return text or None


def _ascii_tag(page, code) -> str | None:
    v = _tag(page, code)
    if isinstance(v, bytes) and len(v) > 4 * MAX_FILE_STRING:
        v = v[:4 * MAX_FILE_STRING]           # no need to scan 64 KiB of it
    elif isinstance(v, str) and len(v) > 4 * MAX_FILE_STRING:
        v = v[:4 * MAX_FILE_STRING]
    return file_string(v)


def _srational_matrix(value) -> np.ndarray | None:
    """A 3x3 matrix from a (S)RATIONAL tag value as tifffile gives it
    (9 numerator/denominator pairs, flat, or 9 floats); ``None`` if not."""
    if value is None:
        return None
    v = np.asarray(value, dtype=np.float64).ravel()
    if v.size == 18:
        num, den = v[0::2], v[1::2]
        if np.any(den == 0):
            return None
        v = num / den
    if v.size != 9 or not np.all(np.isfinite(v)):
        return None
    m = v.reshape(3, 3)
    return None if not np.any(m) else m


def _iter_ifds(pages, depth=0, seen=None, limit=64):
    """Pages and their SubIFDs, at most ``limit`` in all, each IFD once: a
    damaged next-IFD offset can make the chain circular, and tifffile would
    follow it for ever."""
    seen = set() if seen is None else seen
    i = 0
    while len(seen) < limit:
        try:
            page = pages[i]
        except (IndexError, KeyError):
            return
        off = getattr(page, "offset", None)
        if off is None or off in seen:
            return
        seen.add(off)
        yield page
        if depth < 2 and getattr(page, "subifds", None):
            try:
                sub = page.pages
            except Exception:
                sub = None
            if sub is not None:
                yield from _iter_ifds(sub, depth + 1, seen, limit)
        i += 1


def _tiff_info(data: bytes) -> _TiffInfo:
    """Make, Model, the XYZ -> camera matrix and the strip/tile check of a
    TIFF-structured file (IFD0 and SubIFDs of every page)."""
    import tifffile

    info = _TiffInfo()
    size = len(data)
    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        p0 = tf.pages.first if hasattr(tf.pages, "first") else tf.pages[0]
        info.make = _ascii_tag(p0, 271)
        info.model = _ascii_tag(p0, 272)
        info.is_dng = _tag(p0, 50706) is not None
        if info.make is None and info.model is None:
            info.model = _ascii_tag(p0, 50708)        # DNG UniqueCameraModel
        # LibRaw reads a 1-sample 16-bit TIFF without camera tags as an RGGB
        # mosaic (what ``dcraw -D -T`` writes): right for such a dump, wrong
        # for a monochrome picture, so the user is told
        plain = not info.is_dng and info.make is None and _tag(p0, 33422) is None
        spp = int(getattr(p0, "samplesperpixel", 1) or 1)
        info.grey_guess = plain and spp == 1 and int(getattr(p0, "photometric", 1) or 0) in (0, 1)
        info.plain_multisample = plain and spp > 1
        cm1, cm2 = _srational_matrix(_tag(p0, 50721)), _srational_matrix(_tag(p0, 50722))
        ci1, ci2 = _tag(p0, 50778), _tag(p0, 50779)
        # prefer the D65-calibrated matrix (EXIF LightSource 21) of a dual-
        # illuminant DNG; the usual pair is Standard A (17) and D65 (21)
        if cm2 is not None and ci2 is not None and int(ci2) == 21 and (ci1 is None or int(ci1) != 21):
            info.color_matrix = cm2
        else:
            info.color_matrix = cm1 if cm1 is not None else cm2
        for page in _iter_ifds(tf.pages):
            offs = getattr(page, "dataoffsets", ()) or ()
            cnts = getattr(page, "databytecounts", ()) or ()
            for off, cnt in zip(offs, cnts):
                if off < 0 or cnt < 0 or off + cnt > size:
                    info.problem = (f"image data at bytes {off}..{off + cnt} lies beyond the end of the "
                                    f"{size}-byte file (truncated?)")
                    return info
    return info


# ---------------------------------------------------------------------------
# TIFF structure: every strip and tile LibRaw may decode, verified
# ---------------------------------------------------------------------------
#
# LibRaw decodes into a buffer it does not clear: a strip or tile that is
# missing, short, outside the file or damaged leaves part of that buffer as
# the previous decode left it, i.e. another upload's pixels (issue 10). So
# before LibRaw unpacks a TIFF-structured file (DNG, NEF, CR2, ARW, ...; any
# file starting with a byte-order mark, since LibRaw ignores the magic
# number), the IFDs are walked here, independently of tifffile, and every
# IFD that has image data must declare strips or tiles that the file really
# contains. What cannot be verified is refused.

#: Bytes per value of each TIFF field type (TIFF 6.0 section 2; 13 = IFD,
#: 16-18 = BigTIFF 8-byte types).
_TIFF_TYPE_SIZES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 13: 4,
                    16: 8, 17: 8, 18: 8}
_IFD_LIMIT = 64                 # IFDs (chain and SubIFDs) walked before giving up
_ENTRY_LIMIT = 4096             # entries in one IFD
#: Tags whose value decides where LibRaw reads pixels: read here exactly,
#: refused when duplicated or malformed.
_STRUCTURE_TAGS = (254, 256, 257, 258, 259, 262, 273, 277, 278, 279, 284, 322, 323, 324, 325, 330)
_TAG_NAMES = {254: "NewSubfileType", 256: "ImageWidth", 257: "ImageLength", 258: "BitsPerSample",
              259: "Compression", 262: "PhotometricInterpretation", 273: "StripOffsets", 277: "SamplesPerPixel",
              278: "RowsPerStrip", 279: "StripByteCounts", 284: "PlanarConfiguration", 322: "TileWidth",
              323: "TileLength", 324: "TileOffsets", 325: "TileByteCounts", 330: "SubIFDs"}
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_PHOTOMETRIC_RAW = (32803, 34892)   # CFA, LinearRaw: the IFDs LibRaw takes a DNG's pixels from


class _Unverifiable(Exception):
    """The TIFF structure says something the decode cannot be trusted with."""


def _ifd_values(data: bytes, bo: str, typ: int, count: int, pos: int) -> list[int]:
    size = _TIFF_TYPE_SIZES.get(typ)
    if size is None or typ not in (1, 3, 4, 6, 8, 9, 13, 16, 17):
        raise _Unverifiable(f"field type {typ} where an integer is expected")
    if count > len(data) // size:
        raise _Unverifiable(f"a count of {count} values cannot fit in the file")
    if count * size > 4:
        (pos,) = struct.unpack_from(bo + "I", data, pos)
    if pos + count * size > len(data):
        raise _Unverifiable(f"values at bytes {pos}..{pos + count * size} lie beyond the end of the file")
    fmt = {1: "B", 3: "H", 4: "I", 6: "b", 8: "h", 9: "i", 13: "I", 16: "Q", 17: "q"}[typ]
    return list(struct.unpack_from(f"{bo}{count}{fmt}", data, pos))


def _read_ifd(data: bytes, bo: str, off: int) -> tuple[dict, int, tuple[int, int]]:
    """``({tag: [values]}, next-IFD offset, (start, end) of the IFD)`` for
    the structure tags of the IFD at ``off``."""
    if off < 8 or off + 2 > len(data):
        raise _Unverifiable(f"an IFD at byte {off} is outside the {len(data)}-byte file")
    (n,) = struct.unpack_from(bo + "H", data, off)
    end = off + 2 + 12 * n + 4
    if n == 0 or n > _ENTRY_LIMIT or end > len(data):
        why = "past the end of the file" if end > len(data) else "implausible"
        raise _Unverifiable(f"the IFD at byte {off} declares {n} entries ({why})")
    tags: dict = {}
    for i in range(n):
        pos = off + 2 + 12 * i
        tag, typ, count = struct.unpack_from(bo + "HHI", data, pos)
        if tag not in _STRUCTURE_TAGS:
            continue
        if tag in tags:
            raise _Unverifiable(f"{_TAG_NAMES[tag]} (tag {tag}) appears twice in the IFD at byte {off}")
        try:
            tags[tag] = _ifd_values(data, bo, typ, count, pos + 8)
        except _Unverifiable as exc:
            raise _Unverifiable(f"{_TAG_NAMES[tag]} (tag {tag}) of the IFD at byte {off}: {exc}") from None
    (nxt,) = struct.unpack_from(bo + "I", data, end - 4)
    return tags, nxt, (off, end)


def _one(tags: dict, tag: int, default=None):
    v = tags.get(tag)
    if v is None:
        return default
    if len(v) != 1:
        raise _Unverifiable(f"{_TAG_NAMES[tag]} (tag {tag}) has {len(v)} values, not 1")
    return int(v[0])


def _check_jpeg(data: bytes, start: int, end: int, raw_ifd: bool, tile_w: int, tile_h: int, spp: int) -> None:
    """The marker segments of one (lossless) JPEG strip or tile in
    ``data[start:end]``: SOI, well-formed DQT/DHT/SOF/SOS segments inside
    the range and, for the raw image, a frame LibRaw's DNG decoder reads
    (SOF3 lossless or SOF1) whose samples cover the whole tile."""
    if data[start:start + 2] != b"\xff\xd8":
        raise _Unverifiable(f"the JPEG data at byte {start} does not start with an SOI marker")
    p, sof, huffman = start + 2, None, set()
    while True:
        if p + 4 > end or data[p] != 0xFF:
            raise _Unverifiable(f"the JPEG data at byte {start} has no valid marker at byte {p}")
        m = data[p + 1]
        if m == 0xFF:
            p += 1
            continue
        if m == 0x01 or 0xD0 <= m <= 0xD8 or m == 0xD9:
            raise _Unverifiable(f"the JPEG data at byte {start} has marker {m:02X} before its scan")
        (length,) = struct.unpack_from(">H", data, p + 2)
        seg, seg_end = p + 4, p + 2 + length
        if length < 2 or seg_end > end:
            raise _Unverifiable(f"the JPEG segment {m:02X} at byte {p} has length {length}, outside its data")
        if m == 0xC4:                       # DHT: class/id, 16 counts, the values; exactly filled
            q = seg
            while q < seg_end:
                tc, th = data[q] >> 4, data[q] & 15
                if tc > 1 or th > 3 or q + 17 > seg_end:
                    raise _Unverifiable(f"the JPEG Huffman table at byte {q} is malformed")
                q += 17 + sum(data[q + 1:q + 17])
                huffman.add((tc, th))
            if q != seg_end:
                raise _Unverifiable(f"the JPEG Huffman tables at byte {p} overrun their segment")
        elif m == 0xDB:                     # DQT: precision/id, 64 or 128 bytes; exactly filled
            q = seg
            while q < seg_end:
                pq, tq = data[q] >> 4, data[q] & 15
                if pq > 1 or tq > 3:
                    raise _Unverifiable(f"the JPEG quantisation table at byte {q} is malformed")
                q += 1 + 64 * (1 + pq)
            if q != seg_end:
                raise _Unverifiable(f"the JPEG quantisation tables at byte {p} overrun their segment")
        elif m in _JPEG_SOF:
            if sof is not None or length < 8:
                raise _Unverifiable(f"the JPEG data at byte {start} has a second or short frame header")
            prec, height, width, nc = struct.unpack_from(">BHHB", data, seg)
            if length != 8 + 3 * nc or not 1 <= nc <= 4 or not 2 <= prec <= 16 or height < 1 or width < 1:
                raise _Unverifiable(f"the JPEG frame header at byte {p} is malformed (precision {prec}, "
                                    f"{width}x{height}, {nc} components, length {length})")
            sof = (m, height, width, nc)
        elif m == 0xDA:                     # SOS: the entropy-coded data follows
            ns = data[seg] if seg < seg_end else 0
            if sof is None or length != 6 + 2 * ns or not 1 <= ns <= sof[3] or seg_end >= end:
                raise _Unverifiable(f"the JPEG scan header at byte {p} is malformed or has no frame before it")
            break
        p = seg_end
    kind, height, width, nc = sof
    if not raw_ifd and kind != 0xC3:
        return
    if kind not in (0xC1, 0xC3) or not huffman:
        raise _Unverifiable(f"the raw image's JPEG at byte {start} is not a lossless (SOF3) or SOF1 JPEG "
                            f"with Huffman tables (frame type {kind:02X})")
    if kind == 0xC3:
        covered = width * height * nc >= tile_w * tile_h * spp
    else:   # LibRaw reads 8x8 blocks; two tile rows per JPEG row
        covered = nc == 1 and tile_w % 8 == 0 and width // 8 * 8 >= 2 * tile_w and 2 * (height // 8 * 8) >= tile_h
    if not covered:
        raise _Unverifiable(f"the JPEG at byte {start} ({width}x{height}, {nc} component(s)) does not cover its "
                            f"{tile_w}x{tile_h} tile")


def _check_image_ifd(data: bytes, tags: dict, where: str, is_dng: bool, structure: list) -> None:
    """Strips or tiles of one IFD: present in pairs, as many as the image
    needs, each inside the file, after the header and outside every IFD,
    complete when uncompressed, and (JPEG-compressed) with valid markers."""
    size = len(data)
    tiled = 324 in tags or 325 in tags or 322 in tags or 323 in tags
    if tiled and (273 in tags or 279 in tags):
        raise _Unverifiable(f"{where} has both strips and tiles")
    offs, cnts = (tags.get(324), tags.get(325)) if tiled else (tags.get(273), tags.get(279))
    if offs is None or cnts is None:
        raise _Unverifiable(f"{where} has image data offsets without byte counts (or the reverse)")
    if len(offs) != len(cnts) or not offs:
        raise _Unverifiable(f"{where} declares {len(offs)} data offsets but {len(cnts)} byte counts")
    width, height = _one(tags, 256), _one(tags, 257)
    spp, planar, compression = _one(tags, 277, 1), _one(tags, 284, 1), _one(tags, 259, 1)
    photometric = _one(tags, 262)
    bps = tags.get(258) or [1]
    raw_ifd = is_dng and photometric in _PHOTOMETRIC_RAW
    geometry = width is not None and height is not None
    if (is_dng or tiled) and not geometry:
        raise _Unverifiable(f"{where} has image data but no image width and length")
    tile_w = tile_h = None
    if geometry:
        if width < 1 or height < 1 or spp < 1:
            raise _Unverifiable(f"{where} declares a {width}x{height} image of {spp} samples")
        planes = spp if planar == 2 else 1
        if tiled:
            tile_w, tile_h = _one(tags, 322), _one(tags, 323)
            if not tile_w or not tile_h:
                raise _Unverifiable(f"{where} has tiles without a tile width and length")
            expected = -(-width // tile_w) * -(-height // tile_h) * planes
        else:
            rows = _one(tags, 278, 2**32 - 1) or 2**32 - 1
            tile_w, tile_h = width, min(rows, height)
            expected = -(-height // tile_h) * planes if is_dng else len(offs)
        if len(offs) != expected:
            grid = f"{tile_w}x{tile_h} {'tiles' if tiled else 'strips'}"
            raise _Unverifiable(f"{where} declares {len(offs)} {'tiles' if tiled else 'strips'}; a "
                                f"{width}x{height} image in {grid} needs {expected}")
    for k, (off, cnt) in enumerate(zip(offs, cnts)):
        what = f"{'tile' if tiled else 'strip'} {k} of {where} (bytes {off}..{off + cnt})"
        if off <= 0 or cnt <= 0:
            raise _Unverifiable(f"{what} is empty or at offset 0")
        if off + cnt > size:
            raise _Unverifiable(f"{what} lies beyond the end of the {size}-byte file (truncated?)")
        if off < 8 or any(off < e and s < off + cnt for s, e in structure):
            raise _Unverifiable(f"{what} overlaps the TIFF header or an IFD")
        if not geometry:
            continue
        if compression == 1:
            rows = tile_h if tiled else min(tile_h, height - k % -(-height // tile_h) * tile_h)
            bits = tile_w * (1 if planar == 2 else spp) * max(int(b) for b in bps)
            need = -(-bits // 8) * rows
            if cnt < need:
                raise _Unverifiable(f"{what} holds {cnt} bytes; its uncompressed pixels need {need}")
        elif compression == 7:
            _check_jpeg(data, off, off + cnt, raw_ifd, tile_w, tile_h, 1 if planar == 2 else spp)


def _tiff_structured(data: bytes) -> bool:
    """Whether LibRaw reads ``data`` as a TIFF: a byte-order mark (LibRaw
    ignores the magic number), except the TIFF-like formats with their own
    layout (Panasonic RW2, Olympus ORF, Canon CRW), not verified here."""
    return data[:2] in (b"II", b"MM") and _sniff(data) not in ("Panasonic RW2", "Olympus ORF", "Canon CRW")


def _check_tiff_structure(data: bytes) -> None:
    """Verify every strip and tile of a TIFF-structured RAW before LibRaw
    decodes it.

    Walks IFD 0, its next-IFD chain and SubIFDs (each IFD once, at most
    :data:`_IFD_LIMIT`) with its own reader, and checks every IFD holding
    image data (:func:`_check_image_ifd`).

    Parameters
    ----------
    data : bytes
        The whole file, starting with ``II`` or ``MM``.

    Raises
    ------
    ServiceError
        422 ``corrupt_file`` naming the first thing that is missing, outside
        the file or inconsistent: LibRaw would decode such a file partly
        from memory that the previous decode left behind.
    """
    bo = "<" if data[:2] == b"II" else ">"
    try:
        if len(data) < 8:
            raise _Unverifiable("the file ends inside the TIFF header")
        (first,) = struct.unpack_from(bo + "I", data, 4)
        is_dng = first + 2 <= len(data) and 50706 in _tags_present(data, bo, first)
        todo, seen, structure, images = [first], set(), [(0, 8)], []
        while todo:
            off = todo.pop(0)
            while off and off not in seen:
                if len(seen) >= _IFD_LIMIT:
                    raise _Unverifiable(f"more than {_IFD_LIMIT} IFDs")
                seen.add(off)
                tags, nxt, span = _read_ifd(data, bo, off)
                structure.append(span)
                todo.extend(tags.get(330, ()))
                if any(t in tags for t in (273, 279, 324, 325)):
                    images.append((tags, f"the IFD at byte {off}"))
                off = nxt
        if not images:
            raise _Unverifiable("no IFD declares image data")
        for tags, where in images:
            _check_image_ifd(data, tags, where, is_dng, structure)
    except _Unverifiable as exc:
        raise ServiceError(422, "corrupt_file",
                          f"the file's TIFF structure cannot be verified: {exc}; it is truncated or damaged "
                          "(refused rather than decoded partly from memory)") from None
    except (struct.error, OverflowError, MemoryError, ValueError) as exc:
        raise ServiceError(422, "corrupt_file",
                          f"the file's TIFF structure cannot be verified ({type(exc).__name__}: {exc}); it is "
                          "truncated or damaged") from None


def _tags_present(data: bytes, bo: str, off: int) -> set:
    (n,) = struct.unpack_from(bo + "H", data, off)
    n = min(n, (len(data) - off - 2) // 12)
    return {struct.unpack_from(bo + "H", data, off + 2 + 12 * i)[0] for i in range(max(0, n))}


# ---------------------------------------------------------------------------
# RAW
# ---------------------------------------------------------------------------

def _oriented_shape(h: int, w: int, flip: int, pixel_aspect: float = 1.0) -> tuple[int, int]:
    if pixel_aspect and abs(pixel_aspect - 1.0) > 1e-6:
        # LibRaw's stretch(): non-square pixels are resampled to square ones
        if pixel_aspect < 1:
            h = int(h / pixel_aspect + 0.5)
        else:
            w = int(w * pixel_aspect + 0.5)
    return (w, h) if flip & 4 else (h, w)


def _bayer_channels(raw, sizes) -> list[tuple[int, int, int, int]] | None:
    """``[(dy, dx, colour index, channel 0/1/2), ...]`` for the four sites of
    the 2x2 cell at the visible origin, or ``None`` if the sensor is not a
    2x2 R, G, G, B Bayer."""
    pattern = raw.raw_pattern
    if pattern is None or pattern.shape != (2, 2):
        return None
    desc = raw.color_desc.decode("latin-1")
    sites = []
    for dy in (0, 1):
        for dx in (0, 1):
            idx = int(pattern[(dy + sizes.top_margin) % 2, (dx + sizes.left_margin) % 2])
            if idx >= len(desc) or desc[idx] not in "RGB":
                return None
            sites.append((dy, dx, idx, "RGB".index(desc[idx])))
    if sorted(s[3] for s in sites) != [0, 1, 1, 2]:
        return None
    return sites


def _bin_bayer(img: np.ndarray, sites, blacks, white: float, rows_per_chunk: int | None = None):
    """Bin 2x2 CFA cells: ``(d - b_c) / (w - b_c)`` per site, greens
    averaged, and the cell's saturation flag, in row chunks (temporaries
    stay small whatever the image size)."""
    H, W = img.shape
    h2, w2 = H // 2, W // 2
    est = np.empty((h2, w2, 3), np.float32)
    sat = np.zeros((h2, w2), bool)
    rows = rows_per_chunk or max(1, (1 << 19) // max(1, w2))
    plan = []
    for dy, dx, idx, ch in sites:
        b = float(blacks[idx])
        scale = np.float32(1.0 / (white - b))
        thr = math.ceil(b + SATURATION_FRACTION * (white - b))
        plan.append((img[dy:2 * h2:2, dx:2 * w2:2], ch, np.float32(b), scale, thr))
    for r0 in range(0, h2, rows):
        r1 = min(h2, r0 + rows)
        green = None
        for view, ch, b, scale, thr in plan:
            v = view[r0:r1]
            sat[r0:r1] |= v >= thr
            a = v.astype(np.float32)
            a -= b
            a *= scale
            if ch == 1:
                if green is None:
                    green = a
                else:
                    green += a
                    green *= np.float32(0.5)
            else:
                est[r0:r1, :, ch] = a
        est[r0:r1, :, 1] = green
    return est, sat


def _bin_bayer_area(img: np.ndarray, sites, blacks, white: float, f: int):
    """Bin ``2f x 2f`` CFA blocks: each CFA plane averaged over ``f x f``
    sites (OpenCV ``INTER_AREA``, the exact block mean for an integer
    factor, rounded to whole digital numbers), then ``(d - b_c)/(w - b_c)``,
    greens averaged; a block is saturated if any of its sites is."""
    import cv2

    H, W = img.shape
    hh, ww = (H // 2) // f, (W // 2) // f
    est = np.zeros((hh, ww, 3), np.float32)
    sat = np.zeros((hh, ww), bool)
    for dy, dx, idx, ch in sites:
        b = float(blacks[idx])
        plane = np.ascontiguousarray(img[dy:2 * hh * f:2, dx:2 * ww * f:2])
        mean = cv2.resize(plane, (ww, hh), interpolation=cv2.INTER_AREA).astype(np.float32)
        thr = math.ceil(b + SATURATION_FRACTION * (white - b))
        hit = cv2.resize(cv2.compare(plane, min(thr, 65535), cv2.CMP_GE), (ww, hh), interpolation=cv2.INTER_AREA)
        sat |= hit > 0
        mean -= np.float32(b)
        mean *= np.float32(1.0 / (white - b))
        est[..., ch] += mean * np.float32(0.5 if ch == 1 else 1.0)
    return est, sat


def _decode_raw(raw, data: bytes, fmt: str, filename: str | None, max_pixels: int,
                info: _TiffInfo | None = None, info_error: Exception | None = None,
                estimation_pixels: int | None = None) -> DecodedImage:
    import rawpy

    label = f"{filename!r}" if filename else "the upload"
    warnings: list[str] = []
    s = raw.sizes                         # header only: no pixel buffer yet
    declared = max(int(s.raw_height) * int(s.raw_width), int(s.height) * int(s.width))
    if declared > max_pixels:
        raise ServiceError(413, "too_many_pixels",
                          f"{label} declares {s.width}x{s.height} pixels ({declared:,} with margins); "
                          f"the limit is {max_pixels:,}")
    if s.height < 2 or s.width < 2:
        raise ServiceError(422, "corrupt_file", f"{label} declares an image of {s.width}x{s.height} pixels")
    aspect = float(s.pixel_aspect)
    if not (math.isfinite(aspect) and aspect > 0):
        raise ServiceError(422, "corrupt_file", f"{label} declares a pixel aspect ratio of {aspect}")
    # LibRaw stretches non-square pixels (DNG DefaultScale) to square ones when
    # demosaicking: the image it makes, not the declared one, must fit the limit
    out_h, out_w = _oriented_shape(int(s.height), int(s.width), 0, aspect)
    if out_h * out_w > max_pixels:
        raise ServiceError(413, "too_many_pixels",
                          f"{label} declares {s.width}x{s.height} pixels with a pixel aspect ratio of {aspect:.4g} "
                          f"(DNG DefaultScale): {out_w}x{out_h} = {out_h * out_w:,} pixels once stretched to "
                          f"square pixels; the limit is {max_pixels:,}")

    make = model = color_matrix = None
    if fmt in ("TIFF", "BigTIFF"):
        if info is None:
            warnings.append(f"TIFF tags unreadable ({type(info_error).__name__}); camera make/model unknown")
        else:
            if info.problem:
                raise ServiceError(422, "corrupt_file", f"{label}: {info.problem}")
            make, model, color_matrix = info.make, info.model, info.color_matrix
            if info.grey_guess:
                warnings.append("a single-channel TIFF without camera tags, read by LibRaw as an RGGB Bayer mosaic "
                                "(as dcraw -D writes); if it is a monochrome picture the colours are meaningless")
    else:
        warnings.append(f"{fmt} file: camera make/model are not read for this format; "
                        "give camera=... to use measured sensitivities")

    # -- pixels (unpacks; LibRawIOError etc. on truncated data)
    num_colors = int(raw.num_colors)
    if num_colors < 3:
        raise ServiceError(415, "unsupported_format",
                          f"{label} is a monochrome RAW ({num_colors} colour); colour analysis needs R, G, B")
    blacks = [float(b) for b in raw.black_level_per_channel]
    white = float(raw.white_level)
    if raw.raw_type != rawpy.RawType.Flat and white <= 255 and raw.raw_pattern is None:
        # e.g. a Nikon Coolscan NEF: 8-bit RGB per pixel, no sensor mosaic, no colour matrix
        who = camera_label(make, model)
        raise ServiceError(415, "not_camera_raw",
                          f"{label} is not a camera RAW: a scanned 8-bit RGB image"
                          + (f" ({who})" if who else "") + "; it carries no linear sensor data to analyse")
    if not white > max(blacks):
        raise ServiceError(422, "corrupt_file",
                          f"{label}: white level {white:g} is not above the black levels {blacks}")
    flip = int(s.flip) if int(s.flip) in FLIP_OPS else 0
    bmin = min(blacks)
    user_wb = [(white - bmin) / (white - b) for b in blacks]
    post = dict(gamma=(1, 1), no_auto_bright=True, output_bps=16, use_camera_wb=False, use_auto_wb=False,
                user_wb=user_wb, output_color=rawpy.ColorSpace.raw, adjust_maximum_thr=0.0, bright=1.0,
                highlight_mode=rawpy.HighlightMode.Clip, user_flip=flip)

    sites = _bayer_channels(raw, s)
    if sites is not None:
        if raw.raw_type != rawpy.RawType.Flat:
            sites = None
    if sites is not None:
        img = raw.raw_image_visible
        h2, w2 = img.shape[0] // 2, img.shape[1] // 2
        f = 1
        if estimation_pixels and h2 * w2 > estimation_pixels:
            f = int(math.ceil(math.sqrt(h2 * w2 / estimation_pixels)))
        if f > 1 and h2 // f >= 1 and w2 // f >= 1:
            est, sat = _bin_bayer_area(img, sites, blacks, white, f)
        else:
            est, sat = _bin_bayer(img, sites, blacks, white)
        del img
        if s.height % 2 or s.width % 2:
            warnings.append("odd image size: the last row/column is not in the half-size estimation image")
        if flip:
            est = np.ascontiguousarray(FLIP_OPS[flip](est))
            sat = np.ascontiguousarray(FLIP_OPS[flip](sat))
    else:
        desc = raw.color_desc.decode("latin-1")[:num_colors]
        if sorted(desc[:3]) != ["B", "G", "R"]:
            raise ServiceError(415, "unsupported_format",
                              f"{label}: a sensor with colours {desc!r} is not supported (needs R, G, B)")
        # X-Trans, linear (demosaiced) DNG, Foveon...: LibRaw's half-size output
        rgb = raw.postprocess(half_size=True, **post)
        est = _uint16_to_unit_float(rgb[..., :3])
        sat = (rgb[..., :3] >= math.ceil(SATURATION_FRACTION * 65535)).any(axis=-1)
        del rgb
        kind = "demosaiced (linear) DNG" if raw.raw_type != rawpy.RawType.Flat else "not a 2x2 Bayer sensor"
        warnings.append(f"{kind}: the estimation image is LibRaw's own half-size output (full size for "
                        "demosaiced data), clipped at 0, saturation judged after interpolation")

    if color_matrix is None:
        m = np.asarray(raw.rgb_xyz_matrix, dtype=np.float64)[:3]
        if m.shape == (3, 3) and np.all(np.isfinite(m)) and np.any(m):
            color_matrix = m
    neutral = None
    wb = np.asarray(raw.camera_whitebalance, dtype=np.float64)[:3]
    if np.all(np.isfinite(wb)) and np.all(wb > 0):
        neutral = (1.0 / wb) / (1.0 / wb[1])
    full_shape = _oriented_shape(int(s.height), int(s.width), flip, float(s.pixel_aspect))
    if abs(float(s.pixel_aspect) - 1.0) > 1e-6:
        warnings.append(f"non-square pixels (aspect {float(s.pixel_aspect):.4g}): the full-resolution image "
                        "is resampled by LibRaw, the estimation image is not")
    frac = float(sat.mean()) if sat.size else 0.0
    if frac > 0.01:
        warnings.append(f"{100 * frac:.1f} % of the image is saturated (those cells are flagged)")
    return DecodedImage(
        kind="raw", estimation=est, saturated=sat, full_shape=full_shape, make=make, model=model,
        color_matrix=None if color_matrix is None else np.array(color_matrix, dtype=np.float64),
        as_shot_neutral=neutral, black_level=float(np.mean(blacks)), white_level=white,
        warnings=warnings, _source=data, _postprocess=post,
    )


#: OpenCV conversion codes for each 2x2 Bayer cell (measured: a constant
#: colour mosaicked with each pattern comes back unchanged).
_OPENCV_BAYER = {"RGGB": "COLOR_BayerBG2RGB_EA", "BGGR": "COLOR_BayerRG2RGB_EA",
                 "GRBG": "COLOR_BayerGB2RGB_EA", "GBRG": "COLOR_BayerGR2RGB_EA"}

#: Demosaicking choices: ``fast`` (OpenCV's edge-aware bilinear on the
#: black-subtracted mosaic) or a LibRaw algorithm name.
DEMOSAIC_DEFAULT = "fast"


def _opencv_full_linear(img: DecodedImage) -> np.ndarray | None:
    """Full-resolution linear RGB by OpenCV's edge-aware Bayer interpolation.

    Each CFA site is scaled ``(d - b_c) / (w - b_c) * 65535`` (the
    estimation image's scale) into one uint16 mosaic, then demosaicked and
    oriented like LibRaw's output. ``None`` when the sensor is not a plain
    2x2 Bayer with square pixels (then LibRaw demosaics)."""
    import cv2
    import rawpy

    try:
        with rawpy.imread(io.BytesIO(img._source)) as raw:
            s = raw.sizes
            sites = _bayer_channels(raw, s)
            if sites is None or raw.raw_type != rawpy.RawType.Flat or abs(float(s.pixel_aspect) - 1) > 1e-6:
                return None
            flip = int(s.flip) if int(s.flip) in FLIP_OPS else 0
            blacks = [float(b) for b in raw.black_level_per_channel]
            white = float(raw.white_level)
            cfa = raw.raw_image_visible
            H, W = cfa.shape
            mos = np.empty((H, W), np.uint16)
            letters = [""] * 4
            rows = max(1, (1 << 18) // max(1, W))       # 1 MB of float32 per chunk and thread
            tasks = []
            for dy, dx, idx, ch in sites:
                letters[dy * 2 + dx] = "RGB"[ch]
                b = np.float32(blacks[idx])
                k = np.float32(65535.0 / (white - blacks[idx]))
                src, dst = cfa[dy::2, dx::2], mos[dy::2, dx::2]
                tasks += [(src, dst, b, k, r) for r in range(0, src.shape[0], rows)]

            def scale(task):
                src, dst, b, k, r = task
                a = src[r:r + rows].astype(np.float32)
                a -= b
                a *= k
                np.clip(a, 0, 65535, out=a)
                a += np.float32(0.5)
                dst[r:r + rows] = a

            # numpy releases the GIL on these arrays: the row chunks run on every core
            n_threads = min(4, os.cpu_count() or 1, max(1, cv2.getNumThreads()))   # 1 in a pool worker
            if n_threads > 1 and len(tasks) > 1:
                from concurrent.futures import ThreadPoolExecutor

                with ThreadPoolExecutor(n_threads) as pool:
                    list(pool.map(scale, tasks))
            else:
                for t in tasks:
                    scale(t)
            del cfa
    except rawpy.LibRawError as exc:
        raise ServiceError(422, "corrupt_file",
                          f"LibRaw failed to read the pixels ({type(exc).__name__}: {_librawmsg(exc)})") from None
    code = _OPENCV_BAYER.get("".join(letters))
    if code is None:
        return None
    rgb = cv2.cvtColor(mos, getattr(cv2, code))
    del mos
    if flip:
        rgb = np.ascontiguousarray(FLIP_OPS[flip](rgb))
    return rgb


def _raw_full_linear(img: DecodedImage, demosaic: str | None) -> np.ndarray:
    import rawpy

    demosaic = demosaic or DEMOSAIC_DEFAULT
    if str(demosaic).lower() == "fast":
        rgb = _opencv_full_linear(img)
        if rgb is not None:
            return rgb
        demosaic = "AHD"
        img.warnings.append("not a plain Bayer sensor: demosaicked by LibRaw (AHD) instead of the fast path")
    params = dict(img._postprocess)
    if demosaic is not None:
        try:
            params["demosaic_algorithm"] = rawpy.DemosaicAlgorithm[str(demosaic).upper()]
        except KeyError:
            names = [a.name for a in rawpy.DemosaicAlgorithm]
            raise ValueError(f"unknown demosaic algorithm {demosaic!r}; accepted: {names}") from None
    try:
        with rawpy.imread(io.BytesIO(img._source)) as raw:
            rgb = raw.postprocess(**params)
    except (rawpy.LibRawTooBigError, rawpy.LibRawUnsufficientMemoryError, MemoryError) as exc:
        raise ServiceError(413, "too_many_pixels", f"not enough memory to demosaic the image ({exc})") from None
    except rawpy.LibRawError as exc:
        raise ServiceError(422, "corrupt_file",
                          f"LibRaw failed to demosaic the file ({type(exc).__name__}: {_librawmsg(exc)})") from None
    if rgb.shape[2] != 3:
        rgb = np.ascontiguousarray(rgb[..., :3])
    if tuple(rgb.shape[:2]) != tuple(img.full_shape):
        img.warnings.append(f"LibRaw's full-resolution image is {rgb.shape[1]}x{rgb.shape[0]}, not the declared "
                            f"{img.full_shape[1]}x{img.full_shape[0]}")
        img.full_shape = tuple(int(v) for v in rgb.shape[:2])
    return rgb


# ---------------------------------------------------------------------------
# Linear TIFF and PNG
# ---------------------------------------------------------------------------

_LINEAR_NOTE = ("linear camera RGB assumed (black level 0, no camera metadata); gamma-encoded images "
                "give wrong estimates")
_NOT_LINEAR = ("8-bit images are gamma encoded (sRGB-like) and have lost the linear sensor data the "
               "analysis needs; send the camera RAW, or a linear 16-bit or float image")


#: Compressions of a linear TIFF decoded, each by a C decoder (zlib, or
#: imagecodecs for LZW and PackBits) straight into the image buffer: the
#: peak memory of a decode is the image plus one strip or tile, whatever
#: the file's size (tifffile's pure-Python PackBits decoder built a list of
#: ints per strip: 3 GB for a 5.6 MB file). Anything else is a 415.
LINEAR_TIFF_COMPRESSIONS = {1: "none", 5: "LZW", 8: "deflate", 32946: "deflate", 32773: "PackBits"}
#: Of those, the ones tifffile decodes in pure Python without imagecodecs.
_NEEDS_IMAGECODECS = (5, 32773)


def _check_linear_compression(page, label: str) -> None:
    """415 for a compression outside :data:`LINEAR_TIFF_COMPRESSIONS` (or
    one that would be decoded in pure Python, if imagecodecs is missing)."""
    comp = int(getattr(page, "compression", 1) or 1)
    accepted = ", ".join(sorted(set(LINEAR_TIFF_COMPRESSIONS.values())))
    ok = comp in LINEAR_TIFF_COMPRESSIONS
    if ok and comp in _NEEDS_IMAGECODECS:
        try:
            import imagecodecs  # noqa: F401
        except ImportError:
            ok = False
    if not ok:
        raise ServiceError(415, "unsupported_format",
                          f"{label}: TIFF compression {LINEAR_TIFF_COMPRESSIONS.get(comp, comp)!r} is not "
                          f"supported for linear images; send it uncompressed, or {accepted} compressed")


def _decode_tiff(data: bytes, filename: str | None, max_pixels: int) -> DecodedImage:
    import tifffile

    label = f"{filename!r}" if filename else "the upload"
    try:
        tf = tifffile.TiffFile(io.BytesIO(data))
    except Exception as exc:
        raise ServiceError(422, "corrupt_file",
                          f"{label} has a TIFF header but its structure cannot be read "
                          f"({type(exc).__name__}: {exc})") from None
    with tf:
        if not tf.pages:
            raise ServiceError(422, "corrupt_file", f"{label} is a TIFF without images")
        page = tf.pages[0]
        photometric = int(getattr(page, "photometric", 0) or 0)
        if _tag(page, 50706) is not None or photometric in (32803, 34892):
            shape = tuple(page.shape[:2])
            sane = len(shape) == 2 and all(isinstance(v, (int, np.integer)) and v > 0 for v in shape)
            if sane and int(shape[0]) * int(shape[1]) > max_pixels:
                # LibRaw refuses such headers outright; say why in the limit's terms
                raise ServiceError(413, "too_many_pixels",
                                  f"{label} declares {shape[1]}x{shape[0]} = {int(shape[0]) * int(shape[1]):,} "
                                  f"pixels; the limit is {max_pixels:,}")
            if sane and min(shape) < 22:
                raise ServiceError(415, "unsupported_format",
                                  f"{label} is a DNG/CFA image of {shape[1]}x{shape[0]} pixels; LibRaw "
                                  "refuses images under 22 pixels on a side")
            raise ServiceError(422, "corrupt_file",
                              f"{label} is a DNG (or CFA TIFF) that LibRaw cannot decode: damaged, or a "
                              "variant LibRaw does not support")
        axes = page.axes
        shape = page.shape
        dtype = np.dtype(page.dtype) if page.dtype is not None else None
        if "Y" not in axes or "X" not in axes or not all(int(v) > 0 for v in shape):
            raise ServiceError(422, "corrupt_file", f"{label}: TIFF without a readable image (shape {shape}, "
                              f"axes {axes!r})")
        h, w = shape[axes.index("Y")], shape[axes.index("X")]
        channels = shape[axes.index("S")] if "S" in axes else 1
        if dtype is None:
            raise ServiceError(415, "unsupported_format", f"{label}: TIFF sample format not supported")
        if dtype == np.uint8 or (dtype.kind == "u" and int(getattr(page, "bitspersample", 16)) <= 8):
            raise ServiceError(415, "not_linear", f"{label} is an 8-bit TIFF: {_NOT_LINEAR}")
        if not (dtype == np.uint16 or dtype.kind == "f"):
            raise ServiceError(415, "unsupported_format",
                              f"{label}: TIFF samples are {dtype}; need 16-bit unsigned integers or float32")
        if channels not in (3, 4) or axes.replace("S", "") != "YX":
            raise ServiceError(415, "unsupported_format",
                              f"{label}: TIFF with {channels} channel(s) (axes {axes!r}); need an H x W x 3 "
                              "linear RGB image")
        if h * w > max_pixels:
            raise ServiceError(413, "too_many_pixels",
                              f"{label} declares {w}x{h} = {h * w:,} pixels; the limit is {max_pixels:,}")
        size = len(data)
        for off, cnt in zip(page.dataoffsets or (), page.databytecounts or ()):
            if off + cnt > size:
                raise ServiceError(422, "corrupt_file",
                                  f"{label}: image data at bytes {off}..{off + cnt} lies beyond the end of the "
                                  f"{size}-byte file (truncated?)")
        _check_linear_compression(page, label)
        make, model = _ascii_tag(page, 271), _ascii_tag(page, 272)
        try:
            arr = page.asarray()
        except ValueError as exc:
            if "imagecodecs" in str(exc):
                raise ServiceError(415, "unsupported_format",
                                  f"{label}: TIFF compression {page.compression!r} is not supported; send it "
                                  "uncompressed, or deflate/LZW compressed") from None
            raise
    if "S" in axes and axes.index("S") == 0:
        arr = np.moveaxis(arr, 0, -1)
    warnings = [_LINEAR_NOTE]
    if channels == 4:
        arr = arr[..., :3]
        warnings.append("fourth (alpha) channel ignored")
    return _linear_image("tiff", arr, warnings, make, model)


def _png_chunks(data: bytes):
    """``(type, offset of data, length)`` of every chunk, checking lengths
    and CRCs; raises ``ServiceError(422)`` on damage."""
    pos, n = 8, len(data)
    seen_end = False
    while pos < n:
        if pos + 12 > n:
            raise ServiceError(422, "corrupt_file", "PNG truncated inside a chunk header")
        length, ctype = struct.unpack(">I4s", data[pos:pos + 8])
        end = pos + 12 + length
        if end > n:
            raise ServiceError(422, "corrupt_file",
                              f"PNG truncated: chunk {ctype!r} needs {length} bytes, the file ends first")
        crc = struct.unpack(">I", data[end - 4:end])[0]
        if zlib.crc32(data[pos + 4:end - 4]) & 0xFFFFFFFF != crc:
            raise ServiceError(422, "corrupt_file", f"PNG chunk {ctype!r} at byte {pos} fails its CRC (damaged)")
        yield ctype, pos + 8, length
        pos = end
        if ctype == b"IEND":
            seen_end = True
            break
    if not seen_end:
        raise ServiceError(422, "corrupt_file", "PNG truncated: no IEND chunk")


def _decode_png(data: bytes, max_pixels: int) -> DecodedImage:
    import cv2

    if len(data) < 33 or data[12:16] != b"IHDR":
        raise ServiceError(422, "corrupt_file", "PNG without a valid IHDR header")
    width, height, depth, ctype = struct.unpack(">IIBB", data[16:26])
    kinds = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}
    if ctype == 3 or depth <= 8:
        raise ServiceError(415, "not_linear", f"the PNG is {depth}-bit {kinds.get(ctype, '?')}: {_NOT_LINEAR}")
    if ctype not in (2, 6):
        raise ServiceError(415, "unsupported_format",
                          f"the PNG is {kinds.get(ctype, f'colour type {ctype}')}; need 16-bit RGB")
    if width * height > max_pixels:
        raise ServiceError(413, "too_many_pixels",
                          f"the PNG declares {width}x{height} = {width * height:,} pixels; the limit is "
                          f"{max_pixels:,}")
    warnings = [_LINEAR_NOTE]
    for ctype_, off, length in _png_chunks(data):
        if ctype_ == b"sRGB" or ctype_ == b"iCCP":
            warnings.append(f"the PNG carries an {ctype_.decode()} chunk (colour-managed, probably "
                            "gamma-encoded); it is treated as linear camera RGB")
        elif ctype_ == b"gAMA" and length == 4:
            gamma = struct.unpack(">I", data[off:off + 4])[0] / 100000.0
            if abs(gamma - 1.0) > 0.01:
                warnings.append(f"the PNG declares gamma {gamma:.4g} (encoded, not linear); it is treated "
                                "as linear camera RGB")
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise ServiceError(422, "corrupt_file", "OpenCV could not decode the PNG (damaged data)")
    if arr.dtype != np.uint16 or arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ServiceError(415, "unsupported_format",
                          f"the PNG decoded to {arr.dtype} {arr.shape}; need 16-bit RGB")
    if arr.shape[2] == 4:
        warnings.append("fourth (alpha) channel ignored")
    rgb = arr[..., 2::-1]          # BGR(A) -> RGB
    return _linear_image("png", rgb, warnings, None, None)


def _linear_image(kind: str, arr: np.ndarray, warnings: list, make, model) -> DecodedImage:
    h, w = arr.shape[:2]
    est = np.empty((h, w, 3), np.float32)
    sat = np.empty((h, w), bool)
    if arr.dtype == np.uint16:
        white = 65535.0
        inv = np.float32(1.0 / 65535.0)
        for r in range(0, h, 256):
            np.multiply(arr[r:r + 256], inv, out=est[r:r + 256], dtype=np.float32)
            sat[r:r + 256] = (arr[r:r + 256] == 65535).any(axis=-1)
    else:
        white = 1.0
        for r in range(0, h, 256):
            est[r:r + 256] = arr[r:r + 256]
        if not np.all(np.isfinite(est)):
            bad = int((~np.isfinite(est)).any(axis=-1).sum())
            raise ServiceError(422, "non_finite", f"the float image has {bad} pixel(s) with NaN or Inf")
        np.greater_equal(est, 1.0).any(axis=-1, out=sat)
    frac = float(sat.mean()) if sat.size else 0.0
    if frac > 0.01:
        warnings.append(f"{100 * frac:.1f} % of the image is saturated (those pixels are flagged)")
    return DecodedImage(kind=kind, estimation=est, saturated=sat, full_shape=(int(h), int(w)), make=make,
                        model=model, color_matrix=None, as_shot_neutral=None, black_level=0.0,
                        white_level=white, warnings=warnings)
