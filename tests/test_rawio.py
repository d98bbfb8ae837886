"""Upload decoding (service/rawio.py) and camera resolution (recovery/cameras.py).

Real DNG files are written with ``testing.dngwriter`` (scenes whose every
number is known) and decoded through LibRaw; PNG/TIFF/JPEG inputs are made
with OpenCV and tifffile. Tolerances are derived from the noise the writer
adds (1 % multiplicative, 0.0005 additive, per CFA sample) and from the
quantisation step of a 14-bit range.
"""

from __future__ import annotations

import io

import cv2
import numpy as np
import pytest
import tifffile

import models
from testing.dngwriter import (CAMERA_MAKE_MODEL, mosaic, scene_dng, spectral_scene, write_dng)
from recovery.cameras import camera_from_csv, camera_from_matrix, generic_camera, resolve_camera
from recovery.errors import InputError
from service.errors import ServiceError, service_error
from service.rawio import SATURATION_FRACTION, DecodedImage, decode_upload

H, W = 96, 128
BLACK, WHITE = 512, 16383
BIG = 10**8
CAMERAS = models.camera_names()


# ---------------------------------------------------------------------------
# fixtures and helpers
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def dngs(tmp_path_factory):
    """One DNG per measured camera: (bytes, DngTruth)."""
    root = tmp_path_factory.mktemp("dng")
    out = {}
    for i, cam in enumerate(CAMERAS):
        path = root / f"{i}.dng"
        truth = scene_dng(path, cam, "D65", H, W, seed=11 + i, black_level=BLACK, white_level=WHITE)
        out[cam] = (path.read_bytes(), truth)
    return out


@pytest.fixture(scope="module")
def nikon(dngs):
    return dngs["Nikon 5100 (NPL)"]


def _decode(data, filename="scene.dng", max_pixels=BIG) -> DecodedImage:
    return decode_upload(data, filename, max_pixels=max_pixels)


def _error(data, filename=None, max_pixels=BIG) -> ServiceError:
    with pytest.raises(ServiceError) as info:
        decode_upload(data, filename, max_pixels=max_pixels)
    return info.value


def _cells_inside(labels: np.ndarray, p: int) -> np.ndarray:
    """Half-size mask of the 2x2 cells whose four sites all belong to region p."""
    m = labels == p
    h2, w2 = m.shape[0] // 2, m.shape[1] // 2
    return m[: 2 * h2 : 2, : 2 * w2 : 2] & m[1 : 2 * h2 : 2, : 2 * w2 : 2] \
        & m[: 2 * h2 : 2, 1 : 2 * w2 : 2] & m[1 : 2 * h2 : 2, 1 : 2 * w2 : 2]


def _eroded(labels: np.ndarray, p: int, r: int = 3) -> np.ndarray:
    """Pixels of region p at least r pixels from its border (the demosaic of
    a flat patch is flat there)."""
    from scipy import ndimage

    return ndimage.binary_erosion(labels == p, iterations=r)


def _png16(rgb: np.ndarray) -> bytes:
    ok, enc = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    assert ok
    return enc.tobytes()


def _tiff(arr: np.ndarray, **kw) -> bytes:
    buf = io.BytesIO()
    tifffile.imwrite(buf, arr, **kw)
    return buf.getvalue()


def _with_orientation(data: bytes, orientation: int) -> bytes:
    """The DNG with its Orientation tag (274, a SHORT in IFD0) rewritten."""
    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        tag = tf.pages[0].tags[274]
        assert tf.byteorder == "<"
        off = tag.valueoffset
    out = bytearray(data)
    out[off:off + 2] = int(orientation).to_bytes(2, "little")
    return bytes(out)


