""":func:`decode_upload`: the bytes of an upload to a :class:`~service.decode.image.DecodedImage`,
or the 413/415/422 that says why not (the format from its bytes, the TIFF structure checked
before LibRaw reads it, then the RAW or linear decoder).
"""

from __future__ import annotations

import io

from ..errors import ServiceError
from .formats import _NOT_RAW, _extension, _sniff
from .image import RAW_EXTENSIONS
from .linear import _decode_png, _decode_tiff
from .raw import _decode_raw, _librawmsg, decode_linear_dng_without_libraw
from .structure import _check_tiff_structure, _tiff_structured
from .tags import _tiff_info


def decode_upload(data: bytes, filename: str | None, *, max_pixels: int,
                  estimation_pixels: int | None = None, display_referred: str = "linearise",
                  keep_mosaic: bool = False) -> DecodedImage:
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
    display_referred : {"linearise", "refuse"}
        A TIFF/PNG whose ICC profile (or PNG ``sRGB``/``gAMA``/``cICP``
        chunk) says its values are display-referred: decoded through its own
        tone curve, with a warning naming the profile, or refused
        (:mod:`service.decode.icc`).

    Returns
    -------
    DecodedImage

    Raises
    ------
    ServiceError
        422 ``empty_file``; 415 ``unsupported_format`` (JPEG, GIF, ...,
        anything LibRaw cannot read, grey or non-RGB images, unsupported
        sample types); 415 ``not_linear`` (8-bit TIFF/PNG, which are gamma
        encoded); 415 ``display_referred_input`` (a display-referred TIFF/PNG
        with ``display_referred="refuse"``, or one whose profile has no tone
        curves to linearise with); 422 ``corrupt_icc_profile``; 413 ``too_many_pixels``; 422 ``corrupt_file`` (truncated or
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
            return _decode_png(data, max_pixels, display_referred)
        if fmt in _NOT_RAW:
            named = (f" named {_extension(filename)}, but its content has no TIFF or RAW signature LibRaw "
                     "recognises" if _extension(filename) in RAW_EXTENSIONS else "")
            raise ServiceError(415, "unsupported_format",
                              f"{label} is a {fmt} file (detected from its content){named}; send a camera RAW (DNG, NEF, CR2, ARW, ...) or a "
                              "linear 16-bit/float TIFF or 16-bit PNG")
        return _decode_raw_or_tiff(data, fmt, filename, max_pixels, estimation_pixels, display_referred,
                                   keep_mosaic)
    except ServiceError:
        raise
    except MemoryError:
        raise ServiceError(413, "too_many_pixels",
                          f"not enough memory to decode {label}; send a smaller image") from None
    except Exception as exc:  # malformed data must never escape as a 500
        raise ServiceError(422, "corrupt_file",
                          f"{label} ({fmt}) could not be decoded: {type(exc).__name__}: {exc}") from None


def _decode_raw_or_tiff(data: bytes, fmt: str, filename: str | None, max_pixels: int,
                        estimation_pixels: int | None = None, display_referred: str = "linearise",
                        keep_mosaic: bool = False) -> DecodedImage:
    import rawpy

    label = f"{filename!r}" if filename else "the upload"
    try:
        raw = rawpy.imread(io.BytesIO(data))
    except rawpy.LibRawFileUnsupportedError:
        if fmt in ("TIFF", "BigTIFF"):
            got = decode_linear_dng_without_libraw(data, filename, max_pixels, estimation_pixels)
            if got is not None:       # a LinearRaw DNG LibRaw refuses (deflate 32946), read from its samples
                return got
            return _decode_tiff(data, filename, max_pixels, display_referred)
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
                return _decode_tiff(data, filename, max_pixels, display_referred)
        return _decode_raw(raw, data, fmt, filename, max_pixels, info, info_error, estimation_pixels,
                           keep_mosaic)
    except (rawpy.LibRawTooBigError, rawpy.LibRawUnsufficientMemoryError) as exc:
        raise ServiceError(413, "too_many_pixels", f"{label}: LibRaw refused the size ({exc})") from None
    except rawpy.LibRawError as exc:
        raise ServiceError(422, "corrupt_file",
                          f"{label}: LibRaw failed on the pixel data ({type(exc).__name__}: "
                          f"{_librawmsg(exc)}); the file is truncated or damaged") from None
    finally:
        raw.close()
