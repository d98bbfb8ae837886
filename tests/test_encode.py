"""The strip-parallel PNG encoder (service.encode, issue 19): lossless, a
valid zlib stream whatever the strips, readable by libpng (OpenCV) and
Pillow, and the metadata chunks still embed."""

from __future__ import annotations

import io
import struct
import zlib

import cv2
import numpy as np
import pytest
from PIL import Image

from service import encode, outputs


def _chunks(png: bytes):
    assert png[:8] == encode.PNG_SIGNATURE
    pos = 8
    while pos < len(png):
        n = struct.unpack(">I", png[pos:pos + 4])[0]
        ctype, data = png[pos + 4:pos + 8], png[pos + 8:pos + 8 + n]
        crc = struct.unpack(">I", png[pos + 8 + n:pos + 12 + n])[0]
        assert crc == zlib.crc32(ctype + data) & 0xFFFFFFFF
        yield ctype, data
        pos += 12 + n


def test_adler32_combine_matches_zlib():
    rng = np.random.default_rng(0)
    for n1, n2 in ((0, 5), (1, 1), (100, 70000), (65521, 3), (200000, 131071)):
        a, b = rng.integers(0, 256, n1, dtype=np.uint8).tobytes(), rng.integers(0, 256, n2, dtype=np.uint8).tobytes()
        assert encode.adler32_combine(zlib.adler32(a), zlib.adler32(b), len(b)) == zlib.adler32(a + b)


@pytest.mark.parametrize("shape,dtype", [((1, 1, 3), np.uint8), ((5, 7, 3), np.uint8), ((64, 33, 3), np.uint8),
                                         ((40, 21, 3), np.uint16), ((3, 2, 3), np.uint16)])
@pytest.mark.parametrize("threads", [1, 2, 5])
def test_png_round_trip_exact_with_many_strips(monkeypatch, shape, dtype, threads):
    monkeypatch.setattr(encode, "MIN_STRIP_BYTES", 1)          # a strip per few rows, even for small images
    rng = np.random.default_rng(1)
    img = rng.integers(0, np.iinfo(dtype).max + 1, shape).astype(dtype)
    img[: shape[0] // 2, : shape[1] // 2] = img[0, 0]          # a flat area: runs
    png = encode.png_encode(img, threads)
    chunks = list(_chunks(png))
    assert chunks[0][0] == b"IHDR" and chunks[-1][0] == b"IEND"
    W, H, bits, ctype = struct.unpack(">IIBB", chunks[0][1][:10])
    assert (H, W, bits, ctype) == (shape[0], shape[1], 8 * img.itemsize, 2)
    idat = b"".join(d for t, d in chunks if t == b"IDAT")
    raw = zlib.decompress(idat)                                  # checks the combined Adler-32
    assert len(raw) == shape[0] * (1 + shape[1] * 3 * img.itemsize)
    back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(back[..., ::-1], img)
    if dtype == np.uint8:
        np.testing.assert_array_equal(np.asarray(Image.open(io.BytesIO(png)).convert("RGB")), img)


def test_png_is_what_opencv_decodes_for_a_photo_sized_image():
    """Default strips (several per thread) on an image large enough to have them."""
    rng = np.random.default_rng(2)
    img = np.clip(rng.normal(120, 30, (1200, 1500, 3)), 0, 255).astype(np.uint8)
    png = encode.png_encode(img, threads=2)
    assert sum(t == b"IDAT" for t, _ in _chunks(png)) > 2
    back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    np.testing.assert_array_equal(back[..., ::-1], img)


def test_metadata_chunks_embed_after_ihdr():
    img = np.full((8, 8, 3), 200, np.uint8)
    png = outputs.embed(encode.png_encode(img), "png", outputs.shipped_icc("sRGB"), None, {"k": "v"})
    types = [t for t, _ in _chunks(png)]
    assert types[:3] == [b"IHDR", b"iCCP", b"iTXt"]
    assert Image.open(io.BytesIO(png)).info.get("icc_profile") == outputs.shipped_icc("sRGB")


def test_rejects_what_it_cannot_write():
    with pytest.raises(ValueError):
        encode.png_encode(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError):
        encode.png_encode(np.zeros((0, 4, 3), np.uint8))


@pytest.mark.parametrize("shape", [(1200, 1801), (1237, 2001), (2050, 1100)])
def test_jpeg_in_strips_decodes_to_the_one_piece_pixels(shape):
    """Strips joined with restart markers: libjpeg (OpenCV) and Pillow
    decode exactly the pixels of OpenCV's one-piece encode."""
    rng = np.random.default_rng(4)
    y, x = np.mgrid[:shape[0], :shape[1]]
    img = np.stack([(x * 255 // shape[1]), (y * 255 // shape[0]), ((x + y) % 256)], -1).astype(np.uint8)
    img = np.clip(img + rng.normal(0, 8, img.shape), 0, 255).astype(np.uint8)
    joined = encode.jpeg_encode(img, 95, threads=2)
    assert b"\xff\xdd" in joined[:2000] and b"\xff\xd0" in joined              # DRI, RST0: it was split
    ok, one = cv2.imencode(".jpg", np.ascontiguousarray(img[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
    for decode in (lambda b: cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_COLOR)[..., ::-1],
                   lambda b: np.asarray(Image.open(io.BytesIO(b)).convert("RGB"))):
        np.testing.assert_array_equal(decode(joined), decode(one.tobytes()))
    assert Image.open(io.BytesIO(joined)).size == (shape[1], shape[0])


def test_small_jpeg_is_one_piece_and_embeds():
    img = np.full((40, 60, 3), 90, np.uint8)
    jpg = encode.jpeg_encode(img, 95, threads=4)
    assert b"\xff\xdd" not in jpg
    out = outputs.embed(jpg, "jpeg", outputs.shipped_icc("sRGB"), outputs.exif_block({"Make": "X"}))
    assert Image.open(io.BytesIO(out)).info.get("icc_profile") == outputs.shipped_icc("sRGB")


def test_tiff_answer_from_memory_is_the_encoded_file():
    """A TIFF answer is tiff_head's bytes then the pixels from memory
    (issue 19): byte for byte the file encode_image writes, for a crop (a
    view that is not contiguous) as for a whole image."""
    import asyncio

    from service import pipeline
    from service.routers.analysis import _from_memory

    rng = np.random.default_rng(5)
    full = rng.integers(0, 65536, size=(700, 520, 3), dtype=np.uint16)
    meta = {"icc": b"\0" * 3144, "facts": {"Make": "Nikon", "Model": "D5100", "ImageDescription": "a caption",
                                           "Software": "wandell-recovery", "XMP": "<x:xmpmeta/>"}}
    for img in (full, full[13:690, 7:511]):
        head = pipeline.tiff_head(img, meta)
        assert head is not None
        whole = pipeline.encode_image(np.ascontiguousarray(img), "tiff", meta=meta)

        async def collect():
            return b"".join([bytes(c) async for c in _from_memory(head, img)])

        assert asyncio.run(collect()) == whole
