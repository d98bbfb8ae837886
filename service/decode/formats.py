"""What an upload is, from its first bytes (:func:`_sniff`): a TIFF/DNG, a PNG, a RAW LibRaw may
read, or a format that is certainly not RAW (refused without asking LibRaw); the camera label
of a Make/Model pair.
"""

from __future__ import annotations

import os


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
