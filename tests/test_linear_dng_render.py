"""``POST /v1/white-balance`` of LinearRaw DNGs (PhotometricInterpretation
34892) rendered from their own samples (:func:`service.decode.linear_dng.linear_dng_full`),
for every encoding the reader takes: 16-bit integer, 32-bit and 16-bit
float samples, uncompressed, Adobe deflate (8) and deflate (32946, which
this LibRaw build does not open), with and without a predictor, in strips
and in tiles; all written by :func:`testing.dngwriter.write_linear_dng`
from a spectral scene.

The tolerances:

* The rendering here is ``format=tiff`` (16 bits), ``output=linear-sRGB``,
  ``white=as-shot`` and ``exposure=0``: the correction matrix ``M`` depends
  on the file's AsShotNeutral and ColorMatrix only (the tests check the
  answers' matrices agree), and with every white-balanced sample below
  :data:`recovery.highlights.HIGHLIGHT_START` (checked on the scene) no
  highlight blend or shoulder applies, so each output code is
  ``round(65535 clip(M x / 65535))`` of the full-resolution linear pixel
  ``x`` (uint16 codes). Two inputs that differ by at most ``d`` codes per
  channel then give outputs that differ by less than ``L d + 1`` codes,
  ``L = max_i sum_j |M_ij|`` (the clip is 1-Lipschitz, the rounding adds
  less than one).
* 16-bit integer samples, whatever their encoding, are the same samples as
  the uncompressed copy: ``d = 0``, identical outputs.
* Float samples ``s`` (white 1): the 16-bit copy holds ``round(65535 s)``
  (float64); the reader computes ``65535 s`` in float32 (relative error
  ``2^-24``, under 0.004 codes) before rounding, so the two differ by at
  most one code, where ``65535 s`` is that close to a half: ``d = 1``.
* LibRaw (uncompressed 16-bit integer samples, where it reads them right):
  its ``scale_colors`` truncates ``(v - black) * 65535 / (white - black)``
  where the reader rounds, so LibRaw's pixel is the reader's or one code
  below (measured: only 0 and -1 occur): ``d = 1``; its neutral is the
  reciprocal of a float32 multiplier, so its matrix differs by about
  ``1e-8`` (allowed ``1e-6``), worth ``65535 max_i sum_j |dM_ij|`` codes
  more (a fraction of one).
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import tifffile

from recovery.highlights import HIGHLIGHT_START
from testing.dngwriter import spectral_scene, write_linear_dng

from .conftest import isolated_app_client

BLACK, WHITE = 1024, 60000
CROP = (6, 10, 130, 200)                 # DefaultCrop: top, left, height, width
RENDER = dict(format="tiff", output="linear-sRGB", white="as-shot", exposure="0")


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"))


@pytest.fixture(scope="module")
def scene():
    """A ColorChecker under D65 seen by the Nikon D5100 (150 x 226), its
    camera RGB quantised to 16-bit samples between BLACK and WHITE, and the
    light's camera RGB (green 1) as AsShotNeutral."""
    sc = spectral_scene("Nikon 5100 (NPL)", "D65", 150, 226, seed=3, exposure=0.45)
    v = np.clip(sc.image.astype(np.float64), 0, 1)
    q = np.rint(BLACK + v * (WHITE - BLACK)).astype(np.uint16)
    neutral = np.asarray(sc.light_rgb_normalised, float)
    unit = (q.astype(np.float64) - BLACK) / (WHITE - BLACK)
    assert (unit / neutral).max() < HIGHLIGHT_START          # the rendering is linear (module docstring)
    return q, unit, neutral


def _dng(samples, neutral, **kw) -> bytes:
    buf = io.BytesIO()
    write_linear_dng(buf, samples, as_shot_neutral=neutral, default_crop=CROP, **kw)
    return buf.getvalue()


def _render(client, data: bytes):
    r = client.post("/v1/white-balance", files={"file": ("scene.dng", data, "application/octet-stream")},
                    data=RENDER)
    assert r.status_code == 200, r.text
    head = json.loads(r.headers["X-Illuminant"])
    return tifffile.imread(io.BytesIO(r.content)), np.array(head["correction_matrix"]), head


def _gain_bound(M: np.ndarray, d: int, M2: np.ndarray | None = None) -> int:
    """The largest output difference, in codes, for inputs ``d`` codes apart
    (module docstring), rendered by ``M`` and ``M2`` (default ``M``): plus
    ``65535 max_i sum_j |M_ij - M2_ij|`` for the matrices' difference."""
    dm = 0.0 if M2 is None else 65535 * np.abs(M - M2).sum(axis=1).max()
    return int(np.floor(np.abs(M).sum(axis=1).max() * d + dm + 1))


