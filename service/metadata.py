"""Metadata read from the uploaded file's TIFF structure: the DNG colour
tags (for :mod:`recovery.dng_color`) and the EXIF facts copied to outputs.

Read lazily from :attr:`service.decode.image.DecodedImage._source` (the file's
bytes), once per decoded image, so decoding itself is unchanged.

References: Adobe, *Digital Negative (DNG) Specification* 1.4.0.0 (tags
50721-50730, 50778-50779, 50964-50965, 50719-50720); CIPA DC-008 (EXIF 2.3).
"""

from __future__ import annotations


import numpy as np

from recovery.dng_color import ColorProfile

from .decode.tiffbytes import tiff_file

__all__ = ["color_profile", "source_exif", "read_dng_profile", "profile_problem"]

_CACHE_ATTR = "_h13_meta"


def _values(v) -> np.ndarray | None:
    """Numbers of a (S)RATIONAL/SHORT/LONG/float tag as floats (pairs
    numerator, denominator for rationals, as tifffile gives them)."""
    if v is None:
        return None
    a = np.asarray(v, dtype=np.float64).ravel()
    return a


def _rational(v, n: int) -> np.ndarray | None:
    a = _values(v)
    if a is None:
        return None
    if a.size == 2 * n:
        num, den = a[0::2], a[1::2]
        if np.any(den == 0):
            return None
        a = num / den
    if a.size != n or not np.all(np.isfinite(a)):
        return None
    return a


def _matrix(v) -> np.ndarray | None:
    a = _rational(v, 9)
    if a is None or not np.any(a):
        return None
    return a.reshape(3, 3)


def read_dng_profile(page) -> ColorProfile | None:
    """The colour profile of a DNG's IFD0 (a ``tifffile`` page), ``None``
    when it has no ColorMatrix1 or a matrix is not 3x3 (not a 3-colour
    camera)."""
    tags = page.tags

    def get(code):
        t = tags.get(code)
        return None if t is None else t.value

    cm1 = _matrix(get(50721))
    if cm1 is None:
        return None
    ab = _rational(get(50727), 3)
    asn = _rational(get(50728), 3)
    asw = _rational(get(50729), 2)
    be = _rational(get(50730), 1)
    prof = ColorProfile(
        color_matrix1=cm1, color_matrix2=_matrix(get(50722)),
        forward_matrix1=_matrix(get(50964)), forward_matrix2=_matrix(get(50965)),
        camera_calibration1=_matrix(get(50723)), camera_calibration2=_matrix(get(50724)),
        analog_balance=ab if ab is not None and np.all(ab > 0) else None,
        illuminant1=_int(get(50778)), illuminant2=_int(get(50779)),
        baseline_exposure=float(be[0]) if be is not None else 0.0,
        as_shot_neutral=asn if asn is not None and np.all(asn > 0) else None,
        as_shot_white_xy=asw, source="DNG tags")
    origin, size = _rational(get(50719), 2), _rational(get(50720), 2)
    if origin is not None and size is not None and np.all(size > 0) and np.all(origin >= 0):
        # DefaultCropOrigin/Size are (horizontal, vertical) in the active area
        prof.default_crop = (int(round(origin[1])), int(round(origin[0])), int(round(size[1])),
                             int(round(size[0])))
    if get(50982) is not None or get(50938) is not None or get(50940) is not None:
        prof.notes.append("the DNG's HueSatMap/LookTable/ToneCurve are not applied (matrix rendering only)")
    return prof


#: A colour matrix the DNG pipeline inverts (NeutralToXY, the camera -> XYZ
#: matrix) is unusable when its condition number passes this: the inverse
#: would carry no correct digit (1 / float64 epsilon is 4.5e15; 1e12 leaves
#: three digits of margin, far beyond any real camera's matrix, ~10-100).
MAX_MATRIX_CONDITION = 1e12


def profile_problem(prof: ColorProfile) -> str | None:
    """What makes ``prof`` unusable, naming the tag, or ``None``: each colour
    matrix the DNG SDK inverts (``AnalogBalance * CameraCalibrationN *
    ColorMatrixN``, DNG specification 1.4, chapter 6) must be invertible.
    A singular (not all-zero) ColorMatrix1 or CameraCalibration1 made
    ``np.linalg.solve`` fail in :func:`recovery.dng_color.neutral_to_xy`
    (a 500, issue 28)."""
    def bad(m) -> bool:
        if m is None:
            return False
        with np.errstate(all="ignore"):
            c = np.linalg.cond(np.asarray(m, float))
        return not np.isfinite(c) or c > MAX_MATRIX_CONDITION

    ab = np.diag(prof.analog_balance) if prof.analog_balance is not None else np.eye(3)
    used = [(1, prof.color_matrix1, prof.camera_calibration1)]
    if prof.color_matrix2 is not None:
        used.append((2, prof.color_matrix2, prof.camera_calibration2))
    for k, cm, cc in used:
        for name, m in ((f"ColorMatrix{k}", cm), (f"CameraCalibration{k}", cc)):
            if bad(m):
                return (f"the DNG's {name} is singular (condition number above {MAX_MATRIX_CONDITION:.0e}): the "
                        "camera's colours cannot be converted; the file's colour tags are damaged")
        if bad(ab @ (cc if cc is not None else np.eye(3)) @ cm):
            return (f"the DNG's AnalogBalance x CameraCalibration{k} x ColorMatrix{k} is singular: the camera's "
                    "colours cannot be converted; the file's colour tags are damaged")
    return None


