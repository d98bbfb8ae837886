"""PNG and JPEG outputs made strip by strip from the RAW's mosaic
(service.strips, issue 19): the same pixels as the whole-image path
(demosaic, correction, encoder), bit for bit."""

from __future__ import annotations

import os

import cv2
import numpy as np
import pytest

from service import correction, encode, pipeline, strips
from service.decode.raw import _OPENCV_BAYER
from service.options import FORMATS
from service.settings import get_settings
from testing.dngwriter import scene_dng

BLACKMAGIC = os.path.join(os.environ.get("WANDELL_SHARED_DIR") or os.path.join(
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "shared"),
    "data", "raw", "Blackmagic.dng")


@pytest.mark.parametrize("code", sorted(_OPENCV_BAYER.values()))
@pytest.mark.parametrize("bounds", [None, (3, 117, 5, 90), (1, 120, 0, 96)])
def test_strips_demosaic_like_the_whole_mosaic(code, bounds):
    """OpenCV's edge-aware interpolation of a strip with strips.MARGIN rows
    on either side, started on the filter's phase, equals those rows of the
    whole mosaic's (an odd crop top included)."""
    rng = np.random.default_rng(1)
    mos = rng.integers(0, 65536, (120, 96), dtype=np.uint16)
    whole = cv2.cvtColor(mos, getattr(cv2, code))
    src = strips.MosaicRows(mos, getattr(cv2, code), bounds)
    r0, r1, c0, c1 = bounds or (0, 120, 0, 96)
    H = r1 - r0
    for step in (1, 2, 7, 16, H):
        got = np.concatenate([src(r, min(H, r + step)) for r in range(0, H, step)])
        np.testing.assert_array_equal(got, whole[r0:r1, c0:c1])


@pytest.fixture(scope="module", params=["RGGB", "GBRG"])
def bright_dng(request, tmp_path_factory):
    """A DNG with clipped highlights (the correction's mixed chunks)."""
    p = tmp_path_factory.mktemp("strips") / "a.dng"
    scene_dng(p, "Nikon 5100 (NPL)", "A", 200, 240, seed=5, grid=(4, 6), pattern=request.param,
              exposure=1.0)
    return p.read_bytes()


def _decoded_pixels(data: bytes) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return np.ascontiguousarray(img[..., ::-1])


def _both(data: bytes, fmt_name: str, threads=None, exposure=None):
    s = get_settings()
    fmt = FORMATS[fmt_name]
    d0, r0 = pipeline.analyze(data, "a.dng", s, keep_mosaic=True)
    whole, M0, info0, _ = pipeline.render_corrected(d0, r0, target="D65", output="sRGB", fmt=fmt,
                                                    exposure=exposure)
    d1, r1 = pipeline.analyze(data, "a.dng", s, keep_mosaic=True)
    got, M1, info1, meta = pipeline.render_encoded(d1, r1, target="D65", output="sRGB", fmt=fmt, threads=threads,
                                                   exposure=exposure)
    assert "render" in r1.timings_ms and "demosaic" not in r1.timings_ms      # the strip path was taken
    np.testing.assert_array_equal(M0, M1)
    assert info0["crop"] == info1["crop"]
    return whole, got, meta


@pytest.mark.parametrize("fmt_name", ["png", "png16", "jpeg"])
@pytest.mark.parametrize("threads", [1, 2])
def test_strip_outputs_have_the_whole_image_paths_pixels(bright_dng, monkeypatch, fmt_name, threads):
    # small chunks, pieces and strips, so a 200 x 240 image has many of each
    monkeypatch.setattr(correction, "CHUNK_PIXELS", 240 * 3)
    monkeypatch.setattr(strips, "CHUNKS_PER_PIECE", 2)
    monkeypatch.setattr(encode, "MIN_STRIP_BYTES", 1000)
    monkeypatch.setattr(encode, "MIN_JPEG_SPLIT_PIXELS", 1000)
    plain = correction._plain_chunk
    seen = []
    monkeypatch.setattr(correction, "_plain_chunk", lambda *a: seen.append(plain(*a)) or seen[-1])
    whole, data, meta = _both(bright_dng, fmt_name, threads, exposure=0.0)   # no shoulder: plain chunks
    assert True in seen and False in seen           # plain chunks and chunks with highlights
    if fmt_name == "jpeg":   # the same pixels give the same decoded JPEG (restart markers: test_encode)
        np.testing.assert_array_equal(_decoded_pixels(data), _decoded_pixels(encode.jpeg_encode(whole)))
    else:
        np.testing.assert_array_equal(_decoded_pixels(data), whole)
    assert meta.get("icc") and (b"ICC_PROFILE" if fmt_name == "jpeg" else b"iCCP") in data   # metadata embedded


@pytest.mark.parametrize("fmt_name", ["png", "jpeg"])
def test_a_shoulder_exposure_renders_the_same_in_strips(bright_dng, monkeypatch, fmt_name):
    """The highlight shoulder (its luminance weights reversed with the
    matrix for a JPEG's BGR rows) gives the whole-image path's pixels."""
    monkeypatch.setattr(correction, "CHUNK_PIXELS", 240 * 5)
    monkeypatch.setattr(encode, "MIN_STRIP_BYTES", 1000)
    monkeypatch.setattr(encode, "MIN_JPEG_SPLIT_PIXELS", 1000)
    whole, data, _ = _both(bright_dng, fmt_name, 2, exposure=1.5)
    ref = whole if fmt_name == "png" else _decoded_pixels(encode.jpeg_encode(whole))
    np.testing.assert_array_equal(_decoded_pixels(data), ref)


@pytest.mark.skipif(not os.path.isfile(BLACKMAGIC), reason="the shared CinemaDNG is not here")
@pytest.mark.parametrize("fmt_name", ["png", "jpeg"])
def test_the_real_cinemadng_in_strips_is_its_default_crop_as_before(fmt_name):
    with open(BLACKMAGIC, "rb") as f:
        data = f.read()
    whole, got, _ = _both(data, fmt_name)
    assert whole.shape == (2160, 4096, 3)
    ref = whole if fmt_name == "png" else _decoded_pixels(encode.jpeg_encode(whole))
    np.testing.assert_array_equal(_decoded_pixels(got), ref)


def test_a_rotated_or_prefetched_image_takes_the_whole_image_path(bright_dng):
    s = get_settings()
    d, r = pipeline.analyze(bright_dng, "a.dng", s, prefetch=True)
    data, _, _, _ = pipeline.render_encoded(d, r, target="D65", output="sRGB", fmt=FORMATS["png"])
    assert "demosaic" in r.timings_ms and "render" not in r.timings_ms
    d, r = pipeline.analyze(bright_dng, "a.dng", s, keep_mosaic=True)
    d._mosaic["flip"] = 3
    assert strips.mosaic_rows(d, lambda shape: None) is None and d._mosaic is not None
