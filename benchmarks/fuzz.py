"""Mutated RAW files against the service (issue 6): every answer a 4xx with a
JSON error, or a 200 with finite numbers when the mutation left the file
valid; never a 5xx, never a hang; the service still answers afterwards and
its memory stays bounded.

``python -m benchmarks.fuzz [--n 2000] [--timeout 20] [--seed 0] [--real-dng PATH]``
``python -m benchmarks.fuzz --round2 [--scale 1]`` (issue 17's inputs: :func:`run_round2`)

The seeds are small valid DNGs written by :mod:`testing.dngwriter` from
spectral scenes (different cameras, lights and CFA patterns). Each mutation is
a deterministic function of ``(seed, index)`` (:func:`mutations`); the kinds
cycle so that any prefix of the sequence has every kind in it:

=================  ==========================================================
``truncate``        the file cut at an offset: inside the 8-byte header, the
                    IFD, the tag values or the strip data
``flip-header``     one bit of the TIFF header (byte order, magic, IFD offset)
``flip-ifd``        one bit of an IFD entry (tag code, type, count, value)
``flip-value``      one bit of the out-of-line tag values (strings, matrices)
``flip-strip``      bits of the pixel data (the file usually stays valid)
``tag-value``       one tag's value set to 0, 1, 2**15, 2**16-1, 2**31-1 or
                    2**32-1 (as a LONG)
``tag-type``        one tag's field type set to an invalid or wrong type
``huge-dims``       ImageWidth/ImageLength declared 100000 x 100000 (and
                    other large sizes) with the same small strip
``zero-dims``       a zero, "negative" (2**32-1, 2**31 as LONG) or 1-pixel
                    dimension
``bits``            BitsPerSample 0, 1, 3, 7, 12, 15, 17, 32, 64 or 65535
``strip-eof``       StripOffsets past the end of the file, or StripByteCounts
                    larger than the file
``ifd-offset``      the first-IFD offset past EOF, 0, into the header, or an
                    IFD whose next-IFD pointer loops onto itself
``entry-count``     the IFD's entry count 0, 1, 255 or 65535
``splice``          a byte range overwritten with random bytes or another
                    seed's bytes
``wrong-name``      a valid or mutated file sent as ``.jpg``/``.png``/``.txt``
                    with a matching or bogus content type, or random bytes
                    named ``.dng``
=================  ==========================================================

With ``--real-dng PATH`` (a real tiled, JPEG-compressed DNG such as
``shared/data/raw/Blackmagic.dng``), :func:`dng_mutations` of it are sent
too, each twice, after two different images (:func:`run_real_dng`): the two
answers must be the same, or the decode depends on what came before (issue
10: LibRaw's uncleared buffer).

All requests go through the ASGI app in-process (``httpx.ASGITransport``),
each under a timeout. Memory is the resident set size of this process
(``psutil``), sampled after a warm-up (imports, colour data, caches) and at
the end; see :func:`run` for the bound.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import logging
import math
import struct
import sys
import time
from collections import Counter
from dataclasses import dataclass, field

import numpy as np

from testing.tiffs import linear_tiff

__all__ = ["Mutation", "FuzzReport", "seed_dngs", "ifd_entries", "mutations", "memory_bound_mb", "run", "main",
           "dng_mutations", "victim_dngs", "run_real_dng", "ROUND2_KINDS", "round2_cases", "run_round2",
           "round2_table", "packbits_tiff"]

KINDS = ("truncate", "flip-header", "flip-ifd", "flip-value", "flip-strip", "tag-value", "tag-type",
         "huge-dims", "zero-dims", "bits", "strip-eof", "ifd-offset", "entry-count", "splice", "wrong-name")

#: TIFF tags the mutations aim at.
TAG_WIDTH, TAG_LENGTH, TAG_BITS, TAG_STRIP_OFFSETS, TAG_STRIP_BYTES = 256, 257, 258, 273, 279


@dataclass
class Mutation:
    """One mutated upload."""

    index: int
    kind: str
    what: str
    data: bytes
    filename: str = "fuzz.dng"
    content_type: str = "image/x-adobe-dng"


@dataclass
class FuzzReport:
    """What :func:`run` saw."""

    n: int = 0
    statuses: Counter = field(default_factory=Counter)
    by_kind: dict = field(default_factory=dict)
    failures: list = field(default_factory=list)
    elapsed_s: float = 0.0
    latencies_s: list = field(default_factory=list)
    rss_warm_mb: float = 0.0
    rss_end_mb: float = 0.0
    rss_peak_mb: float = 0.0
    health_after: int = 0

    @property
    def rss_growth_mb(self) -> float:
        return self.rss_end_mb - self.rss_warm_mb

    def table(self) -> str:
        lines = [f"{'kind':17s} {'n':>5s}  statuses"]
        for kind in KINDS + DNG_KINDS:
            c = self.by_kind.get(kind)
            if c:
                lines.append(f"{kind:17s} {sum(c.values()):5d}  "
                             + ", ".join(f"{k}: {v}" for k, v in sorted(c.items())))
        lat = np.array(self.latencies_s or [0.0])
        lines.append(f"\n{self.n} requests in {self.elapsed_s:.1f} s ({self.n / max(self.elapsed_s, 1e-9):.1f}/s); "
                     f"latency p50 {1e3 * np.percentile(lat, 50):.0f} ms, p99 {1e3 * np.percentile(lat, 99):.0f} ms, "
                     f"max {1e3 * lat.max():.0f} ms")
        lines.append(f"statuses: {dict(sorted(self.statuses.items()))}; /health afterwards: {self.health_after}")
        lines.append(f"RSS after warm-up {self.rss_warm_mb:.1f} MB, at the end {self.rss_end_mb:.1f} MB "
                     f"(growth {self.rss_growth_mb:+.1f} MB), peak sampled {self.rss_peak_mb:.1f} MB")
        lines.append(f"failures: {len(self.failures)}")
        lines.extend(f"  {f}" for f in self.failures[:20])
        return "\n".join(lines)


# ---------------------------------------------------------------------------
# Seeds and the TIFF structure
# ---------------------------------------------------------------------------

#: (camera, light, pattern, height, width): small scenes, above LibRaw's
#: 22-pixel minimum, a few kilobytes each.
SEEDS = (("Nikon 5100 (NPL)", "A", "RGGB", 48, 64),
         ("Canon EOS 5D Mark II", "D65", "GRBG", 40, 56),
         ("Sigma SDMerill (NPL)", "FL2", "BGGR", 32, 48))


def seed_dngs() -> list[bytes]:
    """The valid DNGs every mutation starts from (:data:`SEEDS`)."""
    from testing.dngwriter import scene_dng

    out = []
    for i, (camera, light, pattern, h, w) in enumerate(SEEDS):
        buf = io.BytesIO()
        scene_dng(buf, camera, light, h, w, seed=10 + i, pattern=pattern)
        out.append(buf.getvalue())
    return out


def ifd_entries(data: bytes) -> tuple[str, int, dict]:
    """Byte order, first-IFD offset and ``{tag: (entry_pos, type, count,
    value_pos)}`` of IFD 0 of a classic TIFF (TIFF 6.0, section 2: 8-byte
    header, 12-byte entries; a value of at most 4 bytes sits in the entry)."""
    bo = "<" if data[:2] == b"II" else ">"
    (ifd,) = struct.unpack(bo + "I", data[4:8])
    (n,) = struct.unpack(bo + "H", data[ifd:ifd + 2])
    sizes = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8}
    entries = {}
    for i in range(n):
        pos = ifd + 2 + 12 * i
        tag, typ, count = struct.unpack(bo + "HHI", data[pos:pos + 8])
        nbytes = sizes.get(typ, 1) * count
        value_pos = pos + 8 if nbytes <= 4 else struct.unpack(bo + "I", data[pos + 8:pos + 12])[0]
        entries[tag] = (pos, typ, count, value_pos)
    return bo, ifd, entries


def _set_long(data: bytearray, bo: str, entries: dict, tag: int, value: int) -> None:
    """Make ``tag`` one LONG with ``value`` (written into its entry)."""
    pos = entries[tag][0]
    struct.pack_into(bo + "HIi" if value < 0 else bo + "HII", data, pos + 2, 4, 1, value)


# ---------------------------------------------------------------------------
# Mutations
# ---------------------------------------------------------------------------

def _flip(data: bytearray, pos: int, bit: int) -> None:
    data[pos] ^= 1 << bit


def mutations(n: int, seeds: list[bytes] | None = None, seed: int = 0):
    """The first ``n`` mutations, deterministic for a given ``seed``.

    Mutation ``i`` is of kind ``KINDS[i % len(KINDS)]`` applied to seed file
    ``(i // len(KINDS)) % len(seeds)`` with parameters drawn from
    ``numpy.random.default_rng((seed, i))``.
    """
    seeds = seed_dngs() if seeds is None else seeds
    for i in range(n):
        kind = KINDS[i % len(KINDS)]
        src = seeds[(i // len(KINDS)) % len(seeds)]
        rng = np.random.default_rng((seed, i))
        yield _mutate(i, kind, src, seeds, rng)


def _mutate(i: int, kind: str, src: bytes, seeds: list[bytes], rng) -> Mutation:
    bo, ifd, ent = ifd_entries(src)
    d = bytearray(src)
    strip = ent[TAG_STRIP_OFFSETS][3]
    (strip_off,) = struct.unpack(bo + "I", src[strip:strip + 4])
    ifd_end = ifd + 2 + 12 * len(ent) + 4
    m = lambda what, data=None, **kw: Mutation(i, kind, what, bytes(d if data is None else data), **kw)  # noqa: E731

    if kind == "truncate":
        region = int(rng.integers(4))
        lo, hi = [(0, 8), (8, ifd_end), (ifd_end, strip_off), (strip_off, len(src))][region]
        cut = int(rng.integers(lo, hi))
        return m(f"cut at byte {cut} of {len(src)}", src[:cut])
    if kind == "flip-header":
        pos, bit = int(rng.integers(8)), int(rng.integers(8))
        _flip(d, pos, bit)
        return m(f"header byte {pos} bit {bit}")
    if kind == "flip-ifd":
        pos, bit = int(rng.integers(ifd, ifd_end)), int(rng.integers(8))
        _flip(d, pos, bit)
        return m(f"IFD byte {pos} bit {bit}")
    if kind == "flip-value":
        pos, bit = int(rng.integers(ifd_end, strip_off)), int(rng.integers(8))
        _flip(d, pos, bit)
        return m(f"tag-value byte {pos} bit {bit}")
    if kind == "flip-strip":
        k = int(rng.integers(1, 65))
        for pos, bit in zip(rng.integers(strip_off, len(src), k), rng.integers(0, 8, k)):
            _flip(d, int(pos), int(bit))
        return m(f"{k} bit(s) of the strip")
    if kind == "tag-value":
        tag = int(rng.choice(sorted(ent)))
        value = int(rng.choice([0, 1, 2**15, 2**16 - 1, 2**31 - 1, 2**32 - 1]))
        _set_long(d, bo, ent, tag, value)
        return m(f"tag {tag} = {value} (LONG)")
    if kind == "tag-type":
        tag = int(rng.choice(sorted(ent)))
        typ = int(rng.choice([0, 1, 2, 3, 4, 5, 7, 10, 12, 13, 99, 65535]))
        struct.pack_into(bo + "H", d, ent[tag][0] + 2, typ)
        return m(f"tag {tag} type {typ}")
    if kind == "huge-dims":
        w, h = [(100000, 100000), (65535, 65535), (2**31 - 1, 2), (2, 2**31 - 1), (20000, 20000),
                (12000, 10000), (2**32 - 1, 2**32 - 1)][int(rng.integers(7))]
        _set_long(d, bo, ent, TAG_WIDTH, w)
        _set_long(d, bo, ent, TAG_LENGTH, h)
        return m(f"declared {w} x {h}")
    if kind == "zero-dims":
        tag = int(rng.choice([TAG_WIDTH, TAG_LENGTH]))
        value = int(rng.choice([0, 1, 2**31, 2**32 - 1, 21]))
        _set_long(d, bo, ent, tag, value)
        return m(f"{'width' if tag == TAG_WIDTH else 'length'} = {value}")
    if kind == "bits":
        bits = int(rng.choice([0, 1, 3, 7, 8, 12, 15, 17, 32, 64, 65535]))
        struct.pack_into(bo + "H", d, ent[TAG_BITS][3], bits)
        return m(f"BitsPerSample {bits}")
    if kind == "strip-eof":
        if rng.integers(2):
            off = int(rng.choice([len(src), len(src) + 1, len(src) - 1, 2**31, 2**32 - 1]))
            struct.pack_into(bo + "I", d, ent[TAG_STRIP_OFFSETS][3], off)
            return m(f"StripOffsets {off}")
        cnt = int(rng.choice([len(src), 2 * len(src), 2**31, 2**32 - 1, 0, 1]))
        struct.pack_into(bo + "I", d, ent[TAG_STRIP_BYTES][3], cnt)
        return m(f"StripByteCounts {cnt}")
    if kind == "ifd-offset":
        choice = int(rng.integers(5))
        if choice == 4:       # next-IFD pointer of IFD 0 points back at IFD 0
            struct.pack_into(bo + "I", d, ifd_end - 4, ifd)
            return m("IFD 0 lists itself as the next IFD")
        off = [len(src) + 100, 0, 2, 2**32 - 1][choice]
        struct.pack_into(bo + "I", d, 4, off)
        return m(f"first IFD at {off}")
    if kind == "entry-count":
        count = int(rng.choice([0, 1, 255, 65535]))
        struct.pack_into(bo + "H", d, ifd, count)
        return m(f"IFD entry count {count}")
    if kind == "splice":
        start = int(rng.integers(len(src)))
        length = int(rng.integers(1, 257))
        if rng.integers(2):
            d[start:start + length] = rng.integers(0, 256, length, dtype=np.uint8).tobytes()
            return m(f"{length} random bytes at {start}")
        other = seeds[int(rng.integers(len(seeds)))]
        o = int(rng.integers(len(other)))
        d[start:start + length] = other[o:o + length]
        return m(f"{length} bytes of another seed at {start}")
    if kind == "wrong-name":
        choice = int(rng.integers(5))
        if choice == 4:
            junk = rng.integers(0, 256, int(rng.integers(1, 8192)), dtype=np.uint8).tobytes()
            return m(f"{len(junk)} random bytes named .dng", junk)
        name, ctype = [("photo.jpg", "image/jpeg"), ("photo.png", "image/png"), ("notes.txt", "text/plain"),
                       ("noext", "application/x-bogus")][choice]
        if rng.integers(2):      # also damaged
            _flip(d, int(rng.integers(len(src))), int(rng.integers(8)))
            return m(f"damaged DNG named {name} ({ctype})", filename=name, content_type=ctype)
        return m(f"valid DNG named {name} ({ctype})", filename=name, content_type=ctype)
    raise ValueError(f"unknown mutation kind {kind!r}")


# ---------------------------------------------------------------------------
# Mutations of a real camera DNG (issue 10)
# ---------------------------------------------------------------------------

#: Kinds of :func:`dng_mutations`. Those from ``dng-truncate`` to
#: ``dng-tile-tags`` damage the strips and tiles LibRaw decodes into its
#: (uncleared) buffer: each of them leaked the previous upload's pixels
#: before the strips and tiles were verified.
DNG_KINDS = ("dng-truncate", "dng-zero-tail", "dng-no-soi", "dng-sof", "dng-jpeg-segment", "dng-tile-geometry",
             "dng-tile-tags", "dng-ifd-flip", "dng-data", "dng-valid")

TAG_TILE_WIDTH, TAG_TILE_LENGTH, TAG_TILE_OFFSETS, TAG_TILE_BYTES = 322, 323, 324, 325


def _longs(data: bytes, bo: str, entry: tuple) -> list[int]:
    _, typ, count, value_pos = entry
    fmt = "H" if typ == 3 else "I"
    return list(struct.unpack_from(f"{bo}{count}{fmt}", data, value_pos))


def _jpeg_segments(data: bytes, start: int) -> dict:
    """``{marker: position of its FF byte}`` of the JPEG at ``start``, up to
    its SOS (the first of each marker)."""
    out, p = {}, start + 2
    while data[p] == 0xFF:
        m = data[p + 1]
        out.setdefault(m, p)
        if m == 0xDA:
            break
        p += 2 + struct.unpack_from(">H", data, p + 2)[0]
    return out


def dng_mutations(data: bytes, seed: int = 0) -> list[Mutation]:
    """Deterministic mutations of a tiled, JPEG-compressed camera DNG (such
    as ``shared/data/raw/Blackmagic.dng``), one of every class that made
    LibRaw decode part of the image from the previous decode's memory.

    The tags are patched in place in IFD 0 (:func:`ifd_entries`), so the
    mutated files keep the original layout:

    ``dng-truncate``
        cut inside the header, the IFD, the tag values, at and next to each
        tile start, and 1-15 bytes before the end of the last tile;
    ``dng-zero-tail``
        every byte after a point inside tile 0 or 1 zeroed (length kept);
    ``dng-no-soi``
        one tile's SOI marker destroyed;
    ``dng-sof``
        a field of tile 0's JPEG frame header (precision, height, width,
        components, marker type, length);
    ``dng-jpeg-segment``
        the length of tile 0's DQT or DHT segment 0 or 65535, or a Huffman
        table of class 9;
    ``dng-tile-geometry``
        ImageWidth one more, TileWidth / TileLength 0, 1, 16, one less or
        more, doubled, the image width, 2**32-1, or with a count of
        2**27+1;
    ``dng-tile-tags``
        TileOffsets' count 1 or huge, the offsets 0, into the IFD, past the
        end, one byte in, or huge, the tile tags renamed to strip tags;
    ``dng-ifd-flip``
        random bytes of the header and IFD 0 changed (``seed``);
    ``dng-data``
        random bytes of tile 0's entropy-coded data changed, 4 KiB of the
        last tile zeroed, an EOI marker inside it: the structure is intact,
        LibRaw decodes them or reports a data error;
    ``dng-valid``
        the file itself, and with its last 1 and 15 bytes cut when they
        follow the last tile (they then belong to no tag).

    Whatever the outcome, each must be the same whatever was decoded
    before.

    Parameters
    ----------
    data : bytes
        A little- or big-endian DNG whose IFD 0 holds the raw image in tiles
        (TileOffsets, TileByteCounts) of JPEG data.
    seed : int

    Returns
    -------
    list of Mutation
        ``index`` counts from 0; ``filename`` ``real.dng``.
    """
    bo, ifd, ent = ifd_entries(data)
    offs, cnts = _longs(data, bo, ent[TAG_TILE_OFFSETS]), _longs(data, bo, ent[TAG_TILE_BYTES])
    (width,) = _longs(data, bo, ent[TAG_WIDTH])
    (tile_w,) = _longs(data, bo, ent[TAG_TILE_WIDTH])
    ifd_end = ifd + 2 + 12 * len(ent) + 4
    data_end = max(o + c for o, c in zip(offs, cnts))
    seg = _jpeg_segments(data, offs[0])
    sof = next(p for m, p in seg.items() if 0xC0 <= m <= 0xCF and m not in (0xC4, 0xC8, 0xCC))
    rng = np.random.default_rng((seed, 10))
    out: list[Mutation] = []

    def add(kind, what, d, **kw):
        out.append(Mutation(len(out), kind, what, bytes(d), filename="real.dng", **kw))

    def patched(fn):
        d = bytearray(data)
        fn(d)
        return d

    for cut in sorted({8, ifd + 100, ifd_end, ifd_end + 32, offs[0] - 1, offs[0], offs[0] + 1, sof + 6,
                       *[o + k for o in offs[1:] for k in (-1, 0, 1)], *[data_end - k for k in (1, 2, 8, 15)]}):
        add("dng-truncate", f"cut at byte {cut} of {len(data)}", data[:cut])
    for start in (offs[0] + 5000, offs[1] + 1000):
        add("dng-zero-tail", f"bytes from {start} zeroed", data[:start] + bytes(len(data) - start))
    for t, o in enumerate(offs):
        add("dng-no-soi", f"tile {t} SOI destroyed", patched(lambda d, o=o: d.__setitem__(slice(o, o + 2), b"\0\0")))
    for name, k, val in [("precision 0", 4, b"\x00"), ("precision 255", 4, b"\xff"), ("height 0", 5, b"\0\0"),
                         ("height 1", 5, b"\0\x01"), ("width 0", 7, b"\0\0"), ("width 1", 7, b"\0\x01"),
                         ("components 0", 9, b"\x00"), ("components 255", 9, b"\xff"), ("SOF0", 1, b"\xc0"),
                         ("SOF2 progressive", 1, b"\xc2"), ("length 0", 2, b"\0\0"), ("length 65535", 2, b"\xff\xff")]:
        add("dng-sof", f"tile 0 frame header {name}",
            patched(lambda d, k=k, val=val: d.__setitem__(slice(sof + k, sof + k + len(val)), val)))
    for name, m, k, val in [("DQT length 0", 0xDB, 2, b"\0\0"), ("DQT length 65535", 0xDB, 2, b"\xff\xff"),
                            ("DHT length 0", 0xC4, 2, b"\0\0"), ("DHT length 65535", 0xC4, 2, b"\xff\xff"),
                            ("DHT class 9", 0xC4, 4, b"\x9f")]:
        if m in seg:
            p = seg[m] + k
            add("dng-jpeg-segment", f"tile 0 {name}", patched(lambda d, p=p, val=val: d.__setitem__(
                slice(p, p + len(val)), val)))
    add("dng-tile-geometry", f"ImageWidth {width + 1}", patched(lambda d: _set_long(d, bo, ent, TAG_WIDTH, width + 1)))
    for v in (0, 1, 16, tile_w - 1, tile_w + 1, 2 * tile_w, width, 2**32 - 1):
        add("dng-tile-geometry", f"TileWidth {v}", patched(lambda d, v=v: _set_long(d, bo, ent, TAG_TILE_WIDTH, v)))
    for v in (0, 2**32 - 1):
        add("dng-tile-geometry", f"TileLength {v}", patched(lambda d, v=v: _set_long(d, bo, ent, TAG_TILE_LENGTH, v)))
    pos = ent[TAG_TILE_WIDTH][0]
    add("dng-tile-geometry", "TileWidth count 2**27+1",
        patched(lambda d: struct.pack_into(bo + "I", d, pos + 4, 2**27 + 1)))
    for c in (1, 2**24 - 1, 2**32 - 1):
        add("dng-tile-tags", f"TileOffsets count {c}",
            patched(lambda d, c=c: struct.pack_into(bo + "I", d, ent[TAG_TILE_OFFSETS][0] + 4, c)))
    vpos = ent[TAG_TILE_OFFSETS][3]
    n = len(offs)
    for name, vals in [("0", [0] * n), ("into the IFD", [ifd] * n), ("past the end", [len(data) + 10] * n),
                       ("one byte in", [o + 1 for o in offs]), ("huge", [2**32 - 16] * n)]:
        add("dng-tile-tags", f"TileOffsets {name}",
            patched(lambda d, vals=vals: struct.pack_into(f"{bo}{n}I", d, vpos, *vals)))

    def as_strips(d):
        for tag, new in ((TAG_TILE_OFFSETS, TAG_STRIP_OFFSETS), (TAG_TILE_BYTES, TAG_STRIP_BYTES),
                         (TAG_TILE_WIDTH, 278), (TAG_TILE_LENGTH, 278)):
            struct.pack_into(bo + "H", d, ent[tag][0], new)
    add("dng-tile-tags", "tile tags renamed to strip tags", patched(as_strips))
    for k in range(8):
        d = bytearray(data)
        where = sorted(int(p) for p in rng.integers(0, ifd_end, 1 + k % 4))
        for p in where:
            d[p] = int(rng.integers(256))
        add("dng-ifd-flip", f"bytes {where} of the header and IFD changed", d)
    add("dng-valid", "the file itself", data)
    for k in (1, 15):
        if len(data) - k >= data_end:
            add("dng-valid", f"last {k} byte(s) cut (after the last tile)", data[:len(data) - k])
    for k in range(4):
        d = bytearray(data)
        for p in rng.integers(offs[0] + 1024, offs[0] + cnts[0] - 4, 10 ** (k % 3 + 1)):   # entropy data
            d[int(p)] = int(rng.integers(256))
        add("dng-data", f"{10 ** (k % 3 + 1)} random bytes of tile 0's entropy-coded data changed", d)
    t = offs[-1]
    add("dng-data", "4 KiB of the last tile zeroed",
        patched(lambda d: d.__setitem__(slice(t + 1000, t + 5096), bytes(4096))))
    add("dng-data", "EOI marker inside the last tile",
        patched(lambda d: d.__setitem__(slice(t + 5000, t + 5002), b"\xff\xd9")))
    return out


def victim_dngs(height: int, width: int) -> tuple[bytes, bytes]:
    """Two different valid DNGs of ``height x width`` (a horizontal ramp
    with a bright band, and a constant 12345): decoded just before a
    mutation, they leave different pixels in LibRaw's freed buffers."""
    from testing.dngwriter import mosaic, write_dng

    rgb = np.empty((height, width, 3), np.uint16)
    rgb[...] = (np.linspace(5000, 37500, width, dtype=np.float64)[None, :, None]).astype(np.uint16)
    rgb[height // 3:height // 2] = 57000
    a, b = io.BytesIO(), io.BytesIO()
    write_dng(a, mosaic(rgb, "RGGB"), make="Victim", model="A")
    write_dng(b, np.full((height, width), 12345, np.uint16), make="Victim", model="B")
    return a.getvalue(), b.getvalue()


def _without_timings(obj):
    """``obj`` without its timings (keys ``ms``, ``ms_*``, ``*_ms``), which
    vary from run to run."""
    if isinstance(obj, dict):
        return {k: _without_timings(v) for k, v in obj.items()
                if not (k == "ms" or k.startswith("ms_") or k.endswith("_ms"))}
    if isinstance(obj, list):
        return [_without_timings(v) for v in obj]
    return obj


def _answer(r) -> tuple:
    """Status and body of an answer, without the timings."""
    try:
        body = json.loads(r.text)
    except ValueError:
        return r.status_code, r.text
    return r.status_code, _without_timings(body)


async def _run_real(muts, victims, timeout: float, report: FuzzReport, app, progress) -> list:
    import httpx

    dependent = []
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://localhost") as client:
        async def post(data, name, mut=None):
            t0 = time.perf_counter()
            try:
                files = {"file": (name, data, "image/x-adobe-dng")}
                r = await asyncio.wait_for(client.post("/v1/analyze", files=files), timeout)
            except asyncio.TimeoutError:
                if mut is not None:
                    report.failures.append(f"#{mut.index} {mut.kind} ({mut.what}): no answer in {timeout} s")
                return None
            except Exception as e:  # raised through the transport: a 500 in a real server
                if mut is not None:
                    report.failures.append(f"#{mut.index} {mut.kind} ({mut.what}): {type(e).__name__}: {e}"[:300])
                return None
            if mut is not None:
                report.latencies_s.append(time.perf_counter() - t0)
                report.n += 1
                report.statuses[r.status_code] += 1
                report.by_kind.setdefault(mut.kind, Counter())[r.status_code] += 1
                problem = _check(mut, "/v1/analyze", r)
                if problem:
                    report.failures.append(problem)
            return r

        t0 = time.perf_counter()
        for j, mut in enumerate(muts):
            answers = []
            for victim in victims:          # the same file after two different uploads
                await post(victim, "victim.dng")
                r = await post(mut.data, mut.filename, mut)
                answers.append(None if r is None else _answer(r))
            if answers[0] is not None and answers[0] != answers[1]:
                dependent.append(mut)
                report.failures.append(f"#{mut.index} {mut.kind} ({mut.what}): the answer depends on the previous "
                                       f"upload ({answers[0][0]} then {answers[1][0]})")
            if j == 0:
                report.rss_warm_mb = _rss_mb()
            report.rss_peak_mb = max(report.rss_peak_mb, _rss_mb())
            if progress:
                progress(j, report)
        report.elapsed_s = time.perf_counter() - t0
        report.rss_end_mb = _rss_mb()
        report.health_after = (await asyncio.wait_for(client.get("/health"), timeout)).status_code
    return dependent


def run_real_dng(data: bytes, *, seed: int = 0, timeout: float = 60.0, every: int = 1, app=None, progress=None):
    """:func:`dng_mutations` of a real DNG to ``/v1/analyze``, each twice:
    once after a :func:`victim_dngs` upload, once after the other.

    Parameters
    ----------
    data : bytes
        The DNG (e.g. ``shared/data/raw/Blackmagic.dng``).
    seed, timeout, app, progress
        As :func:`run`.
    every : int
        Send every ``every``-th mutation only (1: all of them).

    Returns
    -------
    (FuzzReport, list of Mutation)
        The report (two requests per mutation) and the mutations whose
        answer (status and body, timings left out) differed between the two:
        a decode that depends on a previous upload.
    """
    if app is None:
        from service.app import app
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    bo, _, ent = ifd_entries(data)
    (w,), (h,) = _longs(data, bo, ent[TAG_WIDTH]), _longs(data, bo, ent[TAG_LENGTH])
    report = FuzzReport()
    muts = dng_mutations(data, seed)[::max(1, int(every))]
    dependent = asyncio.run(_run_real(muts, victim_dngs(h, w), timeout, report, app, progress))
    return report, dependent


# ---------------------------------------------------------------------------
# Running them against the app
# ---------------------------------------------------------------------------

def _strict_json(text):
    def bad(name):
        raise ValueError(f"non-finite number {name}")
    return json.loads(text, parse_constant=bad)


def _finite_numbers(obj, path="") -> list[str]:
    """Paths of numbers that are not finite, or None where the estimate's
    light should be a number."""
    bad = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            bad += _finite_numbers(v, f"{path}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            bad += _finite_numbers(v, f"{path}[{i}]")
    elif isinstance(obj, float) and not math.isfinite(obj):
        bad.append(path)
    return bad


def _check(mut: Mutation, endpoint: str, r) -> str | None:
    """``None`` if the answer is acceptable, else what was wrong."""
    where = f"#{mut.index} {mut.kind} ({mut.what}) {endpoint}"
    ctype = r.headers.get("content-type", "")
    if r.status_code >= 500:
        return f"{where}: {r.status_code} {r.text[:200]}"
    if 400 <= r.status_code < 500:
        try:
            body = _strict_json(r.text)
        except ValueError as e:
            return f"{where}: {r.status_code} without a JSON body ({e}): {r.text[:120]!r}"
        if not (isinstance(body, dict) and isinstance(body.get("error"), str) and isinstance(body.get("detail"), str)):
            return f"{where}: {r.status_code} body without error/detail: {body!r}"[:300]
        return None
    if r.status_code != 200:
        return f"{where}: unexpected status {r.status_code}"
    try:
        if ctype.startswith("application/json"):
            body = _strict_json(r.text)
        else:
            body = _strict_json(r.headers["x-illuminant"])
            import cv2
            img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
            if img is None or img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 2:
                return f"{where}: 200 image that does not decode to an RGB image"
    except (ValueError, KeyError) as e:
        return f"{where}: 200 with a bad body or header ({type(e).__name__}: {e})"
    rgb = (body.get("illuminant") or {}).get("camera_rgb")
    if not (isinstance(rgb, list) and len(rgb) == 3 and all(isinstance(v, (int, float)) for v in rgb)):
        return f"{where}: 200 without a numeric illuminant.camera_rgb: {rgb!r}"
    if not all(math.isfinite(v) for v in rgb):
        return f"{where}: 200 with non-finite camera_rgb {rgb}"
    bad = _finite_numbers(body)
    if bad:
        return f"{where}: 200 with non-finite numbers at {bad[:5]}"
    return None


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


#: (endpoint, form fields) for the sampled extra requests.
EXTRA = (("/v1/white-balance", {"format": "png"}), ("/v1/surfaces", {"grid": "4x4"}))


async def _run(muts, timeout: float, sample_every: int, warmup: int, report: FuzzReport, app, progress) -> None:
    import httpx

    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://localhost") as client:
        async def post(endpoint, mut, fields):
            t0 = time.perf_counter()
            try:
                r = await asyncio.wait_for(
                    client.post(endpoint, files={"file": (mut.filename, mut.data, mut.content_type)}, data=fields),
                    timeout)
            except asyncio.TimeoutError:
                report.failures.append(f"#{mut.index} {mut.kind} ({mut.what}) {endpoint}: no answer in {timeout} s")
                return
            except Exception as e:  # the app raised through the transport: a 500 in a real server
                report.failures.append(f"#{mut.index} {mut.kind} ({mut.what}) {endpoint}: "
                                       f"{type(e).__name__}: {e}"[:300])
                return
            report.latencies_s.append(time.perf_counter() - t0)
            report.n += 1
            report.statuses[r.status_code] += 1
            report.by_kind.setdefault(mut.kind, Counter())[r.status_code] += 1
            problem = _check(mut, endpoint, r)
            if problem:
                report.failures.append(problem)

        t0 = time.perf_counter()
        for j, mut in enumerate(muts):
            if j == warmup:
                report.rss_warm_mb = _rss_mb()
            await post("/v1/analyze", mut, {})
            if sample_every and j % sample_every == 0:
                endpoint, fields = EXTRA[(j // sample_every) % len(EXTRA)]
                await post(endpoint, mut, fields)
            if j % 50 == 0:
                report.rss_peak_mb = max(report.rss_peak_mb, _rss_mb())
                if progress:
                    progress(j, report)
        report.elapsed_s = time.perf_counter() - t0
        if not report.rss_warm_mb:
            report.rss_warm_mb = _rss_mb()
        report.rss_end_mb = _rss_mb()
        report.rss_peak_mb = max(report.rss_peak_mb, report.rss_end_mb)
        h = await asyncio.wait_for(client.get("/health"), timeout)
        report.health_after = h.status_code


def memory_bound_mb(slack_mb: float = 64.0) -> float:
    """Largest RSS growth over a fuzz run that still counts as bounded.

    Mutated ColorMatrix tags give new matrix-derived cameras, and each new
    camera builds a light-posterior model (:func:`recovery.bayes.bayes_model`)
    that is cached, at most ``recovery.bayes._MODEL_CACHE_MAX`` of them. So
    the resident set may legitimately grow by that cache's capacity times one
    model's arrays (measured here on a measured camera, about 26 MB), plus
    ``slack_mb`` for the allocator (glibc keeps freed arenas; replaying the
    same 300 mutations five times moved RSS by under 1 MB). A leak of every
    upload (7 kB) would stay under this bound over 2,000 requests; a leak of
    every decoded image or model would not.
    """
    from recovery import Camera, bayes

    model = bayes.bayes_model(Camera.named("Nikon 5100 (NPL)"))
    model_mb = sum(v.nbytes for v in vars(model).values() if isinstance(v, np.ndarray)) / 2**20
    return bayes._MODEL_CACHE_MAX * model_mb + slack_mb


def run(n: int = 2000, *, seed: int = 0, timeout: float = 20.0, sample_every: int = 10, warmup: int = 200,
        app=None, progress=None) -> FuzzReport:
    """POST ``n`` mutated DNGs to ``/v1/analyze`` (every ``sample_every``-th
    also to ``/v1/white-balance`` or ``/v1/surfaces``) through the ASGI app.

    Parameters
    ----------
    n : int
        Number of mutations (:func:`mutations`).
    seed : int
        Seed of the mutation parameters.
    timeout : float
        Seconds one request may take before it counts as a hang. A valid seed
        file (at most 64 x 48 pixels) is answered in well under a second.
    sample_every : int
        Every this many mutations also go to the other upload endpoints.
    warmup : int
        Requests before the first memory sample: the first requests import
        LibRaw, OpenCV and colour-science and fill caches (tens of MB) that
        are not a leak.
    app : ASGI app, optional
        Default :data:`service.app.app`.

    Returns
    -------
    FuzzReport
        Statuses by kind, failures, latencies, memory. Memory is the process
        RSS after ``warmup`` requests and at the end: a request holds a few
        kilobytes of upload and at most a ``max_pixels``-limited image, all
        released when it returns, so the growth over the run should be the
        allocator's slack, not a function of ``n``.
    """
    if app is None:
        from service.app import app
    # tifffile logs a warning for every malformed tag it skips: thousands here
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    report = FuzzReport()
    muts = mutations(n, seed=seed)
    asyncio.run(_run(muts, timeout, sample_every, min(warmup, max(n - 1, 0)), report, app, progress))
    return report


# ---------------------------------------------------------------------------
# Issue 17: hostile names, metadata, targets, JSON fields, bombs
# ---------------------------------------------------------------------------

#: Kinds of :func:`round2_cases`, each a class of input that gave a 5xx, a
#: dropped connection, a black image answered 200 or gigabytes of memory.
ROUND2_KINDS = ("nonascii-metadata", "hostile-name", "bad-target", "json-bomb", "packbits-bomb", "csv-bomb",
                "host")


@dataclass
class Case:
    """One request of :func:`round2_cases`."""

    kind: str
    what: str
    method: str
    path: str
    files: dict | None = None
    data: dict | None = None
    headers: dict | None = None


def _utf8_dng(text: str, tag: int = 315, seed: int = 0) -> bytes:
    """A small valid DNG (testing.dngwriter) whose Software text is
    rewritten as UTF-8 ``text`` and retagged ``tag`` (Artist 315, Copyright
    33432 ...), byte for byte, as editors write non-ASCII metadata."""
    from testing.dngwriter import scene_dng

    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", 48, 64, seed=seed, make="MMMMMMMMMMMM", model="NNNNNNNNNNNN")
    d = bytearray(buf.getvalue())
    old = b"wandell-recovery testing.dngwriter"
    i, j = d.find(old), d.find(b"\x31\x01\x02\x00")
    enc = text.encode("utf-8")[:len(old) - 1]
    d[i:i + len(old)] = enc.ljust(len(old), b"\0")
    if tag != 305:
        d[j:j + 2] = tag.to_bytes(2, "little")
    return bytes(d)


def packbits_tiff(h: int, w: int) -> bytes:
    """One PackBits strip of zeros (runs of 128 bytes, 2 bytes each): ~190x smaller than its pixels."""
    n = h * w * 6
    return linear_tiff(h, w, 32773, b"\x81\x00" * (n // 128) + (bytes([257 - n % 128, 0]) if n % 128 else b""), h)


def round2_cases(scale: float = 1.0) -> list[Case]:
    """The issue-17 inputs, small enough for a test (``scale`` 1: bombs of a
    few MB; the round-2 memory scripts send the 100 MB ones)."""
    import zlib

    from testing.dngwriter import scene_dng

    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", 48, 64, seed=1, make="Acme", model="Model 1")
    dng = buf.getvalue()
    cases: list[Case] = []
    add = lambda *a, **kw: cases.append(Case(*a, **kw))  # noqa: E731
    for text, tag in (("(c) José Müller", 315), ("© Ærøskøbing Straße", 33432), ("写真家 山田", 315),
                      ("Привет мир", 33432), ("\u202egnp.evil \x07\x1b[2J", 315), ("Cámara\x00Ñ", 305)):
        d = _utf8_dng(text, tag)
        for fmt in ("tiff", "png", "jpeg"):
            add("nonascii-metadata", f"tag {tag} {text!r} -> {fmt}", "POST", "/v1/white-balance",
                files={"file": ("meta.dng", d)}, data={"format": fmt})
    make = dng.replace(b"Acme\0", "Ñu\0".encode().ljust(5, b"\0")) if b"Acme\0" in dng else dng
    add("nonascii-metadata", "UTF-8 Make", "POST", "/v1/white-balance", files={"file": ("make.dng", make)})
    for name in ("写真.dng", "Привет.dng", "\u202egnp.dng", "a\x00b.dng", 'a";filename*=UTF-8\'\'evil.html;x=".dng',
                 "a\r\nX-Injected: 1.dng", "..\\..\\boot.ini", "../../etc/passwd", "0", "😀" * 60 + ".dng",
                 "x" * 300 + ".dng", "\\", ".dng", "%22%0d%0a.dng"):
        for fmt in ("xmp", "png"):
            add("hostile-name", f"{name[:40]!r} format={fmt}", "POST", "/v1/white-balance",
                files={"file": (name, dng)}, data={"format": fmt})
    for t in ("D²", "BB²", "BB0", "D0", "BB1", "BB" + "9" * 400, "D3999", "D999", "BB25001", "D-5000", "BB1e5",
              "D٥٠٠٠", "BB 3200", "BB3200.5.5", ""):
        add("bad-target", f"target {t[:20]!r} white-balance", "POST", "/v1/white-balance",
            files={"file": ("s.dng", dng)}, data={"target": t, "format": "png"})
        add("bad-target", f"target {t[:20]!r} json", "POST", "/v1/white-balance",
            files={"file": ("s.dng", dng)}, data={"target": t, "response": "json"})
        add("bad-target", f"target {t[:20]!r} preview", "POST", "/v1/preview",
            files={"file": ("s.dng", dng)}, data={"target": t, "wb": "corrected"})
        add("bad-target", f"target {t[:20]!r} batch", "POST", "/v1/batches",
            files={"files": ("s.dng", dng)}, data={"target": t or "\u00b2", "format": "jpeg"})
    big, deep = "[" + "9" * 5000 + ",0]", "[" * 100_000 + "]" * 100_000
    for label, value in (("5000-digit int", big), ("100000 brackets", deep), ("100000 braces", "{" * 100_000),
                         ("1 MB list", "[" + "1," * 500_000 + "1]"), ("nan", "[NaN, 1]"), ("1e999", "[1e999, 2]"),
                         ("string", '["a", "b"]'), ("bool", "[true, false]"), ("negative", "[-1, -1]"),
                         ("huge", "[99999999999999999999, 1]"), ("lone surrogate", '["\\ud800"]')):
        for path, field, extra in (("/v1/analyze", "neutral", {}), ("/v1/surfaces", "points", {}),
                                   ("/v1/surfaces", "rects", {}), ("/v1/preview", "neutral", {"wb": "corrected"}),
                                   ("/v1/white-balance", "neutral", {"format": "png"})):
            v = value if field == "neutral" or not value.startswith("[") or value.startswith("[[") else "[" + value + "]"
            add("json-bomb", f"{field} {label} {path}", "POST", path, files={"file": ("s.dng", dng)},
                data={field: v, **extra})
    h, w = int(1000 * scale), int(1500 * scale)
    add("packbits-bomb", f"PackBits {h}x{w} one strip", "POST", "/v1/analyze",
        files={"file": ("p.tif", packbits_tiff(h, w))})
    add("packbits-bomb", f"deflate {h}x{w}", "POST", "/v1/analyze",
        files={"file": ("d.tif", linear_tiff(h, w, 8, zlib.compress(bytes(100 * w * 6), 9), 100))})
    for comp in (5, 7, 34925, 50000, 32773, 99):      # LZW, JPEG, LZMA, ZSTD, a damaged PackBits, unknown
        strip = b"\x80" * 64 if comp == 32773 else bytes(64 * 96 * 6)
        add("packbits-bomb", f"compression {comp}", "POST", "/v1/analyze",
            files={"file": ("c.tif", linear_tiff(64, 96, comp, strip, 64))})
    add("packbits-bomb", "PackBits declaring 20000 x 20000", "POST", "/v1/analyze",
        files={"file": ("p.tif", linear_tiff(20000, 20000, 32773, b"\x81\x00" * 1000, 20000))})
    n = int(1_000_000 * scale)
    row = ",".join(["0"] * n)
    for label, text in (("2 rows x 1M values", f"400,{row}\n410,{row}\n"),
                        ("200k rows", "".join(f"{400 + i * 1e-3:.3f},0.5\n" for i in range(200_000))),
                        ("ragged", "400,1,2\n410,1\n420,1,2\n"), ("header only", "nm,a,b\n"),
                        ("not numbers", "a,b\nc,d\n"), ("decimal commas", "400;0,5\n" * 3),
                        ("1M blank lines", "\n" * 1_000_000), ("nan", "\n".join(f"{400 + 10 * i},nan" for i in range(31))),
                        ("binary", "\x00\xff" * 1000), ("one huge field", "400," + "9" * n + "\n")):
        add("csv-bomb", f"render {label}", "POST", "/v1/render", files={"file": ("t.csv", text.encode("utf-8", "surrogateescape"))},
            data={"response": "json"})
    add("csv-bomb", "sensitivities 2 rows x 1M values", "POST", "/v1/analyze",
        files={"file": ("s.dng", dng), "sensitivities": ("s.csv", f"400,{row}\n410,{row}\n".encode())})
    for host in ("127.0.0.1:8000@evil.com", "[::1]evil.com", "localhost:80:80", "evil.com#@localhost",
                 "localhost\\@evil", "[::1", "127.0.0.1:999999", "LOCALHOST.", "localhost:8000/x"):
        add("host", f"Host {host!r}", "GET", "/health", headers={"host": host})
    return cases


def _vm(key: str) -> float:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _reset_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def _check_case(case: Case, r) -> str | None:
    """As :func:`_check`, plus: a 200 image is not black, its
    Content-Disposition has only ``filename``/``filename*``."""
    mut = Mutation(0, case.kind, case.what, b"")
    if case.path == "/v1/batches" and r.status_code == 202:
        return None
    if case.path == "/health" and r.status_code == 200:
        return f"{case.kind} ({case.what}): served a hostile Host"
    if case.path in ("/v1/render", "/health") and r.status_code == 200:
        return None
    if r.status_code == 200 and (case.data or {}).get("format") == "xmp":
        if not r.content.startswith(b"<?xpacket"):
            return f"{case.kind} ({case.what}): 200 that is not an XMP packet"
        try:
            summary = _strict_json(r.headers.get("x-illuminant", ""))
        except ValueError as e:
            return f"{case.kind} ({case.what}): XMP with a bad X-Illuminant ({e})"
        if _finite_numbers(summary) or not all(math.isfinite(v) for v in summary.get("camera_rgb") or [math.nan]):
            return f"{case.kind} ({case.what}): XMP whose estimate is not finite"
        problem = None
    elif r.status_code == 200 and case.path == "/v1/preview":
        import cv2

        img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        return None if img is not None and int(img.max()) > 0 else f"{case.kind} ({case.what}): black preview"
    else:
        problem = _check(mut, case.path, r)
    if problem or r.status_code != 200:
        return problem
    cd = r.headers.get("content-disposition")
    if cd is not None:
        import re

        params = {k.lower() for k in re.findall(r';\s*([^=;\s]+)\s*=', cd)}
        if params - {"filename", "filename*"}:
            return f"{case.kind} ({case.what}): Content-Disposition rewritten: {cd!r}"
    if r.headers.get("content-type", "").startswith("image/"):
        import cv2

        img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None or int(img.max()) == 0:
            return f"{case.kind} ({case.what}): 200 with a black or unreadable image"
    return None


async def _run_round2(cases, timeout: float, report: FuzzReport, app, peaks: dict) -> None:
    import httpx

    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://localhost") as client:
        plain = seed_dngs()[0]
        for fmt in ("tiff", "png", "jpeg", "xmp"):     # warm-up: imports and caches are not a request's cost
            try:
                await client.post("/v1/white-balance", files={"file": ("w.dng", plain)}, data={"format": fmt})
            except Exception:  # noqa: BLE001 - the cases themselves report failures
                pass
        t0 = time.perf_counter()
        report.rss_warm_mb = _rss_mb()
        for case in cases:
            hwm = _reset_hwm()
            before = _vm("VmRSS")
            t1 = time.perf_counter()
            try:
                r = await asyncio.wait_for(client.request(case.method, case.path, files=case.files, data=case.data,
                                                          headers=case.headers), timeout)
            except asyncio.TimeoutError:
                report.failures.append(f"{case.kind} ({case.what}): no answer in {timeout} s")
                continue
            except Exception as e:  # raised through the transport: a 500 in a real server
                report.failures.append(f"{case.kind} ({case.what}): {type(e).__name__}: {e}"[:300])
                report.n += 1
                report.statuses[500] += 1
                report.by_kind.setdefault(case.kind, Counter())[500] += 1
                continue
            report.latencies_s.append(time.perf_counter() - t1)
            if hwm:
                grow = _vm("VmHWM") - before
                if grow > peaks.get(case.kind, (0.0, ""))[0]:
                    peaks[case.kind] = (grow, case.what)
            report.n += 1
            report.statuses[r.status_code] += 1
            report.by_kind.setdefault(case.kind, Counter())[r.status_code] += 1
            problem = _check_case(case, r)
            if problem:
                report.failures.append(problem)
        report.elapsed_s = time.perf_counter() - t0
        report.rss_end_mb = report.rss_peak_mb = _rss_mb()
        report.health_after = (await asyncio.wait_for(client.get("/health"), timeout)).status_code


def run_round2(*, scale: float = 1.0, timeout: float = 60.0, app=None) -> tuple[FuzzReport, dict]:
    """:func:`round2_cases` through the ASGI app: the report (statuses by
    kind, failures) and, per kind, the largest rise of this process's peak
    RSS over one request (``VmHWM`` reset before each, Linux) with the input
    that caused it: ``{kind: (MiB, what)}``."""
    if app is None:
        from service.app import app
    logging.getLogger("tifffile").setLevel(logging.CRITICAL)
    logging.getLogger("service").setLevel(logging.CRITICAL)
    report, peaks = FuzzReport(), {}
    asyncio.run(_run_round2(round2_cases(scale), timeout, report, app, peaks))
    return report, peaks


def round2_table(report: FuzzReport, peaks: dict) -> str:
    lines = [f"{'kind':18s} {'n':>4s} {'2xx':>4s} {'4xx':>4s} {'5xx':>4s}  peak RSS rise (worst input)"]
    for kind in ROUND2_KINDS:
        c = report.by_kind.get(kind, Counter())
        cls = Counter()
        for st, v in c.items():
            cls[st // 100] += v
        mib, what = peaks.get(kind, (0.0, ""))
        lines.append(f"{kind:18s} {sum(c.values()):4d} {cls[2]:4d} {cls[4]:4d} {cls[5]:4d}  +{mib:.0f} MiB ({what})")
    lines.append(f"{report.n} requests in {report.elapsed_s:.1f} s; /health afterwards {report.health_after}; "
                 f"failures {len(report.failures)}")
    lines.extend(f"  {f}" for f in report.failures[:30])
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=2000, help="number of mutated files")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--timeout", type=float, default=20.0, help="seconds per request before it is a hang")
    ap.add_argument("--sample-every", type=int, default=10,
                    help="also POST every k-th file to /v1/white-balance or /v1/surfaces")
    ap.add_argument("--max-rss-growth-mb", type=float, default=None,
                    help="default: the posterior-model cache's capacity + 64 MB (fuzz.memory_bound_mb)")
    ap.add_argument("--real-dng", metavar="PATH", default=None,
                    help="also send dng_mutations of this real DNG (e.g. ../shared/data/raw/Blackmagic.dng), each "
                         "after two different images, and count the answers that depend on the previous upload")
    ap.add_argument("--round2", action="store_true",
                    help="send only the issue-17 inputs (hostile names and metadata, bad targets, JSON, PackBits "
                         "and CSV bombs, Host tricks): statuses by class and peak RSS rise per kind")
    ap.add_argument("--scale", type=float, default=1.0, help="--round2: size factor of the bombs")
    args = ap.parse_args(argv)
    if args.round2:
        rep, peaks = run_round2(scale=args.scale, timeout=args.timeout)
        print(round2_table(rep, peaks))
        bad5 = sum(v for st, v in rep.statuses.items() if st >= 500)
        return 0 if not rep.failures and not bad5 and rep.health_after == 200 else 1

    def progress(j, rep):
        print(f"  {j}/{args.n}: {dict(sorted(rep.statuses.items()))}, RSS {_rss_mb():.0f} MB", file=sys.stderr,
              flush=True)

    rep = run(args.n, seed=args.seed, timeout=args.timeout, sample_every=args.sample_every, progress=progress)
    print(rep.table())
    bound = memory_bound_mb() if args.max_rss_growth_mb is None else args.max_rss_growth_mb
    print(f"RSS growth bound {bound:.0f} MB")
    ok = not rep.failures and rep.health_after == 200 and rep.rss_growth_mb <= bound
    if args.real_dng:
        with open(args.real_dng, "rb") as fh:
            real, dependent = run_real_dng(fh.read(), seed=args.seed, timeout=args.timeout)
        print(f"\nreal DNG {args.real_dng}: {real.n // 2} mutations, each sent after two different images")
        print(real.table())
        classes = Counter()
        for s in real.statuses.elements():
            classes[f"{s // 100}xx"] += 1
        print(f"answers: {dict(sorted(classes.items()))}; hangs: "
              f"{sum('no answer' in f for f in real.failures)}; decodes that depend on the previous upload: "
              f"{len(dependent)}")
        ok = ok and not real.failures and not dependent and real.health_after == 200
    print("OK" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
