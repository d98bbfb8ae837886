"""A copy of a DNG carrying the product's white balance (issue 30).

Lightroom and Camera Raw read the settings of a DNG from the XMP packet
inside it (TIFF tag 700), not from a sidecar beside it. :func:`dng_with_white`
returns the bytes of a copy of a DNG whose first IFD holds

* ``XMP`` (700): the same Camera Raw settings packet as the sidecar
  (``crs:WhiteBalance="Custom"``, ``crs:Temperature``, ``crs:Tint``; type BYTE,
  :func:`service.outputs.xmp_sidecar`), replacing any packet there;
* ``AsShotNeutral`` (50728): the estimated light's camera RGB, green 1 (the
  DNG specification's camera neutral), replacing the file's; an
  ``AsShotWhiteXY`` (50729) is dropped, the two being exclusive.

Nothing of the original is moved or rewritten: the new IFD 0 (its other
entries copied as they are, their values still where they were) and the new
values are appended after the file's last byte and the header points at
them; the old IFD 0 stays as unreferenced bytes. So the raw data, the
sub-IFDs and every offset in the file are untouched, and the copy's raw
image is the original's bit for bit (a test reads both with LibRaw).

References
----------
Adobe, *Digital Negative (DNG) Specification* 1.4.0.0 (2012): AsShotNeutral,
AsShotWhiteXY (chapter 4), the XMP packet in IFD 0.
Adobe, *XMP Specification* Part 3 (2016), 1.1.4: XMP in TIFF, tag 700, type
BYTE or UNDEFINED. Adobe Camera Raw settings namespace
``http://ns.adobe.com/camera-raw-settings/1.0/`` (``crs:``).
TIFF 6.0 (1992), section 2: header, IFDs, word alignment of offsets.
"""

from __future__ import annotations

import struct

import numpy as np

XMP_TAG = 700
AS_SHOT_NEUTRAL = 50728
AS_SHOT_WHITE_XY = 50729
_TYPE_SIZES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 13: 4}


class NotADng(ValueError):
    """The bytes are not a classic TIFF whose IFD 0 carries DNGVersion."""


def _rationals(values) -> bytes:
    out = []
    for v in values:
        v = float(v)
        if not np.isfinite(v) or v <= 0:
            raise ValueError(f"AsShotNeutral must be finite and positive, not {v!r}")
        den = 1_000_000
        num = int(round(v * den))
        while num >= 2 ** 32:
            den //= 10
            num = int(round(v * den))
        out.append((num, den))
    return b"".join(struct.pack("<II", n, d) for n, d in out)


def dng_with_white(data: bytes, xmp: str, neutral) -> bytes:
    """A copy of the DNG ``data`` with the XMP packet ``xmp`` and
    AsShotNeutral ``neutral`` (camera RGB of the light, any scale: written
    with green 1) in its IFD 0 (see the module's docstring).

    Raises
    ------
    NotADng
        Not a little- or big-endian classic TIFF with DNGVersion in IFD 0
        (BigTIFF is not a DNG).
    """
    if len(data) < 8 or data[:4] not in (b"II*\x00", b"MM\x00*"):
        raise NotADng("not a TIFF-based file (a DNG starts II*\\0 or MM\\0*)")
    e = "<" if data[:2] == b"II" else ">"
    (ifd0,) = struct.unpack(e + "I", data[4:8])
    if ifd0 + 2 > len(data) or ifd0 < 8:
        raise NotADng("its first IFD lies outside the file")
    (n,) = struct.unpack(e + "H", data[ifd0:ifd0 + 2])
    end = ifd0 + 2 + 12 * n
    if end + 4 > len(data):
        raise NotADng("its first IFD runs past the end of the file")
    entries = {}
    for k in range(n):
        raw = data[ifd0 + 2 + 12 * k: ifd0 + 14 + 12 * k]
        tag, typ, count = struct.unpack(e + "HHI", raw[:8])
        entries[tag] = (typ, count, raw[8:12])
    if 50706 not in entries:
        raise NotADng("no DNGVersion tag: not a DNG")
    (next_ifd,) = struct.unpack(e + "I", data[end:end + 4])

    g = np.asarray(neutral, float)
    g = g / g[1]
    packet = xmp.encode("utf-8")
    rat = _rationals(g)
    if e == ">":                                      # the rationals in the file's byte order
        rat = b"".join(struct.pack(">II", *struct.unpack("<II", rat[i:i + 8])) for i in range(0, len(rat), 8))

    out = bytearray(data)
    if len(out) % 2:
        out += b"\x00"                                # TIFF: values start on a word boundary
    xmp_at = len(out)
    out += packet
    if len(out) % 2:
        out += b"\x00"
    neutral_at = len(out)
    out += rat
    for t in (XMP_TAG, AS_SHOT_NEUTRAL, AS_SHOT_WHITE_XY):
        entries.pop(t, None)
    entries[XMP_TAG] = (1, len(packet), struct.pack(e + "I", xmp_at))    # BYTE, as exiftool and the DNG SDK expect
    entries[AS_SHOT_NEUTRAL] = (5, 3, struct.pack(e + "I", neutral_at))
    new_ifd = len(out)
    out += struct.pack(e + "H", len(entries))
    for tag in sorted(entries):                        # TIFF: entries in ascending tag order
        typ, count, value = entries[tag]
        out += struct.pack(e + "HHI", tag, typ, count) + value
    out += struct.pack(e + "I", next_ifd)
    out[4:8] = struct.pack(e + "I", new_ifd)
    return bytes(out)


def is_dng(data: bytes) -> bool:
    """Whether ``data`` is a DNG this module can copy (:func:`dng_with_white`)."""
    try:
        _check(data)
    except NotADng:
        return False
    return True


def _check(data: bytes) -> None:
    """Raise :class:`NotADng` unless IFD 0 of a classic TIFF holds DNGVersion."""
    if len(data) < 8 or data[:4] not in (b"II*\x00", b"MM\x00*"):
        raise NotADng("not a TIFF")
    e = "<" if data[:2] == b"II" else ">"
    (ifd0,) = struct.unpack(e + "I", data[4:8])
    if ifd0 < 8 or ifd0 + 2 > len(data):
        raise NotADng("bad IFD 0")
    (n,) = struct.unpack(e + "H", data[ifd0:ifd0 + 2])
    if ifd0 + 2 + 12 * n > len(data):
        raise NotADng("bad IFD 0")
    for k in range(n):
        (tag,) = struct.unpack(e + "H", data[ifd0 + 2 + 12 * k: ifd0 + 4 + 12 * k])
        if tag == 50706:
            return
    raise NotADng("no DNGVersion")
