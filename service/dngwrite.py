"""A DNG of a colour-filter-array mosaic: the product's DNG writer.

A minimal, uncompressed, single-IFD CFA DNG (version 1.4) by the DNG
specification (Adobe, DNG Specification 1.4.0.0, 2012: chapter 4 and 5's
tags), written with tifffile. Two users:

* :func:`raw_as_dng` writes a camera RAW of another format (NEF, CR2, ARW,
  ...) as a DNG from LibRaw's own raw data (the CFA, black and white levels,
  the colour matrix, orientation, make and model), with the product's white
  balance inside (AsShotNeutral and the Camera Raw XMP packet): what
  Lightroom reads for a DNG (issue 30 item 3);
* :mod:`testing.dngwriter` makes the test and benchmark scenes with
  :func:`write_dng`.
"""

from __future__ import annotations

import os
from fractions import Fraction

import numpy as np

_TAG_MAKE, _TAG_MODEL, _TAG_ORIENTATION = 271, 272, 274
_TAG_CFA_REPEAT_PATTERN_DIM, _TAG_CFA_PATTERN = 33421, 33422
_TAG_DNG_VERSION, _TAG_DNG_BACKWARD_VERSION, _TAG_UNIQUE_CAMERA_MODEL = 50706, 50707, 50708
_TAG_CFA_PLANE_COLOR, _TAG_CFA_LAYOUT = 50710, 50711
_TAG_BLACK_LEVEL_REPEAT_DIM, _TAG_BLACK_LEVEL, _TAG_WHITE_LEVEL = 50713, 50714, 50717
_TAG_COLOR_MATRIX1, _TAG_AS_SHOT_NEUTRAL, _TAG_CALIBRATION_ILLUMINANT1 = 50721, 50728, 50778
_PHOTOMETRIC_CFA = 32803

_COLOUR_CODE = {"R": 0, "G": 1, "B": 2}
_TAG_XMP = 700
#: CIE XYZ of D50 (CIE 1931 2 degree, xy 0.3457, 0.3585; Y = 1): the white a ColorMatrix is normalised to
D50_XYZ = np.array([0.3457 / 0.3585, 1.0, (1 - 0.3457 - 0.3585) / 0.3585])


def cfa_colour_indices(pattern="RGGB") -> np.ndarray:
    """The 2x2 CFA repeat pattern as DNG colour codes (0 red, 1 green, 2 blue).

    Parameters
    ----------
    pattern : str or array_like
        Four letters from ``R``, ``G``, ``B`` read row by row (``"RGGB"``,
        ``"BGGR"``, ``"GRBG"``, ``"GBRG"``), or a 2x2 array of codes.

    Returns
    -------
    numpy.ndarray
        ``(2, 2)`` uint8, the CFAPattern tag of the file in row-major order.

    Examples
    --------
    >>> cfa_colour_indices("GRBG").tolist()
    [[1, 0], [2, 1]]
    """
    if isinstance(pattern, str):
        letters = pattern.strip().upper()
        if len(letters) != 4 or any(ch not in _COLOUR_CODE for ch in letters):
            raise ValueError(f"CFA pattern must be four letters from R, G, B, not {pattern!r}")
        codes = np.array([_COLOUR_CODE[ch] for ch in letters], dtype=np.uint8).reshape(2, 2)
    else:
        codes = np.asarray(pattern)
        if codes.shape != (2, 2) or not np.all(np.isin(codes, (0, 1, 2))):
            raise ValueError(f"CFA pattern must be a 2x2 array of 0, 1, 2, got {codes!r}")
        codes = codes.astype(np.uint8)
    if set(codes.ravel().tolist()) != {0, 1, 2}:
        raise ValueError(f"CFA pattern must contain red, green and blue, got {codes.tolist()}")
    return codes


def _pattern_letters(codes: np.ndarray) -> str:
    return "".join("RGB"[int(c)] for c in codes.ravel())