#: (samples, compression, predictor, tile or None for strips of 7 rows)
ENCODINGS = [
    ("uint16", "none", False, None), ("uint16", "none", False, (32, 48)),
    ("uint16", "adobe_deflate", False, (32, 48)), ("uint16", "adobe_deflate", True, None),
    ("uint16", "deflate", False, None), ("uint16", "deflate", True, (64, 64)),
    ("float32", "none", False, (32, 48)), ("float32", "adobe_deflate", False, None),
    ("float32", "adobe_deflate", True, (64, 64)), ("float32", "deflate", True, None),
    ("float16", "none", False, None), ("float16", "adobe_deflate", True, (32, 48)),
    ("float16", "deflate", False, (64, 64)),
]


@pytest.mark.parametrize("dtype,compression,predictor,tile", ENCODINGS)
def test_each_encoding_renders_as_its_uncompressed_16_bit_copy(client, scene, dtype, compression, predictor, tile):
    """Rotated (Orientation 6) and DefaultCropped: the answer for each
    encoding equals the one for an uncompressed 16-bit strip copy of the
    same samples, exactly for integer samples and within the float
    quantisation (``L * 1 + 1`` codes, module docstring) for floats."""
    q, unit, neutral = scene
    layout = dict(tile=tile) if tile else dict(rows_per_strip=7)
    if dtype == "uint16":
        samples, levels = q, dict(black_level=BLACK, white_level=WHITE)
        copy, copy_levels, d = q, levels, 0
    else:
        samples, levels = unit.astype(dtype), {}
        copy = np.rint(np.clip(samples.astype(np.float64), 0, 1) * 65535).astype(np.uint16)
        copy_levels, d = dict(black_level=0, white_level=65535), 1
    got, M, head = _render(client, _dng(samples, neutral, compression=compression, predictor=predictor,
                                        orientation=6, **layout, **levels))
    ref, M_ref, _ = _render(client, _dng(copy, neutral, orientation=6, **copy_levels))
    assert got.shape == ref.shape == (CROP[3], CROP[2], 3)        # the crop, turned a quarter
    np.testing.assert_allclose(M, M_ref, rtol=1e-12, atol=0)
    assert ref.max() > 20000                                       # a picture, not a black frame
    diff = np.abs(got.astype(np.int64) - ref)
    assert diff.max() <= _gain_bound(M, d), (diff.max(), _gain_bound(M, d))
    assert any("own samples" in w for w in head["warnings"])


@pytest.mark.parametrize("orientation", [1, 3, 6, 8])
def test_uncompressed_16_bit_matches_libraw(client, scene, monkeypatch, orientation):
    """Where LibRaw reads the file right (uncompressed 16-bit integers), its
    full-resolution image (the former path, forced by turning the reader
    off) is the reader's or one code below, oriented alike; the answers
    then differ by at most ``L * 1 + 1`` codes (module docstring)."""
    import service.decode.linear_dng as L
    from service.decode.upload import decode_upload

    q, _, neutral = scene
    data = _dng(q, neutral, black_level=BLACK, white_level=WHITE, orientation=orientation)
    ours_img = decode_upload(data, "a.dng", max_pixels=10 ** 8, estimation_pixels=10 ** 8)
    ours = ours_img.full_linear()
    got, M, _ = _render(client, data)
    monkeypatch.setattr(L, "linear_dng_estimation", lambda *a, **k: None)
    lib_img = decode_upload(data, "a.dng", max_pixels=10 ** 8, estimation_pixels=10 ** 8)
    assert "LibRaw's own" in lib_img.warnings[-1]
    lib = lib_img.full_linear()
    assert ours.shape == lib.shape == tuple(ours_img.full_shape) + (3,)
    step = lib.astype(np.int64) - ours
    assert set(np.unique(step)) <= {-1, 0}, np.unique(step)
    ref, M_lib, _ = _render(client, data)
    np.testing.assert_allclose(M, M_lib, rtol=0, atol=1e-6)      # LibRaw's neutral: 1 / a float32 multiplier
    assert got.shape == ref.shape
    assert np.abs(got.astype(np.int64) - ref).max() <= _gain_bound(M, 1, M_lib)


def test_linearization_table_is_applied(client, scene):
    """Integer samples through a LinearizationTable render as an
    uncompressed copy holding the table's values: the same numbers."""
    q, _, neutral = scene
    idx = (q >> 4).astype(np.uint16)                      # 12-bit indices
    lut = np.rint(np.linspace(0, 1, 4096) ** 1.5 * 65535).astype(np.uint16)
    got, _, _ = _render(client, _dng(idx, neutral, linearization=lut, compression="deflate", tile=(32, 48),
                                     white_level=65535, orientation=3))
    ref, _, _ = _render(client, _dng(lut[idx], neutral, white_level=65535, orientation=3))
    assert got.max() > 10000 and np.array_equal(got, ref)       # (the indices alone: under 4096)