# ---------------------------------------------------------------------------
# RAW: estimation image, metadata, saturation, full resolution
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("camera", CAMERAS)
def test_estimation_image_matches_the_scene_truth(dngs, camera):
    data, truth = dngs[camera]
    d = _decode(data)
    assert d.kind == "raw"
    assert d.estimation.dtype == np.float32 and d.estimation.shape == (H // 2, W // 2, 3)
    assert d.saturated.shape == (H // 2, W // 2) and not d.saturated.any()
    assert d.full_shape == (H, W) and d.binning == 2
    # Per-cell noise of a channel: a site's DN is round(b + v (1 + 0.01 n1) + 0.0005 n2) in units of
    # (w - b), so var = (0.01 v)^2 + 0.0005^2 + q^2/12 with q = 1/(w - b); green averages two sites
    # (half the variance). A patch mean over n cells is within 5 sigma / sqrt(n) of the truth.
    q2 = (1.0 / (WHITE - BLACK)) ** 2 / 12
    checked = 0
    for p in range(len(truth.patch_names)):
        cells = _cells_inside(truth.labels, p)
        n = int(cells.sum())
        if n < 10:
            continue
        v = truth.patch_rgb[p]
        var = (truth.noise_multiplicative * v) ** 2 + truth.noise_additive**2 + q2
        var = var * np.array([1.0, 0.5, 1.0])
        tol = 5 * np.sqrt(var / n)
        mean = d.estimation[cells].astype(np.float64).mean(axis=0)
        np.testing.assert_array_less(np.abs(mean - v), tol, err_msg=f"{camera} patch {truth.patch_names[p]}")
        checked += 1
    assert checked >= 20


@pytest.mark.parametrize("camera", CAMERAS)
def test_metadata_read_back(dngs, camera):
    data, truth = dngs[camera]
    d = _decode(data)
    assert (d.make, d.model) == CAMERA_MAKE_MODEL[camera]
    assert d.black_level == BLACK and d.white_level == WHITE
    # ColorMatrix1 is stored as SRATIONALs with denominators up to 2**30
    np.testing.assert_allclose(d.color_matrix, truth.color_matrix1, atol=1e-8)
    np.testing.assert_allclose(d.as_shot_neutral, truth.light_rgb, rtol=1e-6)
    assert d.as_shot_neutral[1] == 1.0
    assert d.warnings == []


def test_as_shot_neutral_absent(tmp_path):
    path = tmp_path / "n.dng"
    scene_dng(path, "Canon EOS 5D Mark II", "A", H, W, seed=2, as_shot_neutral=None)
    assert _decode(path.read_bytes()).as_shot_neutral is None


def test_saturated_mask_of_an_overexposed_scene(tmp_path):
    # the scene at 2.5x its normal exposure: the brighter patches clip at the white level
    sc = spectral_scene("Nikon 5100 (NPL)", "D65", H, W, seed=5)
    v = np.clip(sc.image * 2.5, 0.0, 1.0)
    cfa = np.rint(BLACK + mosaic(v, "RGGB") * (WHITE - BLACK)).astype(np.uint16)
    write_dng(tmp_path / "over.dng", cfa, black_level=BLACK, white_level=WHITE)
    d = _decode((tmp_path / "over.dng").read_bytes())
    # exactly the cells with a site at or above the threshold
    thr = np.ceil(BLACK + SATURATION_FRACTION * (WHITE - BLACK))
    cells = (cfa >= thr).reshape(H // 2, 2, W // 2, 2).any(axis=(1, 3))
    np.testing.assert_array_equal(d.saturated, cells)
    # and physically: patches whose brightest channel is far above 1 are saturated everywhere, those
    # far below (5 sigma of noise) nowhere
    n_sat = n_clear = 0
    for p in range(len(sc.patch_names)):
        inside = _cells_inside(sc.labels, p)
        if inside.sum() < 10:
            continue
        top = 2.5 * sc.patch_rgb[p].max()
        if top > 1.1:
            assert d.saturated[inside].all(), sc.patch_names[p]
            n_sat += 1
        elif top * 1.05 + 0.0025 < SATURATION_FRACTION:
            assert not d.saturated[inside].any(), sc.patch_names[p]
            n_clear += 1
    assert n_sat >= 3 and n_clear >= 3
    assert any("saturated" in w for w in d.warnings)


def test_saturation_threshold_is_per_channel_and_exact(tmp_path):
    blacks = [500, 700, 900, 1100]                # per CFA site, RGGB: R, G, G, B
    white = 16000
    cfa = np.full((32, 48), 2000, np.uint16)
    thr = [int(np.ceil(b + SATURATION_FRACTION * (white - b))) for b in blacks]
    cfa[0, 0] = thr[0] - 1                       # cell (0, 0): red just below
    cfa[0, 2] = thr[0]                           # cell (0, 1): red at the threshold
    cfa[3, 3] = thr[3]                           # cell (1, 1): blue at its own threshold
    cfa[5, 5] = thr[0]                           # cell (2, 2): blue site at red's threshold < blue's
    write_dng(tmp_path / "t.dng", cfa, pattern="RGGB", black_level=blacks, white_level=white)
    d = _decode((tmp_path / "t.dng").read_bytes())
    assert sorted(zip(*np.nonzero(d.saturated))) == [(0, 1), (1, 1)]
    # scale: (d - b_c) / (w - b_c) per site, greens averaged
    e = d.estimation[4, 4]
    want = [(2000 - 500) / (white - 500), ((2000 - 700) / (white - 700) + (2000 - 900) / (white - 900)) / 2,
            (2000 - 1100) / (white - 1100)]
    np.testing.assert_allclose(e, want, rtol=1e-6)
    assert d.black_level == np.mean(blacks) and d.white_level == white


def test_full_linear_is_on_the_estimation_scale(nikon):
    data, truth = nikon
    d = _decode(data)
    full = d.full_linear()
    assert full.dtype == np.uint16 and full.shape == (H, W, 3) and full.shape[:2] == d.full_shape
    checked = 0
    for p in range(len(truth.patch_names)):
        # 4 pixels in: the default demosaic (RCD) reads 4 pixels along rows and
        # columns for green; at 3 the frame's thin bands between patches were
        # 2.8 % off in green, the patches within 0.5 % (as the bilinear's)
        px, cells = _eroded(truth.labels, p, 4), _cells_inside(truth.labels, p)
        if px.sum() < 50:
            continue
        f = full[px].mean(axis=0) / 65535
        e = d.estimation[cells].mean(axis=0)
        ok = e > 0.03                      # relative agreement where the signal is well above noise
        np.testing.assert_allclose(f[ok], e[ok], rtol=0.01, err_msg=truth.patch_names[p])
        checked += 1
    assert checked >= 20
    f32 = d.full_linear("float32")
    assert f32.dtype == np.float32
    np.testing.assert_allclose(f32, full / 65535.0, atol=1e-7)
    full[:] = 0                            # a new array on every call
    assert d.full_linear().max() > 0


def test_full_linear_scale_with_per_channel_black_levels(tmp_path):
    # LibRaw divides by (white - min black); the per-channel gains make it (white - b_c)
    vals = {(0, 0): 3000, (0, 1): 9000, (1, 0): 12000, (1, 1): 6000}
    cfa = np.empty((48, 64), np.uint16)
    for (dy, dx), v in vals.items():
        cfa[dy::2, dx::2] = v
    write_dng(tmp_path / "b.dng", cfa, pattern="GRBG", black_level=[500, 1510, 1520, 2530], white_level=16000)
    d = _decode((tmp_path / "b.dng").read_bytes())
    # GRBG: G at (0,0) b=500, R at (0,1) b=1510, B at (1,0) b=1520, G at (1,1) b=2530
    want = [(9000 - 1510) / (16000 - 1510), ((3000 - 500) / 15500 + (6000 - 2530) / (16000 - 2530)) / 2,
            (12000 - 1520) / (16000 - 1520)]
    np.testing.assert_allclose(d.estimation[10, 10], want, rtol=1e-6)
    full = d.full_linear("float32")
    np.testing.assert_allclose(full[8:40, 8:56, 0].mean(), want[0], rtol=1e-4)
    np.testing.assert_allclose(full[8:40, 8:56, 2].mean(), want[2], rtol=1e-4)
    # LibRaw interpolates G from two greens of different levels: the mean is the average
    np.testing.assert_allclose(full[8:40, 8:56, 1].mean(), want[1], rtol=1e-3)


#: EXIF Orientation -> how the stored image is turned for display.
_EXIF = {
    1: lambda a: a, 2: lambda a: a[:, ::-1], 3: lambda a: a[::-1, ::-1], 4: lambda a: a[::-1],
    5: lambda a: np.swapaxes(a, 0, 1), 6: lambda a: np.rot90(a, -1),
    7: lambda a: np.rot90(a, -1)[::-1], 8: lambda a: np.rot90(a, 1),
}


def test_orientation_is_applied_to_both_images_alike(nikon):
    data, _ = nikon
    ref = _decode(data)
    ref_full = ref.full_linear()
    for o in range(2, 9):
        d = _decode(_with_orientation(data, o))
        np.testing.assert_array_equal(d.estimation, _EXIF[o](ref.estimation), err_msg=f"orientation {o}")
        np.testing.assert_array_equal(d.saturated, _EXIF[o](ref.saturated))
        full = d.full_linear()
        assert full.shape[:2] == d.full_shape
        np.testing.assert_array_equal(full, _EXIF[o](ref_full), err_msg=f"orientation {o}")


def test_odd_size_drops_the_last_row_and_column(tmp_path):
    scene_dng(tmp_path / "odd.dng", "Nikon 5100 (NPL)", "D65", 97, 129, seed=1)
    d = _decode((tmp_path / "odd.dng").read_bytes())
    assert d.estimation.shape == (48, 64, 3) and d.full_shape == (97, 129)
    assert d.full_linear().shape == (97, 129, 3)
    assert any("odd image size" in w for w in d.warnings)


def test_grey_tiff_is_read_by_libraw_as_a_mosaic_with_a_warning():
    grey = np.full((48, 64), 1000, np.uint16)
    d = _decode(_tiff(grey), "dump.tiff")
    assert d.kind == "raw" and d.estimation.shape == (24, 32, 3)
    assert any("RGGB Bayer mosaic" in w for w in d.warnings)


# ---------------------------------------------------------------------------
# Linear TIFF / PNG
# ---------------------------------------------------------------------------

def _rgb16():
    img = np.zeros((40, 50, 3), np.uint16)
    img[...] = (1000, 20000, 40000)
    img[5, 7] = (65535, 10, 10)
    return img


def test_png16_is_read_as_rgb():
    img = _rgb16()
    d = _decode(_png16(img), "x.png")
    assert d.kind == "png" and d.full_shape == (40, 50) and d.binning == 1
    np.testing.assert_allclose(d.estimation[0, 0], np.array([1000, 20000, 40000]) / 65535, rtol=1e-6)
    assert d.saturated.sum() == 1 and d.saturated[5, 7]
    assert (d.black_level, d.white_level) == (0.0, 65535.0)
    np.testing.assert_array_equal(d.full_linear(), img)
    assert d.make is None and d.color_matrix is None and d.as_shot_neutral is None


def test_png16_with_alpha_and_gamma_chunk_warn():
    rgba = np.dstack([_rgb16(), np.full((40, 50), 65535, np.uint16)])
    ok, enc = cv2.imencode(".png", np.ascontiguousarray(rgba[..., [2, 1, 0, 3]]))
    d = _decode(enc.tobytes())
    np.testing.assert_array_equal(d.full_linear(), _rgb16())
    assert any("alpha" in w for w in d.warnings)


@pytest.mark.parametrize("planar", [False, True])
def test_tiff16_is_read(planar):
    img = _rgb16()
    data = _tiff(np.moveaxis(img, -1, 0) if planar else img, photometric="rgb",
                 planarconfig="separate" if planar else "contig")
    d = _decode(data, "x.tif")
    assert d.kind == "tiff"
    np.testing.assert_array_equal(d.full_linear(), img)
    assert d.saturated.sum() == 1


def test_float_tiff_is_read_and_nan_refused():
    img = np.full((30, 40, 3), 0.25, np.float32)
    img[0, 0] = (1.5, 0.1, 0.1)
    d = _decode(_tiff(img, photometric="rgb"))
    assert d.white_level == 1.0 and d.saturated[0, 0] and d.saturated.sum() == 1
    np.testing.assert_array_equal(d.full_linear("float32"), img)      # > 1 kept in float
    assert d.full_linear()[0, 0, 0] == 65535
    img[3, 3, 1] = np.nan
    e = _error(_tiff(img, photometric="rgb"))
    assert (e.status, e.code) == (422, "non_finite")


def test_compressed_tiff_is_read():
    img = _rgb16()
    np.testing.assert_array_equal(_decode(_tiff(img, photometric="rgb", compression="zlib")).full_linear(), img)


# ---------------------------------------------------------------------------
# Bad uploads
# ---------------------------------------------------------------------------

def _jpeg() -> bytes:
    ok, enc = cv2.imencode(".jpg", np.full((32, 32, 3), 128, np.uint8))
    return enc.tobytes()


def _png8() -> bytes:
    ok, enc = cv2.imencode(".png", np.full((32, 32, 3), 128, np.uint8))
    return enc.tobytes()


@pytest.mark.parametrize("make, status, code, phrase", [
    (lambda: b"", 422, "empty_file", "empty"),
    (lambda: np.random.default_rng(0).bytes(10000), 415, "unsupported_format", "detected: unknown"),
    (_jpeg, 415, "unsupported_format", "JPEG"),
    (_png8, 415, "not_linear", "8-bit"),
    (lambda: _tiff(np.full((32, 32, 3), 9, np.uint8), photometric="rgb"), 415, "not_linear", "8-bit"),
    (lambda: _png16(np.zeros((32, 32, 3), np.uint16))[:-30], 422, "corrupt_file", "PNG"),
    (lambda: cv2.imencode(".png", np.zeros((32, 32), np.uint16))[1].tobytes(), 415, "unsupported_format", "grey"),
    (lambda: _tiff(np.zeros((32, 32, 3), np.int32), photometric="rgb"), 415, "unsupported_format", "int32"),
    (lambda: _tiff(np.zeros((32, 32, 2), np.uint16), planarconfig="contig", photometric="minisblack"),
     415, "unsupported_format", "channel"),
    (lambda: b"wavelength,r,g,b\n400,1,2,3\n", 415, "unsupported_format", "detected"),
])
def test_bad_uploads(make, status, code, phrase):
    e = _error(make())
    assert (e.status, e.code) == (status, code), e.detail
    assert phrase in e.detail


def test_png_with_a_damaged_crc():
    data = bytearray(_png16(_rgb16()))
    data[-20] ^= 0x40                        # inside the IDAT data
    e = _error(bytes(data))
    assert (e.status, e.code) == (422, "corrupt_file") and "CRC" in e.detail


@pytest.mark.parametrize("cut", ["1 byte short", "100 bytes short", "half", "inside the pixels",
                                 "end of the IFD", "inside the IFD", "header only", "3 bytes"])
def test_truncated_dng_is_corrupt(nikon, cut):
    data, _ = nikon
    n = len(data)
    keep = {"1 byte short": n - 1, "100 bytes short": n - 100, "half": n // 2, "inside the pixels": 600,
            "end of the IFD": 560, "inside the IFD": 300, "header only": 8, "3 bytes": 3}[cut]
    for name in ("scene.dng", None):
        e = _error(data[:keep], name)
        assert (e.status, e.code) == (422, "corrupt_file"), (cut, name, e.detail)


def test_bit_flipped_headers(nikon):
    data, _ = nikon

    def flipped(pos, bit=7):
        d = bytearray(data)
        d[pos] ^= 1 << bit
        return bytes(d)

    # byte-order mark damaged: unrecognisable; corrupt if the name promises a RAW
    e = _error(flipped(0, 0), "scene.dng")
    assert (e.status, e.code) == (422, "corrupt_file")
    e = _error(flipped(0, 0), None)
    assert (e.status, e.code) == (415, "unsupported_format")   # "HI*": nothing says what it was
    # LibRaw ignores the TIFF magic number 42: the pixels decode, the tags (read with tifffile) do not
    d = _decode(flipped(2, 7), None)
    np.testing.assert_array_equal(d.estimation, _decode(data).estimation)
    assert d.make is None and d.warnings
    # first-IFD offset pointing into the pixels
    e = _error(flipped(4, 7))
    assert (e.status, e.code) == (422, "corrupt_file"), e.detail
    # StripOffsets beyond the end of the file
    with tifffile.TiffFile(io.BytesIO(data)) as tf:
        strip = tf.pages[0].tags[273].valueoffset
        width = tf.pages[0].tags[256].valueoffset
    e = _error(flipped(strip + 2, 7))
    assert (e.status, e.code) == (422, "corrupt_file"), e.detail
    # a width beyond the data: never a 500
    e = _error(flipped(width + 1, 6))
    assert e.status in (413, 415, 422)
    # every header byte damaged in turn: a decoded image or an ServiceError, nothing else
    for pos in range(0, 600):
        try:
            d = _decode(flipped(pos), None)
        except ServiceError as err:
            assert err.status in (413, 415, 422)
        else:
            assert d.estimation.dtype == np.float32 and d.estimation.ndim == 3


def test_random_bytes_with_a_raw_name_are_corrupt():
    e = _error(np.random.default_rng(1).bytes(5000), "photo.NEF")
    assert (e.status, e.code) == (422, "corrupt_file")


def test_too_many_pixels_before_decoding(nikon):
    data, _ = nikon
    e = _error(data, max_pixels=H * W - 1)
    assert (e.status, e.code) == (413, "too_many_pixels") and f"{H * W - 1:,}" in e.detail
    assert _decode(data, max_pixels=H * W).estimation.shape == (H // 2, W // 2, 3)
    for blob in (_png16(_rgb16()), _tiff(_rgb16(), photometric="rgb")):
        e = _error(blob, max_pixels=40 * 50 - 1)
        assert (e.status, e.code) == (413, "too_many_pixels")


def test_dng_below_libraw_minimum_size(tmp_path):
    write_dng(tmp_path / "tiny.dng", np.full((16, 16), 100, np.uint16))
    e = _error((tmp_path / "tiny.dng").read_bytes())
    assert (e.status, e.code) == (415, "unsupported_format") and "22" in e.detail


def test_bytearray_and_memoryview_accepted(nikon):
    data, _ = nikon
    a = _decode(bytearray(data)).estimation
    b = _decode(memoryview(data)).estimation
    np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------
# Cameras
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("camera", CAMERAS)
def test_resolve_camera_measured_from_make_and_model(dngs, camera):
    cam, warns = resolve_camera(_decode(dngs[camera][0]))
    assert cam.source == "measured" and cam.name == camera and warns == []
    np.testing.assert_array_equal(cam.sensitivities, models.camera_sensitivities(camera))


def test_resolve_camera_matrix_derived_for_an_unknown_model(tmp_path):
    truth = scene_dng(tmp_path / "foo.dng", "Canon EOS 5D Mark II", "D65", H, W, seed=4, make="Foo", model="Bar")
    d = _decode((tmp_path / "foo.dng").read_bytes())
    assert (d.make, d.model) == ("Foo", "Bar")
    np.testing.assert_allclose(d.color_matrix, truth.color_matrix1, atol=1e-8)
    cam, warns = resolve_camera(d)
    assert cam.source == "matrix-derived" and "approximate: derived from colour matrix" in warns
    assert "Foo Bar" in cam.name
    r = models.observer("XYZ") @ truth.color_matrix1.T
    want = np.clip(r, 0, None)
    np.testing.assert_allclose(cam.sensitivities, want / want.max(), rtol=1e-6, atol=1e-9)


def test_resolve_camera_generic_when_nothing_is_known():
    d = _decode(_png16(_rgb16()))
    cam, warns = resolve_camera(d)
    assert cam.source == "generic" and warns and warns[0].startswith("approximate")
    nameless = DecodedImage("raw", np.zeros((2, 2, 3), np.float32), np.zeros((2, 2), bool), (4, 4),
                            make="Foo", model="Bar")
    cam, warns = resolve_camera(nameless)
    assert cam.source == "generic" and "'Foo Bar'" in warns[0]
    cam, warns = resolve_camera(None)
    assert cam.source == "generic" and warns


def test_generic_camera_is_the_mean_of_the_measured_ones():
    g = generic_camera()
    want = np.mean([models.camera_sensitivities(n) for n in CAMERAS], axis=0)
    np.testing.assert_allclose(g.sensitivities, want)
    assert g.source == "generic" and g.name == "generic" and g.notes
    assert generic_camera(models.wavelength_grid(400, 700, 5)).sensitivities.shape == (61, 3)


def test_resolve_camera_explicit_names(nikon):
    d = _decode(nikon[0])
    cam, warns = resolve_camera(d, "Canon EOS 5D Mark II")
    assert cam.name == "Canon EOS 5D Mark II" and cam.source == "measured"
    assert any("NIKON D5100" in w for w in warns)
    cam, warns = resolve_camera(d, "nikon d5100")                       # alias
    assert cam.name == "Nikon 5100 (NPL)" and warns == []
    cam, warns = resolve_camera(d, "matrix")
    assert cam.source == "matrix-derived" and "approximate: derived from colour matrix" in warns
    cam, warns = resolve_camera(d, "generic")
    assert cam.source == "generic" and warns
    cam, warns = resolve_camera(d, "auto")
    assert cam.source == "measured"
    with pytest.raises(InputError) as info:
        resolve_camera(d, "Leica M9")
    assert (service_error(info.value).status, info.value.code) == (422, "unknown_camera")
    for name in CAMERAS + ["generic", "matrix"]:
        assert name in info.value.detail
    with pytest.raises(InputError) as info:
        resolve_camera(_decode(_png16(_rgb16())), "matrix")
    assert (service_error(info.value).status, info.value.code) == (422, "no_color_matrix")


def _csv(wl, sens, header="nm,r,g,b", delim=",") -> bytes:
    rows = [header] if header else []
    rows += [delim.join(f"{v:.10g}" for v in (w, *s)) for w, s in zip(wl, sens)]
    return "\n".join(rows).encode()


def test_camera_from_csv_good():
    wl5 = models.wavelength_grid(380, 780, 5)
    sens = models.camera_sensitivities("Nikon 5100 (NPL)", wl5) * 37.0
    ref = models.camera_sensitivities("Nikon 5100 (NPL)")
    for blob in (_csv(wl5, sens), _csv(wl5, sens, header=None), _csv(wl5, sens, header="a\tb\tc\td", delim="\t"),
                 _csv(wl5, sens, header=None, delim=" "),
                 _csv(wl5, sens, header="nm;r;g;b", delim=";").replace(b".", b",")):
        cam = camera_from_csv(blob)
        assert cam.source == "uploaded" and cam.name == "uploaded" and cam.channels == 3
        # the 10 nm grid is a subset of the 5 nm rows: the values, up to one scale
        np.testing.assert_allclose(cam.sensitivities, ref / ref.max(), rtol=1e-8, atol=1e-12)
    four = np.hstack([sens, sens[:, :1]])
    cam = camera_from_csv(_csv(wl5, four, header="nm,r,g,b,e"), models.wavelength_grid(400, 700, 20), "mine")
    assert cam.channels == 4 and cam.wavelengths.size == 16 and cam.name == "mine"
    cam, warns = resolve_camera(None, "Canon EOS 5D Mark II", _csv(wl5, sens))
    assert cam.source == "uploaded" and any("ignored" in w for w in warns)


@pytest.mark.parametrize("text, phrase", [
    ("nm,r,g,b\n400,1,1,1\n550,1,x,1\n700,1,1,1\n", "line 3, column 3: 'x' is not a number"),
    ("nm,r,g\n400,1,1\n700,1,1\n", "at least 3 channel columns; found 2"),
    ("400,1,1,1\n550,1,1,1\n500,1,1,1\n700,1,1,1\n", "strictly increasing: 500 nm follows 550 nm"),
    ("400,1,1,1\n400,1,1,1\n700,1,1,1\n", "strictly increasing"),
    ("420,1,1,1\n700,1,1,1\n", "span 420-700 nm; they must cover 400-700 nm"),
    ("400,1,1,1\n650,1,1,1\n", "must cover 400-700"),
    ("0.4,1,1,1\n0.7,1,1,1\n", "micrometres"),
    ("400,1,nan,1\n700,1,1,1\n", "line 1, column 3: 'nan' is NaN or Inf"),
    ("400,1,1,1\n700,1,1,inf\n", "NaN or Inf"),
    ("nm,r,g,b\n400,1,0,1\n700,1,0,1\n", "channel(s) g are zero"),
    ("400,1,1,1\n550,1,1\n700,1,1,1\n", "line 2 has 3 columns, expected 4"),
    ("", "empty"),
    ("# only a comment\n", "no numeric rows"),
    ("400,1,1,1\n", "at least two wavelengths"),
])
def test_camera_from_csv_bad(text, phrase):
    with pytest.raises(InputError) as info:
        camera_from_csv(text.encode())
    assert (service_error(info.value).status, info.value.code) == (422, "bad_csv")
    assert phrase in info.value.detail, info.value.detail


def test_camera_from_csv_not_text():
    with pytest.raises(InputError) as info:
        camera_from_csv(b"\xff\xfe\x00\x01garbage")
    assert "UTF-8" in info.value.detail


def test_camera_from_matrix():
    cam = camera_from_matrix(np.eye(3))
    cmf = models.observer("XYZ")
    np.testing.assert_allclose(cam.sensitivities, cmf / cmf.max())
    assert cam.source == "matrix-derived"
    # response to a spectrum is M @ XYZ (up to the overall scale) when nothing is clipped
    m = np.array([[1.0, 0.2, 0.0], [0.1, 1.0, 0.1], [0.0, 0.1, 1.0]])
    cam = camera_from_matrix(m)
    spd = models.illuminant("A", cam.wavelengths)
    xyz = (spd * cam.dlambda) @ cmf
    rgb = cam.response(spd)
    np.testing.assert_allclose(rgb / rgb.max(), (m @ xyz) / (m @ xyz).max(), rtol=1e-9)
    # a real matrix has negative lobes: clipped, and said so
    cam = camera_from_matrix([[0.8198, -0.2239, -0.0724], [-0.4871, 1.2389, 0.2798], [-0.1043, 0.205, 0.7181]])
    assert cam.sensitivities.min() == 0.0 and any("negative lobes clipped" in n for n in cam.notes)
    for bad in (np.zeros((3, 3)), np.ones((2, 3)), [[np.nan] * 3] * 3, -np.eye(3)):
        with pytest.raises(InputError) as info:
            camera_from_matrix(bad)
        assert (service_error(info.value).status, info.value.code) == (422, "bad_color_matrix")