def _rational(value: float, signed: bool) -> tuple[int, int]:
    """``value`` as numerator/denominator fitting TIFF (S)RATIONAL (32 bits)."""
    v = float(value)
    if not np.isfinite(v):
        raise ValueError(f"cannot store {value!r} as a TIFF rational")
    top = 2**31 - 1 if signed else 2**32 - 1
    if signed is False and v < 0:
        raise ValueError(f"negative value {v} for an unsigned RATIONAL tag")
    max_den = max(1, min(2**30, int(top // max(abs(v), 1.0))))
    f = Fraction(v).limit_denominator(max_den)
    if abs(f.numerator) > top:
        raise ValueError(f"{v} is too large for a TIFF rational")
    return f.numerator, f.denominator


def _rationals(values, signed: bool) -> list[int]:
    out: list[int] = []
    for v in np.ravel(values):
        out.extend(_rational(v, signed))
    return out


def _ascii(name: str, value: str) -> str:
    try:
        value.encode("ascii")
    except UnicodeEncodeError as exc:
        raise ValueError(f"{name} must be ASCII, got {value!r}") from exc
    if "\x00" in value:
        raise ValueError(f"{name} must not contain NUL")
    return value


def _level_tag(code: int, values) -> tuple:
    """BlackLevel/WhiteLevel as LONG when integral, RATIONAL otherwise."""
    vals = np.asarray(values, dtype=np.float64).ravel()
    if np.all(vals == np.round(vals)) and np.all(vals >= 0) and np.all(vals < 2**32):
        return (code, "I", vals.size, [int(v) for v in vals], True)
    return (code, "2I", vals.size, _rationals(vals, signed=False), True)


def _srgb_color_matrix() -> np.ndarray:
    """XYZ -> linear sRGB (IEC 61966-2-1's matrix; camera space taken as
    sRGB), normalised as the DNG SDK's NormalizeColorMatrix does (D50 white
    -> camera max 1)."""
    m = np.linalg.inv(np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]]))
    return normalise_color_matrix(m)


def normalise_color_matrix(m) -> np.ndarray:
    """Scale an XYZ->camera matrix so the D50 white (Y = 1) maps to a camera
    vector whose largest entry is 1 (DNG SDK ``NormalizeColorMatrix``)."""
    m = np.asarray(m, float)
    top = float(np.max(m @ D50_XYZ))
    if not top > 0:
        raise ValueError("colour matrix maps the D50 white to no positive camera response")
    return m / top


