"""TIFF/DNG tags read with tifffile: Make, Model, the colour matrices, the as-shot neutral and
the crop (:func:`_tiff_info`), file strings bounded and cleaned (:func:`file_string`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .tiffbytes import tiff_file


@dataclass
class _TiffInfo:
    make: str | None = None
    model: str | None = None
    color_matrix: np.ndarray | None = None
    is_dng: bool = False
    grey_guess: bool = False       # a plain grey TIFF LibRaw takes for an RGGB mosaic
    plain_multisample: bool = False  # a plain TIFF of 2+ samples LibRaw misreads as a mosaic
    problem: str | None = None     # strips/tiles beyond the end of the file
    as_shot_neutral: np.ndarray | None = None   # a DNG's AsShotNeutral tag as written (any values)
    # a DNG's AsShotWhiteXY (without AsShotNeutral) as a camera neutral (green 1) through its colour
    # matrices, or why it cannot be one (:func:`_white_xy_neutral`); None, None without the tag
    white_xy_neutral: np.ndarray | None = None
    white_xy_problem: str | None = None


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


def _white_xy_neutral(p0) -> tuple[np.ndarray | None, str | None]:
    """``(neutral with green 1, None)`` of a DNG whose IFD0 ``p0`` records
    its as-shot white as AsShotWhiteXY, not AsShotNeutral: the camera
    neutral of that chromaticity through the file's colour matrices
    (:func:`recovery.dng_color.xy_to_neutral`: DNG specification 1.6,
    "Mapping Camera Color Space to CIE XYZ Space", the matrix interpolated
    for the white's temperature; LibRaw puts the same numbers in its
    daylight multipliers, not its as-shot ones); ``(None, why)`` when it
    cannot be made (a damaged tag or colour matrix)."""
    from recovery.dng_color import xy_to_neutral

    from ..metadata import profile_problem, read_dng_profile

    v = np.asarray(_tag(p0, 50729), dtype=np.float64).ravel()
    if v.size == 4:                                         # numerator/denominator pairs
        with np.errstate(divide="ignore", invalid="ignore"):
            v = v[0::2] / v[1::2]
    shown = ", ".join(f"{x:.6g}" for x in v[:2])
    prof = read_dng_profile(p0)
    why = (None if v.size == 2 and prof is not None else
           "no 3x3 ColorMatrix1" if prof is None else "it is not two numbers")
    why = why or profile_problem(prof)
    if why is None:
        try:
            n = xy_to_neutral(prof, v)
        except ValueError as exc:
            why = str(exc)
        else:
            return n / n[1], None
    return None, (f"the file records an as-shot white (AsShotWhiteXY {shown}) that cannot be made a camera "
                  f"neutral: {why}")


def _tiff_info(data: bytes) -> _TiffInfo:
    """Make, Model, the XYZ -> camera matrix and the strip/tile check of a
    TIFF-structured file (IFD0 and SubIFDs of every page)."""
    info = _TiffInfo()
    size = len(data)
    with tiff_file(data) as tf:
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
        asn = _tag(p0, 50728)
        if asn is not None:
            v = np.asarray(asn, dtype=np.float64).ravel()
            if v.size == 6:                                  # numerator/denominator pairs
                with np.errstate(divide="ignore", invalid="ignore"):
                    v = v[0::2] / v[1::2]
            info.as_shot_neutral = v if v.size == 3 else np.full(3, np.nan)
        elif info.is_dng and _tag(p0, 50729) is not None:
            info.white_xy_neutral, info.white_xy_problem = _white_xy_neutral(p0)
        for page in _iter_ifds(tf.pages):
            offs = getattr(page, "dataoffsets", ()) or ()
            cnts = getattr(page, "databytecounts", ()) or ()
            for off, cnt in zip(offs, cnts):
                if off < 0 or cnt < 0 or off + cnt > size:
                    info.problem = (f"image data at bytes {off}..{off + cnt} lies beyond the end of the "
                                    f"{size}-byte file (truncated?)")
                    return info
    return info
