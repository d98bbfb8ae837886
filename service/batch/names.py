"""Safe names for the files of a batch: no directory part, no control characters, within the file
system's NAME_MAX, unique within a batch (case-insensitively)."""

from __future__ import annotations

import os
import re

__all__ = ["MAX_NAME_BYTES", "DISK_NAME_BYTES", "clip_name", "safe_name", "unique"]

#: Longest file name, in UTF-8 bytes, the batch endpoint accepts (the usual
#: file-system limit, NAME_MAX); longer ones are refused (422).
MAX_NAME_BYTES = 255
#: Longest name the service itself gives a file on disk (inputs, outputs):
#: room for the ``.<name>.XXXXXXXX.part`` temporaries and ``.json``/``.lock``
#: sidecars next to them within NAME_MAX.
DISK_NAME_BYTES = 200


def clip_name(name: str, limit: int = DISK_NAME_BYTES) -> str:
    """``name`` cut to at most ``limit`` UTF-8 bytes on a character boundary,
    keeping its extension (so the format is still recognised)."""
    if len(name.encode("utf-8")) <= limit:
        return name
    stem, ext = os.path.splitext(name)
    if len(ext.encode("utf-8")) > limit // 4:
        stem, ext = name, ""
    return stem.encode("utf-8")[:limit - len(ext.encode("utf-8"))].decode("utf-8", "ignore") + ext


def safe_name(name: str) -> str:
    """A file name with no directory part, no control characters and no
    unpaired surrogates, at most :data:`MAX_NAME_BYTES` bytes."""
    base = os.path.basename(str(name).replace("\\", "/")) or "file"
    base = base.encode("utf-8", "replace").decode("utf-8")
    base = re.sub(r"[\x00-\x1f/]", "_", base).strip() or "file"
    return clip_name(base, MAX_NAME_BYTES)


def unique(name: str, seen: set) -> str:
    """``name``, or ``stem (k).ext`` with the smallest free k."""
    cand, k = name, 2
    stem, ext = os.path.splitext(name)
    while cand.lower() in seen:
        cand = f"{stem} ({k}){ext}"
        k += 1
    seen.add(cand.lower())
    return cand