def write_dng(
    path,
    cfa,
    *,
    pattern="RGGB",
    black_level=0,
    white_level=None,
    color_matrix1=None,
    calibration_illuminant1: int = 21,
    as_shot_neutral=None,
    make: str = "wandell-recovery",
    model: str = "synthetic CFA",
    unique_camera_model: str | None = None,
    bits: int = 16,
    extratags=(),
    orientation: int = 1,
    software: str = "wandell-recovery",
) -> None:
    """Write a minimal, uncompressed, single-IFD CFA DNG (version 1.4).

    Tags written: NewSubfileType 0, ImageWidth/Length, BitsPerSample,
    Compression 1, PhotometricInterpretation 32803 (CFA), one strip,
    Orientation 1, SamplesPerPixel 1, Make, Model, Software,
    CFARepeatPatternDim (2, 2), CFAPattern, DNGVersion 1.4.0.0,
    DNGBackwardVersion 1.1.0.0, UniqueCameraModel, CFAPlaneColor (0, 1, 2),
    CFALayout 1, BlackLevelRepeatDim, BlackLevel, WhiteLevel, ColorMatrix1,
    CalibrationIlluminant1 and, when given, AsShotNeutral.

    The pixels are written straight from ``cfa`` (no copy when it is already a
    C-contiguous unsigned integer array of the right width), so a 24-megapixel
    image costs little more than its own 48 MB.

    Parameters
    ----------
    path : str, os.PathLike or binary file object
        Destination.
    cfa : (H, W) array_like of int
        Raw digital numbers, ``0 <= cfa < 2**bits``. LibRaw refuses images
        narrower or shorter than 22 pixels (``LibRawFileUnsupportedError``);
        such files are written all the same, e.g. to test that refusal.
    pattern : str or array_like
        2x2 CFA pattern, see :func:`cfa_colour_indices`.
    black_level : float or array_like
        One value, or four (a 2x2 array or a sequence in row-major order of
        the CFA repeat) written with BlackLevelRepeatDim (2, 2).
    white_level : int, optional
        WhiteLevel; default ``2**bits - 1``.
    color_matrix1 : (3, 3) array_like, optional
        ColorMatrix1, XYZ -> camera (rows are camera channels R, G, B), stored
        as SRATIONAL. Default: XYZ -> linear sRGB, normalised as the DNG SDK
        does, i.e. a camera whose native space is linear sRGB.
    calibration_illuminant1 : int
        EXIF LightSource code of ColorMatrix1 (21 = D65, 17 = A, 23 = D50).
    as_shot_neutral : (3,) array_like, optional
        AsShotNeutral, the camera response to the scene's white (any scale;
        written as given, conventionally green = 1). Omitted when ``None``.
    make, model, unique_camera_model : str
        ASCII identification; UniqueCameraModel defaults to
        ``make + " " + model``.
    bits : {8, 16}
        BitsPerSample of the stored samples (uint8 or uint16).
    extratags : sequence of tifffile tag tuples
        ``(code, dtype, count, value, writeonce)`` added verbatim.
    orientation : int
        TIFF/EXIF Orientation (1 upright, 3 rotated 180, 6 and 8 rotated 90).
    software : str
        The Software tag.

    Raises
    ------
    ValueError
        On a malformed array, out-of-range values or inconsistent levels.

    Examples
    --------
    >>> import io, rawpy
    >>> buf = io.BytesIO()
    >>> write_dng(buf, np.full((24, 32), 700, np.uint16), black_level=64, white_level=4095)
    >>> with rawpy.imread(io.BytesIO(buf.getvalue())) as raw:
    ...     int(raw.raw_image[0, 0]), raw.black_level_per_channel, raw.white_level
    (700, [64, 64, 64, 64], 4095)
    """
    import tifffile

    if bits not in (8, 16):
        raise ValueError(f"bits must be 8 or 16, not {bits!r}")
    dtype = np.uint8 if bits == 8 else np.uint16
    maxval = 2**bits - 1

    arr = np.asarray(cfa)
    if arr.ndim != 2 or arr.shape[0] < 2 or arr.shape[1] < 2:
        raise ValueError(f"cfa must be a 2-D array of at least 2x2, got shape {arr.shape}")
    if arr.dtype != dtype:
        if arr.dtype.kind not in "ui" and not (arr.dtype.kind == "f" and np.all(arr == np.round(arr))):
            raise ValueError(f"cfa must hold integers, got dtype {arr.dtype}")
        lo, hi = arr.min(), arr.max()
        if lo < 0 or hi > maxval:
            raise ValueError(f"cfa values {lo}..{hi} do not fit {bits} bits")
        arr = arr.astype(dtype)
    arr = np.ascontiguousarray(arr)

    codes = cfa_colour_indices(pattern)

    white = maxval if white_level is None else white_level
    if not (0 < float(white) <= maxval):
        raise ValueError(f"white_level {white} must be in (0, {maxval}]")
    black = np.asarray(black_level, dtype=np.float64)
    if black.size == 1:
        black_vals, black_dim = black.reshape(1), (1, 1)
    elif black.size == 4:
        black_vals, black_dim = black.reshape(4), (2, 2)
    else:
        raise ValueError(f"black_level must be one value or four (2x2), got {black.shape}")
    if np.any(black_vals < 0) or np.any(black_vals >= float(white)):
        raise ValueError(f"black_level {black_vals.tolist()} must be in [0, white_level={white})")

    cm = _srgb_color_matrix() if color_matrix1 is None else np.asarray(color_matrix1, float)
    if cm.shape != (3, 3) or not np.all(np.isfinite(cm)):
        raise ValueError(f"color_matrix1 must be a finite 3x3 array, got {cm.shape}")
    if abs(np.linalg.det(cm)) < 1e-12:
        raise ValueError("color_matrix1 is singular")

    make = _ascii("make", str(make))
    model = _ascii("model", str(model))
    ucm = _ascii("unique_camera_model",
                 f"{make} {model}".strip() if unique_camera_model is None else str(unique_camera_model))

    tags = [
        (_TAG_MAKE, "s", 0, make, True),
        (_TAG_MODEL, "s", 0, model, True),
        (_TAG_ORIENTATION, "H", 1, int(orientation), True),
        (_TAG_CFA_REPEAT_PATTERN_DIM, "H", 2, (2, 2), True),
        (_TAG_CFA_PATTERN, "B", 4, tuple(int(c) for c in codes.ravel()), True),
        (_TAG_DNG_VERSION, "B", 4, (1, 4, 0, 0), True),
        (_TAG_DNG_BACKWARD_VERSION, "B", 4, (1, 1, 0, 0), True),
        (_TAG_UNIQUE_CAMERA_MODEL, "s", 0, ucm, True),
        (_TAG_CFA_PLANE_COLOR, "B", 3, (0, 1, 2), True),
        (_TAG_CFA_LAYOUT, "H", 1, 1, True),
        (_TAG_BLACK_LEVEL_REPEAT_DIM, "H", 2, black_dim, True),
        _level_tag(_TAG_BLACK_LEVEL, black_vals),
        _level_tag(_TAG_WHITE_LEVEL, [white]),
        (_TAG_COLOR_MATRIX1, "2i", 9, _rationals(cm, signed=True), True),
        (_TAG_CALIBRATION_ILLUMINANT1, "H", 1, int(calibration_illuminant1), True),
    ]
    if as_shot_neutral is not None:
        neutral = np.asarray(as_shot_neutral, dtype=np.float64).ravel()
        if neutral.size != 3 or not np.all(np.isfinite(neutral)) or np.any(neutral <= 0):
            raise ValueError(f"as_shot_neutral must be three positive numbers, got {as_shot_neutral!r}")
        tags.append((_TAG_AS_SHOT_NEUTRAL, "2I", 3, _rationals(neutral, signed=False), True))
    tags.extend(extratags)

    if isinstance(path, os.PathLike):
        path = os.fspath(path)
    tifffile.imwrite(
        path,
        arr,
        photometric=_PHOTOMETRIC_CFA,
        subfiletype=0,
        rowsperstrip=arr.shape[0],
        compression=None,
        metadata=None,
        software=software,
        extratags=tags,
    )




