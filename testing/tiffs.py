"""Linear 16-bit RGB TIFFs built byte by byte (any compression code, strips
that all point at the same bytes): small files that declare many pixels, for
the decoding-memory tests and the fuzz run (issue 17, item 10; the layout of
``../shared/repro/round2/mem_packbits_tiff.py``)."""

from __future__ import annotations

import struct


def linear_tiff(h: int, w: int, comp: int, strip: bytes, rps: int) -> bytes:
    """A little-endian 16-bit RGB TIFF whose strips of ``rps`` rows all point
    at the same ``strip`` bytes."""
    n = -(-h // rps)
    bps = 8 + 2 + 10 * 12 + 4
    offs = bps + 8
    data = offs + (8 * n if n > 1 else 0)
    tags = [(256, 4, 1, w), (257, 4, 1, h), (258, 3, 3, bps), (259, 3, 1, comp), (262, 3, 1, 2),
            (273, 4, n, offs if n > 1 else data), (277, 3, 1, 3), (278, 4, 1, rps),
            (279, 4, n, offs + 4 * n if n > 1 else len(strip)), (284, 3, 1, 1)]
    ifd = struct.pack("<H", len(tags)) + b"".join(
        struct.pack("<HHII", t, ty, k, v) if ty == 4 or k > 1 else struct.pack("<HHIHH", t, ty, k, v, 0)
        for t, ty, k, v in tags) + b"\0\0\0\0"
    arrays = struct.pack(f"<{2 * n}I", *[data] * n, *[len(strip)] * n) if n > 1 else b""
    return b"II*\0" + struct.pack("<I", 8) + ifd + struct.pack("<HHH", 16, 16, 16) + b"\0\0" + arrays + strip
