"""TIFF/DNG structural verification: every strip and tile LibRaw may decode is inside the file
and consistent with its IFD (a file one byte short would otherwise decode silently from
memory), the structure tags read exactly, duplicates and malformed values refused.
"""

from __future__ import annotations

import struct

from ..errors import ServiceError
from .formats import _sniff


# LibRaw decodes into a buffer it does not clear: a strip or tile that is
# missing, short, outside the file or damaged leaves part of that buffer as
# the previous decode left it, i.e. another upload's pixels (issue 10). So
# before LibRaw unpacks a TIFF-structured file (DNG, NEF, CR2, ARW, ...; any
# file starting with a byte-order mark, since LibRaw ignores the magic
# number), the IFDs are walked here, independently of tifffile, and every
# IFD that has image data must declare strips or tiles that the file really
# contains. What cannot be verified is refused.

#: Bytes per value of each TIFF field type (TIFF 6.0 section 2; 13 = IFD,
#: 16-18 = BigTIFF 8-byte types).
_TIFF_TYPE_SIZES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 13: 4,
                    16: 8, 17: 8, 18: 8}
_IFD_LIMIT = 64                 # IFDs (chain and SubIFDs) walked before giving up
_ENTRY_LIMIT = 4096             # entries in one IFD
#: Tags whose value decides where LibRaw reads pixels: read here exactly,
#: refused when duplicated or malformed.
_STRUCTURE_TAGS = (254, 256, 257, 258, 259, 262, 273, 277, 278, 279, 284, 322, 323, 324, 325, 330)
_TAG_NAMES = {254: "NewSubfileType", 256: "ImageWidth", 257: "ImageLength", 258: "BitsPerSample",
              259: "Compression", 262: "PhotometricInterpretation", 273: "StripOffsets", 277: "SamplesPerPixel",
              278: "RowsPerStrip", 279: "StripByteCounts", 284: "PlanarConfiguration", 322: "TileWidth",
              323: "TileLength", 324: "TileOffsets", 325: "TileByteCounts", 330: "SubIFDs"}
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
_PHOTOMETRIC_RAW = (32803, 34892)   # CFA, LinearRaw: the IFDs LibRaw takes a DNG's pixels from


class _Unverifiable(Exception):
    """The TIFF structure says something the decode cannot be trusted with."""


def _ifd_values(data: bytes, bo: str, typ: int, count: int, pos: int) -> list[int]:
    size = _TIFF_TYPE_SIZES.get(typ)
    if size is None or typ not in (1, 3, 4, 6, 8, 9, 13, 16, 17):
        raise _Unverifiable(f"field type {typ} where an integer is expected")
    if count > len(data) // size:
        raise _Unverifiable(f"a count of {count} values cannot fit in the file")
    if count * size > 4:
        (pos,) = struct.unpack_from(bo + "I", data, pos)
    if pos + count * size > len(data):
        raise _Unverifiable(f"values at bytes {pos}..{pos + count * size} lie beyond the end of the file")
    fmt = {1: "B", 3: "H", 4: "I", 6: "b", 8: "h", 9: "i", 13: "I", 16: "Q", 17: "q"}[typ]
    return list(struct.unpack_from(f"{bo}{count}{fmt}", data, pos))