class NotConvertible(ValueError):
    """A file LibRaw reads whose raw data a CFA DNG cannot hold (no 2x2
    Bayer mosaic, no colour matrix), or not a RAW at all."""


#: LibRaw's ``flip`` -> TIFF/EXIF Orientation
_ORIENTATION = {0: 1, 3: 3, 5: 8, 6: 6}


def _tiff_make_model(data: bytes) -> tuple[str | None, str | None]:
    """Make and Model of a TIFF-based RAW's first IFD (NEF, CR2, ARW, PEF,
    ... are TIFF files), or ``(None, None)``."""
    from .decode.tiffbytes import tiff_file

    try:
        with tiff_file(data) as tf:
            tags = tf.pages[0].tags
            get = (lambda code: str(tags[code].value).strip("\x00 ") if code in tags else None)
            return get(_TAG_MAKE) or None, get(_TAG_MODEL) or None
    except Exception:  # noqa: BLE001 - not TIFF-based (CR3, RAF, ...): the tags are simply not known
        return None, None


def raw_as_dng(data: bytes, xmp: str, neutral, *, make: str | None = None, model: str | None = None,
               color_matrix=None) -> bytes:
    """A camera RAW of any format LibRaw reads, as a DNG of its own raw data
    with a white balance inside (issue 30 item 3: Lightroom reads a DNG's
    settings from inside the file).

    What is written (the DNG specification's tags, :func:`write_dng`): the
    visible area of LibRaw's raw mosaic (``raw_image_visible``, untouched),
    its 2x2 CFA pattern, the black level of each site and the white level,
    ``ColorMatrix1`` = LibRaw's XYZ -> camera matrix (the Adobe DNG
    Converter's D65 matrix, so ``CalibrationIlluminant1`` = 21, D65),
    ``Orientation`` from LibRaw's flip, ``Make``/``Model`` (given, else read
    from a TIFF-based RAW's first IFD), ``AsShotNeutral`` = ``neutral`` (the
    product's white in the camera's RGB) and the XMP packet ``xmp`` (tag 700:
    ``crs:WhiteBalance``, ``crs:Temperature``, ``crs:Tint``).

    Not carried: the masked margins and any lens, noise or opcode metadata;
    a Fuji X-Trans or other non-Bayer sensor, a demosaicked (LinearRaw) or
    monochrome file raises :class:`NotConvertible`.

    Parameters
    ----------
    data : bytes
        The RAW file.
    xmp : str
        The Camera Raw XMP packet (:func:`service.outputs.xmp_sidecar`).
    neutral : (3,) array_like
        The white's camera RGB (any scale; written green = 1).
    make, model : str, optional
    color_matrix : (3, 3) array_like, optional
        XYZ -> camera (D65); default LibRaw's (``rgb_xyz_matrix``).

    Returns
    -------
    bytes
        The DNG.
    """
    import io

    import rawpy

    try:
        raw = rawpy.imread(io.BytesIO(data))
    except Exception as e:  # noqa: BLE001 - LibRaw's errors: not a RAW it reads
        raise NotConvertible(f"LibRaw cannot read it ({type(e).__name__})") from None
    with raw:
        pat = None if raw.raw_pattern is None else np.asarray(raw.raw_pattern)
        if raw.raw_type != rawpy.RawType.Flat or pat is None or pat.shape != (2, 2) or int(raw.num_colors) < 3:
            raise NotConvertible("its sensor is not a 2x2 Bayer mosaic of red, green and blue")
        desc = raw.color_desc.decode("ascii", "replace")
        try:
            codes = np.array([[_COLOUR_CODE[desc[int(i)]] for i in row] for row in pat], np.uint8)
            codes = cfa_colour_indices(codes)
        except (KeyError, IndexError, ValueError):
            raise NotConvertible(f"its colour filters ({desc!r}) are not red, green and blue") from None
        cm = np.asarray(raw.rgb_xyz_matrix if color_matrix is None else color_matrix, float)[:3]
        if not (np.all(np.isfinite(cm)) and abs(np.linalg.det(cm)) > 1e-9):
            raise NotConvertible("LibRaw has no colour matrix for this camera")
        blacks = np.asarray(raw.black_level_per_channel, float)
        black = np.array([[blacks[int(i)] for i in row] for row in pat])
        cfa = np.array(raw.raw_image_visible, dtype=np.uint16, copy=True)
        white = int(raw.white_level)
        orientation = _ORIENTATION.get(int(raw.sizes.flip), 1)
    if make is None and model is None:
        make, model = _tiff_make_model(data)
    neutral = np.asarray(neutral, float).ravel()
    if neutral.size != 3 or not np.all(np.isfinite(neutral)) or np.any(neutral <= 0):
        raise ValueError(f"the white must be three positive numbers, got {neutral.tolist()}")

    def ascii_(s, default):
        s = "".join(ch for ch in str(s or "") if 32 <= ord(ch) < 127).strip()
        return s or default

    packet = xmp.encode("utf-8")
    buf = io.BytesIO()
    write_dng(buf, cfa, pattern=codes, black_level=black, white_level=white,
              color_matrix1=normalise_color_matrix(cm), calibration_illuminant1=21,
              as_shot_neutral=neutral / neutral[1], make=ascii_(make, "unknown"), model=ascii_(model, "unknown"),
              orientation=orientation, extratags=[(_TAG_XMP, "B", len(packet), packet, True)])
    return buf.getvalue()