def _int(v):
    try:
        return int(np.asarray(v).ravel()[0])
    except (TypeError, ValueError, IndexError):
        return None


def _tiff_pages(decoded):
    data = getattr(decoded, "_source", None)
    if not data or bytes(data[:2]) not in (b"II", b"MM"):
        return None

    return tiff_file(data)


def _meta(decoded) -> dict:
    """Parse once per decoded image: ``{"profile": ColorProfile|None, "exif": dict}``."""
    cached = getattr(decoded, _CACHE_ATTR, None)
    if cached is not None:
        return cached
    meta: dict = {"profile": None, "exif": {}}
    try:
        tf = _tiff_pages(decoded)
    except Exception:  # noqa: BLE001 - LibRaw read the file; tags are a bonus
        tf = None
    if tf is not None:
        try:
            with tf:
                p0 = tf.pages.first if hasattr(tf.pages, "first") else tf.pages[0]
                if p0.tags.get(50706) is not None:
                    meta["profile"] = read_dng_profile(p0)
                    if meta["profile"] is not None:
                        meta["problem"] = profile_problem(meta["profile"])
                meta["exif"] = _exif_of(tf, p0)
        except Exception:  # noqa: BLE001
            pass
    if meta.get("problem"):
        meta["profile"] = None
    elif meta["profile"] is None and getattr(decoded, "kind", None) == "raw" and decoded.color_matrix is not None:
        cm = np.asarray(decoded.color_matrix, float)
        if cm.shape == (3, 3) and np.all(np.isfinite(cm)) and abs(np.linalg.det(cm)) > 1e-12:
            meta["profile"] = ColorProfile.from_matrix(cm, "LibRaw")
    if getattr(decoded, "make", None) and "Make" not in meta["exif"]:
        meta["exif"]["Make"] = decoded.make
    if getattr(decoded, "model", None) and "Model" not in meta["exif"]:
        meta["exif"]["Model"] = decoded.model
    try:
        setattr(decoded, _CACHE_ATTR, meta)
    except AttributeError:
        pass
    return meta


def color_profile(decoded) -> ColorProfile | None:
    """The camera->XYZ profile of a decoded RAW: the DNG's colour tags, or
    LibRaw's XYZ(D65)->camera matrix for other RAWs; ``None`` for TIFF/PNG
    input and cameras LibRaw has no matrix for.

    Raises a 422 ``bad_color_matrix`` naming the tag when a colour matrix
    of the DNG is singular (:func:`profile_problem`)."""
    if getattr(decoded, "kind", None) != "raw":
        return None
    meta = _meta(decoded)
    if meta.get("problem"):
        from .errors import ServiceError

        raise ServiceError(422, "bad_color_matrix", meta["problem"])
    return meta["profile"]


#: EXIF facts copied to outputs: name -> (tag code, in the EXIF sub-IFD?)
EXIF_TAGS = {
    "Make": 271, "Model": 272, "DateTime": 306, "Artist": 315, "Copyright": 33432,
    "ExposureTime": 33434, "FNumber": 33437, "ISOSpeedRatings": 34855, "DateTimeOriginal": 36867,
    "ExposureBiasValue": 37380, "FocalLength": 37386, "LensModel": 42036, "LensMake": 42035,
    "BodySerialNumber": 42033, "ImageDescription": 270,
}


def _exif_of(tf, p0) -> dict:
    """The facts of :data:`EXIF_TAGS` from IFD0 and its EXIF sub-IFD (as
    Python numbers/strings; rationals as (numerator, denominator))."""
    out: dict = {}
    sources = [p0.tags]
    exif = p0.tags.get(34665)
    if exif is not None and isinstance(exif.value, dict):
        sources.append(exif.value)
    names = {v: k for k, v in EXIF_TAGS.items()}
    for src in sources:
        for code, name in names.items():
            if name in out:
                continue
            if hasattr(src, "get") and not isinstance(src, dict):
                t = src.get(code)
                val = None if t is None else t.value
            else:
                val = src.get(name, src.get(code))
            if val is None:
                continue
            if isinstance(val, bytes):      # UTF-8 as most editors write it, else Latin-1
                try:
                    val = val.decode("utf-8")
                except UnicodeDecodeError:
                    val = val.decode("latin-1")
            if isinstance(val, str):
                val = val.replace("\x00", " ").strip()
                if not val:
                    continue
            elif isinstance(val, tuple) and len(val) == 1:
                val = val[0]
            out[name] = val
    return out


def source_exif(decoded) -> dict:
    """EXIF facts of the source (Make, Model, dates, exposure...) for the
    outputs; empty for files without a TIFF structure."""
    if getattr(decoded, "kind", None) != "raw":
        return {}
    return dict(_meta(decoded)["exif"])
