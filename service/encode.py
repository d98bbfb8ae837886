"""Image encoders that use every core (issue 19): :func:`png_encode` and
:func:`jpeg_encode`.

:func:`png_encode` writes a PNG (8- or 16-bit RGB) whose compressed stream
is made in horizontal strips on a thread pool, as pigz does for gzip: each
strip's rows are filtered (PNG filter type 1, *Sub*, computed with numpy)
and deflated by its own compressor (zlib-ng when installed, else zlib;
:data:`PNG_STRATEGY`), ended with a sync flush (an empty stored block, so
the next strip starts on a byte boundary) and the last one with the final
block. The concatenation is one valid deflate stream (no
strip refers back into another), wrapped in the zlib header and the Adler-32
of all the filtered bytes, combined from the strips' own (zlib's
``adler32_combine``). Each strip is one IDAT chunk. numpy, the compressor
and the checksums release the GIL, so the strips run in parallel.

The pixels decoded from the file are exactly the input (PNG is lossless);
only the bytes differ from a one-thread encoder's. One strip per thread
would leave a core idle at the end when strips take unequal times, so
there are a few per thread; each restarts the compressor's window, which
costs a fraction of a percent of the size at these strip heights.
"""

from __future__ import annotations

import math
import os
import struct
import zlib

import numpy as np

try:        # zlib-ng: the same deflate format, its Huffman-only and RLE coders about 2x zlib's speed
    from zlib_ng import zlib_ng as _deflate
except ImportError:     # pragma: no cover - a dependency; stdlib zlib gives the same pixels, slower
    _deflate = zlib

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_ADLER_BASE = 65521
#: zlib level and strategy of the strips. Huffman coding only
#: (``Z_HUFFMAN_ONLY``) on Sub-filtered rows of a photograph: sensor noise
#: leaves few repeated strings, and the ones Run-length matches (``Z_RLE``)
#: find cost more than they save (the real CinemaDNG's 8-bit sRGB output:
#: 10.64 MB against RLE's 10.72 MB and OpenCV level 1's 12.9 MB; the
#: 24-megapixel bench DNG's 22.26 MB against 22.79 MB) while taking 0.8x
#: RLE's time with stdlib zlib and 0.65x with zlib-ng (issue 19: the PNG
#: encode was 0.66 s of a 1.7 s request). A strip that is mostly zero
#: differences (flat graphics, not a photograph: :data:`PNG_FLAT_ZEROS`)
#: keeps ``Z_RLE``, which collapses the runs Huffman coding cannot go below
#: one bit a byte for.
PNG_LEVEL = 1
PNG_STRATEGY = zlib.Z_HUFFMAN_ONLY
#: a strip whose share of zero filtered bytes is above this is coded with ``Z_RLE``
PNG_FLAT_ZEROS = 0.5
#: strips per thread (load balance against the window restart per strip)
STRIPS_PER_THREAD = 4
#: threads when the caller gives none (a pool of the CPU count, capped)
MAX_THREADS = 8
#: the smallest strip worth a task (bytes of filtered rows)
MIN_STRIP_BYTES = 1 << 20


def _chunk(ctype: bytes, data: bytes) -> bytes:
    crc = _deflate.crc32(data, _deflate.crc32(ctype)) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + ctype + data + struct.pack(">I", crc)


def adler32_combine(adler1: int, adler2: int, len2: int) -> int:
    """The Adler-32 of ``A + B`` from ``adler32(A)``, ``adler32(B)`` and
    ``len(B)`` (zlib's ``adler32_combine``)."""
    a1, b1 = adler1 & 0xFFFF, adler1 >> 16
    a2, b2 = adler2 & 0xFFFF, adler2 >> 16
    a = (a1 + a2 - 1) % _ADLER_BASE
    b = (b1 + b2 + len2 * (a1 - 1)) % _ADLER_BASE
    return (b << 16) | a


def _filtered_rows(rows: np.ndarray, bpp: int) -> np.ndarray:
    """PNG rows with filter type 1 (Sub: each byte minus the byte ``bpp``
    before it, modulo 256), the filter byte first: ``(h, 1 + W * bpp)``."""
    h = rows.shape[0]
    flat = rows.reshape(h, -1)
    out = np.empty((h, flat.shape[1] + 1), np.uint8)
    out[:, 0] = 1
    out[:, 1:1 + bpp] = flat[:, :bpp]
    np.subtract(flat[:, bpp:], flat[:, :-bpp], out=out[:, 1 + bpp:])
    return out


def png_encode(img: np.ndarray, threads: int | None = None, level: int = PNG_LEVEL,
               strategy: int = PNG_STRATEGY) -> bytes:
    """An RGB image (``(H, W, 3)`` uint8 or uint16) as PNG bytes (IHDR,
    IDAT, IEND; no colour chunks: :func:`service.outputs.embed` adds them).
    ``threads``: the pool size (default: the CPU count, at most
    :data:`MAX_THREADS`)."""
    if img.ndim != 3 or img.shape[2] != 3 or img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"png_encode: an (H, W, 3) uint8 or uint16 image, not {img.shape} {img.dtype}")
    return png_encode_rows(img.shape[0], img.shape[1], img.dtype, lambda r0, r1: img[r0:r1], threads, level,
                           strategy)