def _damaged(data: bytes, n: int) -> bytes:
    """``data`` with the second half of the raw image's segment ``n`` zeroed."""
    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        page = tf.pages[0]
        off, cnt = int(page.dataoffsets[n]), int(page.databytecounts[n])
    out = bytearray(data)
    out[off + cnt // 2:off + cnt] = bytes(cnt - cnt // 2)
    return bytes(out)


@pytest.mark.parametrize("compression", ["adobe_deflate", "deflate"])
@pytest.mark.parametrize("dtype", ["uint16", "float32"])
def test_a_damaged_deflate_tile_is_a_422_naming_it(client, scene, compression, dtype):
    """Tile 7 of a 226-pixel-wide image in 32 x 48 tiles (5 across): the
    second tile row, third column."""
    q, unit, neutral = scene
    samples, levels = (q, dict(black_level=BLACK, white_level=WHITE)) if dtype == "uint16" else (
        unit.astype(np.float32), {})
    data = _damaged(_dng(samples, neutral, compression=compression, tile=(32, 48), **levels), 7)
    r = client.post("/v1/white-balance", files={"file": ("scene.dng", data, "application/octet-stream")},
                    data=RENDER)
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["error"] == "corrupt_file"
    assert "tile 7 (rows 32-63, columns 96-143)" in body["detail"] and "deflate" in body["detail"], body


def test_a_truncated_strip_is_a_422_not_a_500(client, scene):
    q, _, neutral = scene
    data = _dng(q, neutral, black_level=BLACK, white_level=WHITE, compression="deflate", rows_per_strip=16)
    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        page = tf.pages[0]
        last = int(page.dataoffsets[-1]) + int(page.databytecounts[-1]) // 2
    r = client.post("/v1/white-balance", files={"file": ("scene.dng", data[:last], "application/octet-stream")},
                    data=RENDER)
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "corrupt_file" and r.json()["detail"]


def test_full_image_holds_the_image_and_a_segment_not_libraws_buffers(rng):
    """1000 x 1500 float32 samples in 256-pixel deflate tiles: the reader's
    peak (tracemalloc: Python's and numpy's allocations) is the 9 MB uint16
    image plus one decoded tile and its float32 temporaries (a few MiB),
    where a decode of the whole image first would add its 18 MB float32
    copy, and LibRaw's full decode about 24 MiB per megapixel
    (``benchmarks.request_costs``)."""
    import tracemalloc

    from service.decode.linear_dng import linear_dng_full

    img = np.ascontiguousarray(np.broadcast_to(rng.uniform(0.1, 0.8, (1, 1500, 3)).astype(np.float32),
                                               (1000, 1500, 3)))
    buf = io.BytesIO()
    write_linear_dng(buf, img, compression="adobe_deflate", predictor=True, tile=(256, 256), orientation=8)
    data = buf.getvalue()
    del img
    tracemalloc.start()
    out = linear_dng_full(data, 1000, 1500, 5)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert out.shape == (1500, 1000, 3)
    assert peak < out.nbytes + 4 * 2 ** 20, peak - out.nbytes


@pytest.mark.parametrize("flip", range(8))
def test_written_in_place_is_the_oriented_image(rng, flip):
    """Each segment written through the inverse view lands where
    ``FLIP_OPS[flip]`` of the whole image puts it."""
    from service.decode import FLIP_OPS
    from service.decode.linear_dng import linear_dng_full

    img = rng.integers(0, 65536, (40, 56, 3)).astype(np.uint16)
    buf = io.BytesIO()
    write_linear_dng(buf, img, tile=(16, 16))
    out = linear_dng_full(buf.getvalue(), 40, 56, flip)
    assert np.array_equal(out, FLIP_OPS[flip](img))


def test_per_sample_black_levels_match_libraw(client, scene, monkeypatch):
    """BlackLevel with one value per sample: the reader's image (from
    deflate tiles) has each channel scaled by its own black, within the
    samples' rounding (0.56 codes) and the output's (0.5) of the scene, and
    is LibRaw's (from the uncompressed copy: it cannot read 16-bit deflate
    ones) to LibRaw's truncation (one code)."""
    import service.decode.linear_dng as L
    from service.decode.upload import decode_upload

    _, unit, neutral = scene
    blacks = np.array([1024, 1100, 980])
    q = np.rint(blacks + unit * (WHITE - blacks)).astype(np.uint16)
    kw = dict(black_level=blacks, white_level=WHITE, orientation=8)
    ours = decode_upload(_dng(q, neutral, compression="deflate", tile=(64, 64), **kw), "a.dng",
                         max_pixels=10 ** 8, estimation_pixels=10 ** 8).full_linear()
    monkeypatch.setattr(L, "linear_dng_estimation", lambda *a, **k: None)
    lib = decode_upload(_dng(q, neutral, **kw), "a.dng", max_pixels=10 ** 8, estimation_pixels=10 ** 8).full_linear()
    assert ours.shape == lib.shape
    assert set(np.unique(lib.astype(np.int64) - ours)) <= {-1, 0}
    expect = np.rint(np.rot90(unit, 1) * 65535)         # Orientation 8: flip 5, a quarter turn anticlockwise
    assert np.abs(ours - expect).max() <= 1


def test_a_tile_without_data_is_never_left_uninitialised(rng):
    """TileByteCounts 0 for tile 5 (5 tiles across 130 columns: the second
    row's first): the upload's structure check refuses
    such a file first; the reader itself refuses it too (a 422 naming the
    tile), rather than leave those pixels as whatever memory held."""
    from service.decode.linear_dng import linear_dng_full
    from service.errors import ServiceError

    img = rng.integers(0, 65536, (100, 130, 3)).astype(np.uint16)
    buf = io.BytesIO()
    write_linear_dng(buf, img, tile=(32, 32), compression="deflate")
    buf.seek(0)
    with tifffile.TiffFile(buf, mode="r+b") as tf:
        tag = tf.pages[0].tags[325]
        counts = list(tag.value)
        counts[5] = 0
        tag.overwrite(counts)
    with pytest.raises(ServiceError) as e:
        linear_dng_full(buf.getvalue(), 100, 130, 0, label="'x.dng'")
    assert e.value.status == 422 and "tile 5 (rows 32-63, columns 0-31)" in e.value.detail, e.value.detail


@pytest.mark.parametrize("fmt", ["png", "png16", "jpeg"])
@pytest.mark.parametrize("dtype,compression,tile", [("uint16", "deflate", (32, 48)), ("float32", "adobe_deflate", None)])
def test_png_and_jpeg_strip_by_strip_are_the_whole_image_path(client, scene, monkeypatch, fmt, dtype, compression,
                                                             tile):
    """Unrotated, DefaultCropped: a PNG or JPEG made strip by strip from the
    file's strips or tiles (``timings_ms.render``) has the pixels of the
    whole-image path (``timings_ms.demosaic``), bit for bit: the same
    scaling of the same samples, the same correction chunks
    (:mod:`service.strips`)."""
    import cv2

    from service import strips

    q, unit, neutral = scene
    samples, levels = (q, dict(black_level=BLACK, white_level=WHITE)) if dtype == "uint16" else (
        unit.astype(np.float32), {})
    layout = dict(tile=tile) if tile else dict(rows_per_strip=16)
    data = _dng(samples, neutral, compression=compression, **layout, **levels)
    fields = dict(RENDER, format=fmt)

    def post():
        r = client.post("/v1/white-balance", files={"file": ("scene.dng", data, "application/octet-stream")},
                        data=fields)
        assert r.status_code == 200, r.text
        img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        return img, json.loads(r.headers["X-Illuminant"])["timings_ms"]

    by_strips, t_strips = post()
    monkeypatch.setattr(strips, "linear_rows", lambda *a, **k: None)
    whole, t_whole = post()
    assert "render" in t_strips and "demosaic" not in t_strips and "demosaic" in t_whole
    assert by_strips.shape == whole.shape == (CROP[2], CROP[3], 3)
    assert whole.max() > (100 if whole.dtype == np.uint8 else 20000)
    assert np.array_equal(by_strips, whole)


def test_strip_rows_are_the_full_images_rows(rng):
    """Any rows of :class:`LinearRawRows` (strips of 7 rows or 32 x 48
    tiles, cropped) are those rows of :func:`linear_dng_full`."""
    from service.decode.linear_dng import LinearRawRows, linear_dng_full

    img = rng.uniform(-0.01, 1.02, (100, 130, 3)).astype(np.float32)
    for layout in (dict(rows_per_strip=7), dict(tile=(32, 48))):
        buf = io.BytesIO()
        write_linear_dng(buf, img, compression="deflate", predictor=True, **layout)
        full = linear_dng_full(buf.getvalue(), 100, 130, 0)
        rows = LinearRawRows.of(buf.getvalue(), 100, 130, 0, lambda shape: (5, 97, 3, 120))
        assert rows.shape == (92, 117)
        for r0, r1 in ((0, 92), (0, 1), (30, 65), (91, 92), (10, 11)):
            assert np.array_equal(rows(r0, r1), full[5 + r0:5 + r1, 3:120]), (layout, r0, r1)
        assert LinearRawRows.of(buf.getvalue(), 100, 130, 6, lambda shape: None) is None    # rotated