def _read_ifd(data: bytes, bo: str, off: int) -> tuple[dict, int, tuple[int, int]]:
    """``({tag: [values]}, next-IFD offset, (start, end) of the IFD)`` for
    the structure tags of the IFD at ``off``."""
    if off < 8 or off + 2 > len(data):
        raise _Unverifiable(f"an IFD at byte {off} is outside the {len(data)}-byte file")
    (n,) = struct.unpack_from(bo + "H", data, off)
    end = off + 2 + 12 * n + 4
    if n == 0 or n > _ENTRY_LIMIT or end > len(data):
        why = "past the end of the file" if end > len(data) else "implausible"
        raise _Unverifiable(f"the IFD at byte {off} declares {n} entries ({why})")
    tags: dict = {}
    for i in range(n):
        pos = off + 2 + 12 * i
        tag, typ, count = struct.unpack_from(bo + "HHI", data, pos)
        if tag not in _STRUCTURE_TAGS:
            continue
        if tag in tags:
            raise _Unverifiable(f"{_TAG_NAMES[tag]} (tag {tag}) appears twice in the IFD at byte {off}")
        try:
            tags[tag] = _ifd_values(data, bo, typ, count, pos + 8)
        except _Unverifiable as exc:
            raise _Unverifiable(f"{_TAG_NAMES[tag]} (tag {tag}) of the IFD at byte {off}: {exc}") from None
    (nxt,) = struct.unpack_from(bo + "I", data, end - 4)
    return tags, nxt, (off, end)


def _one(tags: dict, tag: int, default=None):
    v = tags.get(tag)
    if v is None:
        return default
    if len(v) != 1:
        raise _Unverifiable(f"{_TAG_NAMES[tag]} (tag {tag}) has {len(v)} values, not 1")
    return int(v[0])


def _check_jpeg(data: bytes, start: int, end: int, raw_ifd: bool, tile_w: int, tile_h: int, spp: int) -> None:
    """The marker segments of one (lossless) JPEG strip or tile in
    ``data[start:end]``: SOI, well-formed DQT/DHT/SOF/SOS segments inside
    the range and, for the raw image, a frame LibRaw's DNG decoder reads
    (SOF3 lossless or SOF1) whose samples cover the whole tile."""
    if data[start:start + 2] != b"\xff\xd8":
        raise _Unverifiable(f"the JPEG data at byte {start} does not start with an SOI marker")
    p, sof, huffman = start + 2, None, set()
    while True:
        if p + 4 > end or data[p] != 0xFF:
            raise _Unverifiable(f"the JPEG data at byte {start} has no valid marker at byte {p}")
        m = data[p + 1]
        if m == 0xFF:
            p += 1
            continue
        if m == 0x01 or 0xD0 <= m <= 0xD8 or m == 0xD9:
            raise _Unverifiable(f"the JPEG data at byte {start} has marker {m:02X} before its scan")
        (length,) = struct.unpack_from(">H", data, p + 2)
        seg, seg_end = p + 4, p + 2 + length
        if length < 2 or seg_end > end:
            raise _Unverifiable(f"the JPEG segment {m:02X} at byte {p} has length {length}, outside its data")
        if m == 0xC4:                       # DHT: class/id, 16 counts, the values; exactly filled
            q = seg
            while q < seg_end:
                tc, th = data[q] >> 4, data[q] & 15
                if tc > 1 or th > 3 or q + 17 > seg_end:
                    raise _Unverifiable(f"the JPEG Huffman table at byte {q} is malformed")
                q += 17 + sum(data[q + 1:q + 17])
                huffman.add((tc, th))
            if q != seg_end:
                raise _Unverifiable(f"the JPEG Huffman tables at byte {p} overrun their segment")
        elif m == 0xDB:                     # DQT: precision/id, 64 or 128 bytes; exactly filled
            q = seg
            while q < seg_end:
                pq, tq = data[q] >> 4, data[q] & 15
                if pq > 1 or tq > 3:
                    raise _Unverifiable(f"the JPEG quantisation table at byte {q} is malformed")
                q += 1 + 64 * (1 + pq)
            if q != seg_end:
                raise _Unverifiable(f"the JPEG quantisation tables at byte {p} overrun their segment")
        elif m in _JPEG_SOF:
            if sof is not None or length < 8:
                raise _Unverifiable(f"the JPEG data at byte {start} has a second or short frame header")
            prec, height, width, nc = struct.unpack_from(">BHHB", data, seg)
            if length != 8 + 3 * nc or not 1 <= nc <= 4 or not 2 <= prec <= 16 or height < 1 or width < 1:
                raise _Unverifiable(f"the JPEG frame header at byte {p} is malformed (precision {prec}, "
                                    f"{width}x{height}, {nc} components, length {length})")
            sof = (m, height, width, nc)
        elif m == 0xDA:                     # SOS: the entropy-coded data follows
            ns = data[seg] if seg < seg_end else 0
            if sof is None or length != 6 + 2 * ns or not 1 <= ns <= sof[3] or seg_end >= end:
                raise _Unverifiable(f"the JPEG scan header at byte {p} is malformed or has no frame before it")
            break
        p = seg_end
    kind, height, width, nc = sof
    if not raw_ifd and kind != 0xC3:
        return
    if kind not in (0xC1, 0xC3) or not huffman:
        raise _Unverifiable(f"the raw image's JPEG at byte {start} is not a lossless (SOF3) or SOF1 JPEG "
                            f"with Huffman tables (frame type {kind:02X})")
    if kind == 0xC3:
        covered = width * height * nc >= tile_w * tile_h * spp
    else:   # LibRaw reads 8x8 blocks; two tile rows per JPEG row
        covered = nc == 1 and tile_w % 8 == 0 and width // 8 * 8 >= 2 * tile_w and 2 * (height // 8 * 8) >= tile_h
    if not covered:
        raise _Unverifiable(f"the JPEG at byte {start} ({width}x{height}, {nc} component(s)) does not cover its "
                            f"{tile_w}x{tile_h} tile")


