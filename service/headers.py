"""The one place a name goes into a response header: ``Content-Disposition``
(RFC 6266) with the name in ``filename*=UTF-8''...`` (RFC 8187, formerly
5987) and an ASCII fallback ``filename="..."`` for old clients.

Every download builds its header here (``format=xmp``, the corrected image,
``/v1/render``, batch items and zips), so an upload's name, whatever it holds
(characters outside Latin-1, ``"``, ``\\``, ``;``, NUL and other control
characters, bidi overrides), can neither fail the response nor add
parameters to the header.
"""

from __future__ import annotations

import unicodedata
from urllib.parse import quote

__all__ = ["content_disposition", "download_name", "ascii_name"]

#: Characters RFC 8187's ``attr-char`` allows unencoded, besides letters and digits.
_ATTR_CHARS = "!#$&+-.^_`|~"
#: Characters kept in the quoted ASCII fallback (a conservative set: no ``"``, ``\\``, ``;``, ``%``).
_FALLBACK_OK = frozenset("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789 ._-+()[],=@!#$&'~")
_MAX_CHARS = 200


def download_name(name: str | None, default: str = "download") -> str:
    """``name`` fit for a download: the last path component (``/`` and
    ``\\`` both separate), control and format characters (NUL, CR/LF, bidi
    overrides, zero-width marks) removed, white space runs to one space,
    at most 200 characters, the extension kept (a cut name lost it: a long
    RAW's sidecar downloaded as ``www...w``, no ``.xmp``: probe round 8);
    ``default`` when nothing is left.

    >>> download_name("w" * 300 + ".xmp")[-6:], len(download_name("w" * 300 + ".xmp"))
    ('ww.xmp', 200)
    """
    text = str(name or "").replace("\\", "/").rsplit("/", 1)[-1]
    text = "".join(c for c in text if unicodedata.category(c)[0] not in "CZ" or c == " ")
    text = " ".join(text.split()).strip(". ")
    if len(text) > _MAX_CHARS:
        stem, dot, ext = text.rpartition(".")
        keep = dot + ext if dot and 0 < len(ext) <= 10 and " " not in ext else ""
        text = text[:_MAX_CHARS - len(keep)].rstrip(". ") + keep
    return text or default


def ascii_name(name: str, default: str = "download") -> str:
    """An ASCII rendering of ``name`` for the quoted ``filename=``: accents
    dropped (NFKD), anything else outside a safe set as ``_``; the extension
    kept."""
    flat = unicodedata.normalize("NFKD", name).encode("ascii", "ignore").decode("ascii")
    out = "".join(c if c in _FALLBACK_OK else "_" for c in flat).strip(" ")
    stem, dot, ext = out.rpartition(".")
    if dot and not stem.strip("_ "):     # nothing but the extension survived
        out = f"{default}.{ext}"
    return out or default


def content_disposition(name: str | None, disposition: str = "attachment", default: str = "download") -> str:
    """The header value: ``attachment; filename="ascii"`` and, when the name
    is not plain ASCII, ``; filename*=UTF-8''percent-encoded``.

    >>> content_disposition("写真.xmp")
    'attachment; filename="download.xmp"; filename*=UTF-8\\'\\'%E5%86%99%E7%9C%9F.xmp'
    >>> content_disposition('a";x=".xmp', "inline")
    'inline; filename="a__x=_.xmp"; filename*=UTF-8\\'\\'a%22%3Bx%3D%22.xmp'
    """
    clean = download_name(name, default)
    fallback = ascii_name(clean, default)
    value = f'{disposition}; filename="{fallback}"'
    if fallback != clean:
        value += "; filename*=UTF-8''" + quote(clean, safe=_ATTR_CHARS)
    return value