def strip_bounds(H: int, n_strips: int, multiple: int = 1) -> list[int]:
    """``n_strips + 1`` (or fewer) row bounds from 0 to ``H``, each inner one
    a multiple of ``multiple``, the strips as even as that allows."""
    multiple = max(1, int(multiple))
    units = -(-H // multiple)
    n = max(1, min(int(n_strips), units))
    cuts = sorted({min(H, int(round(units * k / n)) * multiple) for k in range(n + 1)})
    return cuts


def png_encode_rows(H: int, W: int, dtype, rows, threads: int | None = None, level: int = PNG_LEVEL,
                    strategy: int = PNG_STRATEGY, row_multiple: int = 1) -> bytes:
    """:func:`png_encode` of an image given by its rows: ``rows(r0, r1)``
    returns rows ``r0:r1`` (``(r1 - r0, W, 3)`` of ``dtype``), called once
    for each strip on the strip's thread, so the image need never exist
    whole (:mod:`service.strips`). Every strip bound but the last is a
    multiple of ``row_multiple``."""
    dtype = np.dtype(dtype)
    if dtype not in (np.uint8, np.uint16):
        raise ValueError(f"png_encode: uint8 or uint16 rows, not {dtype}")
    if H < 1 or W < 1:
        raise ValueError("png_encode: empty image")
    bits = 8 if dtype == np.uint8 else 16
    bpp = 3 * bits // 8
    row_bytes = 1 + W * bpp
    n_threads = max(1, threads or min(MAX_THREADS, os.cpu_count() or 1))
    n_strips = max(1, min(H, n_threads * STRIPS_PER_THREAD, (H * row_bytes) // MIN_STRIP_BYTES or 1))
    bounds = strip_bounds(H, n_strips, row_multiple)
    n_strips = len(bounds) - 1

    def strip(i: int):
        r0, r1 = int(bounds[i]), int(bounds[i + 1])
        px = rows(r0, r1)
        if bits == 16:
            px = px.astype(">u2")           # PNG samples are big-endian
            px = px.view(np.uint8).reshape(r1 - r0, W, 6)
        buf = _filtered_rows(px, bpp)
        st = strategy
        if st == zlib.Z_HUFFMAN_ONLY and buf.size and np.count_nonzero(buf) < (1 - PNG_FLAT_ZEROS) * buf.size:
            st = zlib.Z_RLE
        c = _deflate.compressobj(level, zlib.DEFLATED, -15, 8, st)
        last = i == n_strips - 1
        data = c.compress(buf) + c.flush(zlib.Z_FINISH if last else zlib.Z_SYNC_FLUSH)
        if i == 0:
            data = b"\x78\x01" + data            # zlib header: deflate, 32 KiB window
        return _chunk(b"IDAT", data), _deflate.adler32(buf), buf.size

    if n_threads == 1 or n_strips == 1:
        parts = [strip(i) for i in range(n_strips)]
    else:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(min(n_threads, n_strips)) as pool:
            parts = list(pool.map(strip, range(n_strips)))
    adler = parts[0][1]
    for _, a, n in parts[1:]:
        adler = adler32_combine(adler, a, n)
    ihdr = struct.pack(">IIBBBBB", W, H, bits, 2, 0, 0, 0)
    return b"".join([PNG_SIGNATURE, _chunk(b"IHDR", ihdr)] + [p[0] for p in parts]
                    + [_chunk(b"IDAT", struct.pack(">I", adler)), _chunk(b"IEND", b"")])


# ---------------------------------------------------------------------------
# JPEG
# ---------------------------------------------------------------------------

#: JPEG quality of the service's outputs
JPEG_QUALITY = 95
#: the smallest image worth splitting (pixels)
MIN_JPEG_SPLIT_PIXELS = 1 << 21


def _segments(jpg: bytes):
    """The marker segments of a baseline JPEG up to and including SOS:
    ``[(marker, start, end)]`` (``end`` past the segment), then the offset
    where the entropy-coded data starts."""
    if jpg[:2] != b"\xff\xd8":
        raise ValueError("not a JPEG")
    pos, segs = 2, []
    while True:
        if jpg[pos] != 0xFF:
            raise ValueError("JPEG: marker expected")
        marker = jpg[pos + 1]
        n = struct.unpack(">H", jpg[pos + 2:pos + 4])[0]
        segs.append((marker, pos, pos + 2 + n))
        pos += 2 + n
        if marker == 0xDA:
            return segs, pos


def _mcu_rows(jpg: bytes, segs) -> tuple[int, int, int, int]:
    """``(SOF offset, MCU height, MCU width, components)`` of a baseline JPEG."""
    for marker, start, _ in segs:
        if marker == 0xC0:
            ncomp = jpg[start + 9]
            hs = [jpg[start + 11 + 3 * i] >> 4 for i in range(ncomp)]
            vs = [jpg[start + 11 + 3 * i] & 15 for i in range(ncomp)]
            return start, 8 * max(vs), 8 * max(hs), ncomp
    raise ValueError("JPEG: not baseline (no SOF0)")


def jpeg_encode(img: np.ndarray, quality: int = JPEG_QUALITY, threads: int | None = None) -> bytes:
    """An 8-bit RGB image as a baseline JPEG (OpenCV/libjpeg, ``quality``),
    encoded in horizontal strips on a thread pool and joined into one file
    with restart markers.

    Each strip is a whole number of MCU rows and is encoded by OpenCV with
    the same settings, so its quantisation and Huffman tables are the
    whole image's and its blocks the same coefficients (colour conversion,
    4:2:0 subsampling and the DCT never look across an MCU); a strip's
    entropy-coded data starts with zero DC predictions and ends byte-
    aligned, which is what a restart marker means. The joined file is the
    first strip's headers with the full height, a DRI segment (restart
    interval: one strip's MCUs), the strips' data separated by RST0..RST7,
    EOI. Decoders give the pixels of a one-piece encode exactly (a test
    checks); when the strips' tables differ, or the image is small, it is
    encoded in one piece."""
    return jpeg_encode_rows(img.shape[0], img.shape[1], lambda r0, r1: img[r0:r1], quality, threads)


def jpeg_encode_rows(H: int, W: int, rows, quality: int = JPEG_QUALITY, threads: int | None = None,
                     row_multiple: int = 1, bgr: bool = False) -> bytes:
    """:func:`jpeg_encode` of an image given by its rows: ``rows(r0, r1)``
    returns rows ``r0:r1`` (``(r1 - r0, W, 3)`` uint8), called once for each
    strip on the strip's thread (:mod:`service.strips`), in BGR order when
    ``bgr`` (OpenCV's: no conversion). The strips are a whole number of MCU
    rows and of ``row_multiple`` rows; an image that cannot be joined so is
    asked for whole."""
    import cv2

    params = [cv2.IMWRITE_JPEG_QUALITY, int(quality)]

    def one(px: np.ndarray) -> bytes:
        # RGB -> BGR by OpenCV (SIMD: a fifth of numpy's reversed copy, issue 19)
        ok, enc = cv2.imencode(".jpg", px if bgr else cv2.cvtColor(px, cv2.COLOR_RGB2BGR), params)
        if not ok:
            raise ValueError("OpenCV could not encode the JPEG")
        return enc.tobytes()

    n_threads = max(1, threads or min(MAX_THREADS, os.cpu_count() or 1))
    if n_threads == 1 or H * W < MIN_JPEG_SPLIT_PIXELS or H < 64:
        return one(rows(0, H))
    head = one(rows(0, min(H, 16)))
    segs, _ = _segments(head)
    _, mcu_h, mcu_w, _ = _mcu_rows(head, segs)
    mcus_per_row = -(-W // mcu_w)
    n_strips = n_threads * STRIPS_PER_THREAD
    mcu_rows = -(-H // mcu_h)
    strip_mcu_rows = max(1, -(-mcu_rows // n_strips))
    unit = math.lcm(mcu_h, max(1, int(row_multiple))) // mcu_h      # MCU rows a strip is a multiple of
    strip_mcu_rows = -(-strip_mcu_rows // unit) * unit
    if strip_mcu_rows > 65535 // mcus_per_row:                       # the restart interval is 16-bit
        strip_mcu_rows = (65535 // mcus_per_row) // unit * unit
    if strip_mcu_rows < 1:
        return one(rows(0, H))
    step = strip_mcu_rows * mcu_h
    starts = list(range(0, H, step))
    if len(starts) < 2:
        return one(rows(0, H))
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(min(n_threads, len(starts))) as pool:
        parts = list(pool.map(lambda r: one(rows(r, min(H, r + step))), starts))
    first_segs, first_data = _segments(parts[0])
    sof, _, _, _ = _mcu_rows(parts[0], first_segs)
    tables = [parts[0][s:e] for m, s, e in first_segs if m in (0xDB, 0xC4, 0xDA)]
    data = []
    for k, p in enumerate(parts):
        segs, start = _segments(p)
        if [p[s:e] for m, s, e in segs if m in (0xDB, 0xC4, 0xDA)] != tables or p[-2:] != b"\xff\xd9":
            return one(rows(0, H))                                    # not joinable: one piece
        data.append(p[start:-2])
        if k < len(parts) - 1:
            data.append(bytes((0xFF, 0xD0 + k % 8)))
    header = bytearray(parts[0][:first_segs[-1][1]])                   # SOI .. before SOS
    struct.pack_into(">H", header, sof + 5, H)                          # SOF0 height: the whole image
    dri = b"\xff\xdd" + struct.pack(">HH", 4, strip_mcu_rows * mcus_per_row)
    sos = parts[0][first_segs[-1][1]:first_data]
    return b"".join([bytes(header), dri, sos] + data + [b"\xff\xd9"])