def _check_image_ifd(data: bytes, tags: dict, where: str, is_dng: bool, structure: list) -> None:
    """Strips or tiles of one IFD: present in pairs, as many as the image
    needs, each inside the file, after the header and outside every IFD,
    complete when uncompressed, and (JPEG-compressed) with valid markers."""
    size = len(data)
    tiled = 324 in tags or 325 in tags or 322 in tags or 323 in tags
    if tiled and (273 in tags or 279 in tags):
        raise _Unverifiable(f"{where} has both strips and tiles")
    offs, cnts = (tags.get(324), tags.get(325)) if tiled else (tags.get(273), tags.get(279))
    if offs is None or cnts is None:
        raise _Unverifiable(f"{where} has image data offsets without byte counts (or the reverse)")
    if len(offs) != len(cnts) or not offs:
        raise _Unverifiable(f"{where} declares {len(offs)} data offsets but {len(cnts)} byte counts")
    width, height = _one(tags, 256), _one(tags, 257)
    spp, planar, compression = _one(tags, 277, 1), _one(tags, 284, 1), _one(tags, 259, 1)
    photometric = _one(tags, 262)
    bps = tags.get(258) or [1]
    raw_ifd = is_dng and photometric in _PHOTOMETRIC_RAW
    geometry = width is not None and height is not None
    if (is_dng or tiled) and not geometry:
        raise _Unverifiable(f"{where} has image data but no image width and length")
    tile_w = tile_h = None
    if geometry:
        if width < 1 or height < 1 or spp < 1:
            raise _Unverifiable(f"{where} declares a {width}x{height} image of {spp} samples")
        planes = spp if planar == 2 else 1
        if tiled:
            tile_w, tile_h = _one(tags, 322), _one(tags, 323)
            if not tile_w or not tile_h:
                raise _Unverifiable(f"{where} has tiles without a tile width and length")
            expected = -(-width // tile_w) * -(-height // tile_h) * planes
        else:
            rows = _one(tags, 278, 2**32 - 1) or 2**32 - 1
            tile_w, tile_h = width, min(rows, height)
            expected = -(-height // tile_h) * planes if is_dng else len(offs)
        if len(offs) != expected:
            grid = f"{tile_w}x{tile_h} {'tiles' if tiled else 'strips'}"
            raise _Unverifiable(f"{where} declares {len(offs)} {'tiles' if tiled else 'strips'}; a "
                                f"{width}x{height} image in {grid} needs {expected}")
    for k, (off, cnt) in enumerate(zip(offs, cnts)):
        what = f"{'tile' if tiled else 'strip'} {k} of {where} (bytes {off}..{off + cnt})"
        if off <= 0 or cnt <= 0:
            raise _Unverifiable(f"{what} is empty or at offset 0")
        if off + cnt > size:
            raise _Unverifiable(f"{what} lies beyond the end of the {size}-byte file (truncated?)")
        if off < 8 or any(off < e and s < off + cnt for s, e in structure):
            raise _Unverifiable(f"{what} overlaps the TIFF header or an IFD")
        if not geometry:
            continue
        if compression == 1:
            rows = tile_h if tiled else min(tile_h, height - k % -(-height // tile_h) * tile_h)
            bits = tile_w * (1 if planar == 2 else spp) * max(int(b) for b in bps)
            need = -(-bits // 8) * rows
            if cnt < need:
                raise _Unverifiable(f"{what} holds {cnt} bytes; its uncompressed pixels need {need}")
        elif compression == 7:
            _check_jpeg(data, off, off + cnt, raw_ifd, tile_w, tile_h, 1 if planar == 2 else spp)


def _tiff_structured(data: bytes) -> bool:
    """Whether LibRaw reads ``data`` as a TIFF: a byte-order mark (LibRaw
    ignores the magic number), except the TIFF-like formats with their own
    layout (Panasonic RW2, Olympus ORF, Canon CRW), not verified here."""
    return data[:2] in (b"II", b"MM") and _sniff(data) not in ("Panasonic RW2", "Olympus ORF", "Canon CRW")


def _check_tiff_structure(data: bytes) -> None:
    """Verify every strip and tile of a TIFF-structured RAW before LibRaw
    decodes it.

    Walks IFD 0, its next-IFD chain and SubIFDs (each IFD once, at most
    :data:`_IFD_LIMIT`) with its own reader, and checks every IFD holding
    image data (:func:`_check_image_ifd`).

    Parameters
    ----------
    data : bytes
        The whole file, starting with ``II`` or ``MM``.

    Raises
    ------
    ServiceError
        422 ``corrupt_file`` naming the first thing that is missing, outside
        the file or inconsistent: LibRaw would decode such a file partly
        from memory that the previous decode left behind.
    """
    bo = "<" if data[:2] == b"II" else ">"
    try:
        if len(data) < 8:
            raise _Unverifiable("the file ends inside the TIFF header")
        (first,) = struct.unpack_from(bo + "I", data, 4)
        is_dng = first + 2 <= len(data) and 50706 in _tags_present(data, bo, first)
        todo, seen, structure, images = [first], set(), [(0, 8)], []
        while todo:
            off = todo.pop(0)
            while off and off not in seen:
                if len(seen) >= _IFD_LIMIT:
                    raise _Unverifiable(f"more than {_IFD_LIMIT} IFDs")
                seen.add(off)
                tags, nxt, span = _read_ifd(data, bo, off)
                structure.append(span)
                todo.extend(tags.get(330, ()))
                if any(t in tags for t in (273, 279, 324, 325)):
                    images.append((tags, f"the IFD at byte {off}"))
                off = nxt
        if not images:
            raise _Unverifiable("no IFD declares image data")
        for tags, where in images:
            _check_image_ifd(data, tags, where, is_dng, structure)
    except _Unverifiable as exc:
        raise ServiceError(422, "corrupt_file",
                          f"the file's TIFF structure cannot be verified: {exc}; it is truncated or damaged "
                          "(refused rather than decoded partly from memory)") from None
    except (struct.error, OverflowError, MemoryError, ValueError) as exc:
        raise ServiceError(422, "corrupt_file",
                          f"the file's TIFF structure cannot be verified ({type(exc).__name__}: {exc}); it is "
                          "truncated or damaged") from None


def _tags_present(data: bytes, bo: str, off: int) -> set:
    (n,) = struct.unpack_from(bo + "H", data, off)
    n = min(n, (len(data) - off - 2) // 12)
    return {struct.unpack_from(bo + "H", data, off + 2 + 12 * i)[0] for i in range(max(0, n))}
