"""Linear 16-bit TIFF and PNG uploads (camera RGB with black level 0): TIFFs decoded by C
decoders only (:data:`LINEAR_TIFF_COMPRESSIONS`), PNG chunks read for their bit depth and
colour type, 8-bit (gamma-encoded) images refused. A 16-bit or float image whose ICC profile
(or PNG ``sRGB``/``gAMA``/``cICP`` chunk) says it is display-referred is linearised through its
own tone curve, or refused, by the ``display_referred`` policy (:mod:`service.decode.icc`).
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

from ..errors import ServiceError
from .icc import Encoding, display_referred_policy, linearise, png_encoding, tiff_encoding
from .image import FLIP_OPS, DecodedImage
from .tags import _ascii_tag, _tag
from .tiffbytes import tiff_file


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
#: PhotometricInterpretation of a linear TIFF: BlackIsZero (samples as they are) or RGB. The
#: others' samples are not camera R, G, B: refused, not read as RGB (CMYK's K as an alpha).
_LINEAR_PHOTOMETRICS = (1, 2)
_PHOTOMETRIC_NAMES = {0: "WhiteIsZero", 3: "palette", 4: "transparency mask", 5: "CMYK (separated)",
                      6: "YCbCr", 8: "CIELab", 9: "ICCLab", 10: "ITULab", 32844: "LogL", 32845: "LogLuv"}


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


def _decode_tiff(data: bytes, filename: str | None, max_pixels: int,
                 display_referred: str = "linearise") -> DecodedImage:

    label = f"{filename!r}" if filename else "the upload"
    try:
        tf = tiff_file(data)
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
        page, page_note = _full_resolution_page(tf, page)
        photometric = int(getattr(page, "photometric", 0) or 0)
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
        if photometric not in _LINEAR_PHOTOMETRICS and _tag(page, 262) is not None:
            # CMYK, CIELab, YCbCr...: 3 or 4 samples that are not R, G, B (and alpha) (probe round 9)
            raise ServiceError(415, "unsupported_format",
                              f"{label} is a {_PHOTOMETRIC_NAMES.get(photometric, 'non-RGB')} TIFF "
                              f"(PhotometricInterpretation {photometric}); need an H x W x 3 linear RGB image")
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
        orientation = _tag(page, 274)
        orientation = int(orientation) if isinstance(orientation, (int, np.integer)) and 1 <= orientation <= 8 else 1
        enc = tiff_encoding(page)
        enc_warnings = display_referred_policy(enc, display_referred, label)   # before the pixels
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
    arr, flip = _oriented(arr, orientation)
    warnings = _encoding_notes(enc, enc_warnings) + ([page_note] if page_note else [])
    if photometric == 1 and _tag(page, 262) is not None:
        # kept (scientific files are RGB in all but the tag), but not silently (probe round 9c)
        warnings.append(f"the TIFF's PhotometricInterpretation says grey (BlackIsZero) but it has {channels} "
                        "samples a pixel: they were read as three channels of camera RGB")
    if channels == 4:
        arr = arr[..., :3]
        warnings.append("fourth (alpha) channel ignored")
    decoded = _linear_image("tiff", arr, warnings, make, model, enc)
    if flip:
        decoded._postprocess = {"user_flip": flip}     # the flip applied, as for a RAW (Photo.orientation)
    return decoded


def _oriented(arr: np.ndarray, orientation: int) -> tuple[np.ndarray, int]:
    """``arr`` as viewers show it by its TIFF/EXIF Orientation (1..8), turned as LibRaw
    orients a RAW (probe round 9), and the flip applied (LibRaw's code, 0 for none: what
    ``_postprocess["user_flip"]`` and ``Photo.orientation`` say)."""
    if orientation == 1:
        return arr, 0
    from .raw import _ORIENTATION_FLIP

    flip = _ORIENTATION_FLIP[orientation]
    return FLIP_OPS[flip](arr), flip


#: Pages of a multi-page linear TIFF looked at for the full-resolution image (a hostile file may
#: chain millions of tiny IFDs).
_PAGES_LOOKED_AT = 16


def _reduced(page) -> bool:
    """Whether a TIFF page is a reduced-resolution copy (NewSubfileType bit 0: a thumbnail)."""
    return bool(int(getattr(page, "subfiletype", 0) or 0) & 1)


def _full_resolution_page(tf, first):
    """The page a linear TIFF is read from, and a note when the file holds
    more than one image: the first one of the first :data:`_PAGES_LOOKED_AT`
    that is not a reduced-resolution copy (a file may start with its
    thumbnail; the whole file was analysed and written at the thumbnail's
    size before probe round 9)."""
    pages = [first]
    for i in range(1, _PAGES_LOOKED_AT + 1):
        try:
            pages.append(tf.pages[i])
        except Exception:     # no more pages (IndexError), or one tifffile cannot read: not looked at
            break
    if len(pages) < 2:
        return first, None
    index, page = next(((i, p) for i, p in enumerate(pages[:_PAGES_LOOKED_AT]) if not _reduced(p)), (0, first))
    shape = getattr(page, "shape", ())
    size = f"{shape[1]}x{shape[0]} pixels" if len(shape) >= 2 and str(page.axes)[:2] == "YX" else "its size"
    count = f"more than {_PAGES_LOOKED_AT}" if len(pages) > _PAGES_LOOKED_AT else str(len(pages))
    return page, (f"the TIFF holds {count} images; image {index + 1} ({size}) is analysed, the others are "
                  "ignored" + (" (image 1 is a reduced-resolution copy)" if index else ""))


def _encoding_notes(enc: Encoding | None, enc_warnings: list) -> list:
    """The decode's first warnings: linear camera RGB assumed (no colour tags), said by
    the profile, or linearised from a display-referred encoding."""
    if enc is None:
        return [_LINEAR_NOTE]
    if enc.linear:
        return [f"linear RGB by its {enc.source} {enc.name!r}, taken as camera RGB (black level 0, no camera "
                "metadata)"]
    return list(enc_warnings)


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


def _decode_png(data: bytes, max_pixels: int, display_referred: str = "linearise") -> DecodedImage:
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
    colour, exif = {}, None
    for ctype_, off, length in _png_chunks(data):
        if ctype_ in (b"cICP", b"iCCP", b"sRGB", b"gAMA") and ctype_ not in colour:
            colour[ctype_] = data[off:off + length]
        elif ctype_ == b"eXIf" and exif is None:
            exif = data[off:off + length]
    enc = png_encoding(colour)
    warnings = _encoding_notes(enc, display_referred_policy(enc, display_referred, "the PNG"))
    orientation, exif_note = _png_orientation(exif)
    if exif_note:
        warnings.append(exif_note)
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise ServiceError(422, "corrupt_file", "OpenCV could not decode the PNG (damaged data)")
    if arr.dtype != np.uint16 or arr.ndim != 3 or arr.shape[2] not in (3, 4):
        raise ServiceError(415, "unsupported_format",
                          f"the PNG decoded to {arr.dtype} {arr.shape}; need 16-bit RGB")
    if arr.shape[2] == 4:
        warnings.append("fourth (alpha) channel ignored")
    rgb, flip = _oriented(arr[..., 2::-1], orientation)         # BGR(A) -> RGB, upright as a TIFF's
    decoded = _linear_image("png", rgb, warnings, None, None, enc)
    if flip:
        decoded._postprocess = {"user_flip": flip}     # the flip applied, as for a RAW (Photo.orientation)
    return decoded


def _png_orientation(exif: bytes | None) -> tuple[int, str | None]:
    """The Orientation (1..8) of a PNG's ``eXIf`` chunk (EXIF in TIFF layout, read by
    Pillow), and a note when the chunk cannot be read (its orientation then ignored).
    OpenCV decodes the pixels as stored: before probe round 9c a portrait PNG was
    analysed and written on its side."""
    if not exif:
        return 1, None
    from PIL import Image

    try:
        tags = Image.Exif()
        tags.load(exif)
        value = tags.get(274, 1)
    except Exception as exc:     # Pillow raises SyntaxError, struct.error, ValueError... on damage
        return 1, (f"the PNG's eXIf chunk cannot be read ({type(exc).__name__}); its orientation, if any, "
                   "is ignored (the pixels are used as stored)")
    return (int(value) if isinstance(value, int) and 1 <= value <= 8 else 1), None


def _linear_image(kind: str, arr: np.ndarray, warnings: list, make, model,
                  enc: Encoding | None = None) -> DecodedImage:
    """The decoded image of linear (or, by ``enc``, linearised) RGB code values;
    saturation is read from the code values (65535, or 1.0 for floats)."""
    h, w = arr.shape[:2]
    est = np.empty((h, w, 3), np.float32)
    sat = np.empty((h, w), bool)
    convert = enc is not None and not enc.linear
    if arr.dtype == np.uint16:
        white = 65535.0
        inv = np.float32(1.0 / 65535.0)
        for r in range(0, h, 256):
            if not convert:
                np.multiply(arr[r:r + 256], inv, out=est[r:r + 256], dtype=np.float32)
            sat[r:r + 256] = (arr[r:r + 256] == 65535).any(axis=-1)
    else:
        white = 1.0
        if not np.all(np.isfinite(arr)):
            bad = int((~np.isfinite(arr)).any(axis=-1).sum())
            raise ServiceError(422, "non_finite", f"the float image has {bad} pixel(s) with NaN or Inf")
        for r in range(0, h, 256):
            np.greater_equal(arr[r:r + 256], 1.0).any(axis=-1, out=sat[r:r + 256])
            if not convert:
                est[r:r + 256] = arr[r:r + 256]
        if not convert and not np.all(np.isfinite(est)):      # float64 beyond float32's range
            bad = int((~np.isfinite(est)).any(axis=-1).sum())
            raise ServiceError(422, "non_finite", f"the float image has {bad} pixel(s) with NaN or Inf")
    if convert:
        linearise(arr, enc, est)
    frac = float(sat.mean()) if sat.size else 0.0
    if frac > 0.01:
        warnings.append(f"{100 * frac:.1f} % of the image is saturated (those pixels are flagged)")
    cm = enc.xyz_to_rgb() if enc is not None else None
    return DecodedImage(kind=kind, estimation=est, saturated=sat, full_shape=(int(h), int(w)), make=make,
                        model=model, color_matrix=cm, as_shot_neutral=None, black_level=0.0,
                        white_level=white, warnings=warnings,
                        encoding=enc.describe() if enc is not None else None)
