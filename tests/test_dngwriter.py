"""DNG fixtures (testing/dngwriter.py) decoded by LibRaw through rawpy.

Each test writes a small DNG (64 x 96 unless said) to ``tmp_path``, reads it
back with ``rawpy`` and compares what LibRaw reports with what was written
and with the spectral truth of the scene.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
import rawpy

import models
from recovery import angular_error
from testing.dngwriter import (CAMERA_MAKE_MODEL, cfa_colour_indices, color_matrix_for_camera,
                               mosaic, scene_dng, spectral_scene, write_dng)
from testing.dngwriter import d50_xyz as _d50_xyz

H, W = 64, 96
BLACK, WHITE = 512, 16383
CAMERAS = models.camera_names()


def _srgb_to_xyz() -> np.ndarray:
    import colour

    return np.asarray(colour.RGB_COLOURSPACES["sRGB"].matrix_RGB_to_XYZ, float)


def _site_colours(pattern, shape) -> np.ndarray:
    """Colour code (0 R, 1 G, 2 B) of every CFA site."""
    codes = cfa_colour_indices(pattern)
    return np.tile(codes, (shape[0] // 2 + 1, shape[1] // 2 + 1))[: shape[0], : shape[1]]


def _expected_cfa(truth, **scene_kw) -> np.ndarray:
    """The CFA scene_dng must have written: the full-RGB scene with the same
    seed, mosaicked and quantised as round(black + v (white - black))."""
    sc = spectral_scene(truth.camera, truth.illuminant, *truth.labels.shape, truth.seed, **scene_kw)
    v = mosaic(sc.image, truth.pattern)
    dn = np.rint(np.float32(truth.black_level) + v * np.float32(truth.white_level - truth.black_level))
    return np.clip(dn, 0, truth.white_level).astype(np.uint16)


# ---------------------------------------------------------------------------
# Raw data, levels, pattern
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("pattern", ["RGGB", "BGGR", "GRBG", "GBRG"])
@pytest.mark.parametrize("camera", CAMERAS)
def test_raw_image_levels_and_pattern(tmp_path, camera, pattern):
    path = tmp_path / "scene.dng"
    truth = scene_dng(path, camera, "D65", H, W, seed=7, pattern=pattern,
                      black_level=BLACK, white_level=WHITE)
    expected = _expected_cfa(truth)
    with rawpy.imread(str(path)) as raw:
        assert raw.raw_type == rawpy.RawType.Flat
        assert raw.num_colors == 3
        assert raw.raw_image.dtype == np.uint16
        np.testing.assert_array_equal(raw.raw_image, expected)
        np.testing.assert_array_equal(raw.raw_image_visible, expected)  # no margins
        assert raw.black_level_per_channel == [BLACK] * 4
        assert raw.white_level == WHITE
        desc = raw.color_desc.decode()
        assert desc == "RGBG"
        letters = "".join(desc[i] for i in raw.raw_pattern.ravel())
        assert letters == pattern
        # raw_colors: the colour of every site, second green numbered 3
        sites = np.asarray(raw.raw_colors)
        np.testing.assert_array_equal(np.where(sites == 3, 1, sites), _site_colours(pattern, (H, W)))


def test_raw_image_is_the_cfa_bit_for_bit(tmp_path):
    rng = np.random.default_rng(0)
    cfa = rng.integers(0, 2**16, size=(48, 70), dtype=np.uint16)
    write_dng(tmp_path / "noise.dng", cfa, black_level=0, white_level=65535)
    with rawpy.imread(str(tmp_path / "noise.dng")) as raw:
        np.testing.assert_array_equal(raw.raw_image, cfa)


def test_per_site_black_levels_map_to_colour_channels(tmp_path):
    # BlackLevel is given per CFA position (row-major over the 2x2 repeat);
    # rawpy reports it per colour in color_desc order (R, G, B, G2).
    cfa = np.full((32, 48), 2000, np.uint16)
    write_dng(tmp_path / "b.dng", cfa, pattern="GRBG", black_level=[500, 510, 520, 530], white_level=16383)
    with rawpy.imread(str(tmp_path / "b.dng")) as raw:
        assert raw.black_level_per_channel == [510, 500, 520, 530]


def test_eight_bit_dng(tmp_path):
    cfa = np.random.default_rng(1).integers(16, 256, size=(32, 48), dtype=np.uint8)
    write_dng(tmp_path / "8.dng", cfa, bits=8, black_level=16, white_level=255)
    with rawpy.imread(str(tmp_path / "8.dng")) as raw:
        np.testing.assert_array_equal(raw.raw_image, cfa)   # rawpy widens to uint16
        assert raw.black_level_per_channel == [16] * 4 and raw.white_level == 255
        assert raw.postprocess().shape == (32, 48, 3)


def test_dng_tags_as_written(tmp_path):
    import tifffile

    truth = scene_dng(tmp_path / "t.dng", "Canon EOS 5D Mark II", "A", H, W, seed=2)
    with tifffile.TiffFile(tmp_path / "t.dng") as tf:
        tags = {t.name: t.value for t in tf.pages[0].tags}
    assert tags["NewSubfileType"] == 0
    assert int(tags["PhotometricInterpretation"]) == 32803
    assert int(tags["Compression"]) == 1
    assert tags["DNGVersion"] == b"\x01\x04\x00\x00"
    assert tags["CFARepeatPatternDim"] == (2, 2)
    assert tags["CFAPattern"] == b"\x00\x01\x01\x02"
    assert (tags["Make"], tags["Model"]) == CAMERA_MAKE_MODEL["Canon EOS 5D Mark II"]
    assert tags["UniqueCameraModel"] == "Canon Canon EOS 5D Mark II"
    assert tags["CalibrationIlluminant1"] == 21
    cm = np.array(tags["ColorMatrix1"], float).reshape(9, 2)
    np.testing.assert_allclose(cm[:, 0] / cm[:, 1], truth.color_matrix1.ravel(), atol=1e-8)
    asn = np.array(tags["AsShotNeutral"], float).reshape(3, 2)
    np.testing.assert_allclose(asn[:, 0] / asn[:, 1], truth.light_rgb, rtol=1e-8)


@pytest.mark.parametrize("camera", CAMERAS)
def test_make_model_identify_the_measured_camera(camera):
    make, model = CAMERA_MAKE_MODEL[camera]
    assert models.canonical_camera_name(f"{make} {model}") == camera


# ---------------------------------------------------------------------------
# White balance and colour matrix
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("camera", CAMERAS)
@pytest.mark.parametrize("illuminant", ["D65", "A", "FL11"])
def test_camera_whitebalance_is_inverse_as_shot_neutral(tmp_path, camera, illuminant):
    truth = scene_dng(tmp_path / "wb.dng", camera, illuminant, H, W, seed=3)
    np.testing.assert_allclose(truth.as_shot_neutral, truth.light_rgb)
    assert truth.light_rgb[1] == 1.0
    with rawpy.imread(str(tmp_path / "wb.dng")) as raw:
        wb = np.asarray(raw.camera_whitebalance, float)
    # LibRaw: cam_mul = 1 / AsShotNeutral (float32), no fourth colour
    np.testing.assert_allclose(wb[:3], 1.0 / truth.light_rgb, rtol=1e-6)
    assert wb[3] == 0.0


def test_wrong_and_missing_as_shot_neutral(tmp_path):
    wrong = scene_dng(tmp_path / "w.dng", "Nikon 5100 (NPL)", "D65", H, W, as_shot_neutral="A")
    assert float(angular_error(wrong.as_shot_neutral, wrong.light_rgb)) > 5.0
    with rawpy.imread(str(tmp_path / "w.dng")) as raw:
        np.testing.assert_allclose(raw.camera_whitebalance[:3], 1.0 / wrong.as_shot_neutral, rtol=1e-6)
    given = scene_dng(tmp_path / "g.dng", "Nikon 5100 (NPL)", "D65", H, W, as_shot_neutral=[0.5, 1.0, 0.8])
    with rawpy.imread(str(tmp_path / "g.dng")) as raw:
        np.testing.assert_allclose(raw.camera_whitebalance[:3], [2.0, 1.0, 1.25], rtol=1e-6)
    scene_dng(tmp_path / "n.dng", "Nikon 5100 (NPL)", "D65", H, W, as_shot_neutral=None)
    with rawpy.imread(str(tmp_path / "n.dng")) as raw:
        # without AsShotNeutral LibRaw reports no camera white balance
        assert raw.camera_whitebalance == [0.0, 1.0, 0.0, 0.0]


def test_color_matrix_for_camera_is_white_preserving_and_normalised():
    wl = models.wavelength_grid(400, 700, 5)
    for cam in CAMERAS:
        m = color_matrix_for_camera(cam, wl)
        e = models.illuminant("D65", wl) * models.wavelength_step(wl)
        xyz_w = e @ models.observer("CIE 1931 2 Degree Standard Observer", wl)
        cam_w = e @ models.camera_sensitivities(cam, wl)
        mapped = m @ xyz_w
        np.testing.assert_allclose(mapped / mapped[1], cam_w / cam_w[1], rtol=1e-9)
        assert np.max(m @ _d50_xyz()) == pytest.approx(1.0, abs=1e-12)


@pytest.mark.parametrize("camera", CAMERAS)
def test_color_matrix1_reaches_libraw(tmp_path, camera):
    """ColorMatrix1 is what LibRaw turns into rgb_cam (rawpy ``color_matrix``)
    and pre_mul (``daylight_whitebalance``): with cam_rgb = CM . M_sRGB->XYZ,
    pre_mul = 1 / rowsum(cam_rgb) and rgb_cam = inverse of cam_rgb with rows
    normalised to sum 1 (dcraw's cam_xyz_coeff). Tolerances: LibRaw's own
    sRGB constants differ from colour-science's in the 4th decimal."""
    truth = scene_dng(tmp_path / "cm.dng", camera, "D65", H, W)
    cam_rgb = truth.color_matrix1 @ _srgb_to_xyz()
    with rawpy.imread(str(tmp_path / "cm.dng")) as raw:
        rgb_cam = np.asarray(raw.color_matrix)[:, :3]
        pre_mul = np.asarray(raw.daylight_whitebalance, float)
        rgb_xyz = np.asarray(raw.rgb_xyz_matrix)[:3]
    np.testing.assert_allclose(rgb_cam, np.linalg.inv(cam_rgb / cam_rgb.sum(1, keepdims=True)), atol=2e-3)
    np.testing.assert_allclose(pre_mul[:3], 1.0 / cam_rgb.sum(1), rtol=1e-3)
    # the matrix is white preserving for D65, so LibRaw's daylight balance is
    # the inverse camera response to D65 (0.5 %: LibRaw's D65 white is the
    # sRGB one, ours is the tabulated D65 on the 400-700 nm grid)
    wl = truth.wavelengths
    d65 = (models.illuminant("D65", wl) * models.wavelength_step(wl)) @ models.camera_sensitivities(camera, wl)
    np.testing.assert_allclose(pre_mul[:3] / pre_mul[1], d65[1] / d65, rtol=5e-3)
    # LibRaw does NOT report ColorMatrix1 as rgb_xyz_matrix: it reports its
    # built-in table entry for the Make/Model (Adobe's matrix for the Nikon and
    # the Canon) -- never the matrix in the file.
    assert not np.allclose(rgb_xyz, truth.color_matrix1, atol=1e-2)


def test_rgb_xyz_matrix_is_zero_for_an_unknown_camera(tmp_path):
    cm = color_matrix_for_camera("Nikon 5100 (NPL)")
    write_dng(tmp_path / "u.dng", np.full((32, 48), 4000, np.uint16), black_level=512,
              white_level=16383, color_matrix1=cm, make="wandell-recovery", model="synthetic CFA")
    with rawpy.imread(str(tmp_path / "u.dng")) as raw:
        assert not np.any(raw.rgb_xyz_matrix)
        assert np.any(raw.color_matrix)           # but ColorMatrix1 was used


# ---------------------------------------------------------------------------
# Decoded data against the synthesised truth
# ---------------------------------------------------------------------------

def _patch_channel_means(raw_image, truth):
    """Mean of each CFA colour over each region, as a fraction of the range,
    with the number of sites it averages."""
    v = (raw_image.astype(np.float64) - truth.black_level) / (truth.white_level - truth.black_level)
    colours = _site_colours(truth.pattern, raw_image.shape)
    P = len(truth.patch_names)
    means, counts = np.zeros((P, 3)), np.zeros((P, 3), int)
    for c in range(3):
        sel = colours == c
        lab = truth.labels[sel].astype(np.intp)
        counts[:, c] = np.bincount(lab, minlength=P)
        means[:, c] = np.bincount(lab, weights=v[sel], minlength=P) / np.maximum(counts[:, c], 1)
    return means, counts


def _mean_tolerance(truth, counts):
    """Bound on |decoded mean - synthesised response| per region and channel.

    Quantisation: rounding to an integer DN moves each value by at most half a
    DN, so a mean by at most 0.5 DN; allow 1 DN / (white - black). Noise: each
    value is v (1 + m n1) + a n2, so the mean of n values has standard
    deviation sqrt((m v)^2 + a^2) / sqrt(n); allow 4 of them (no value comes
    near the clipping points 0 and 1 at exposure 0.9 and 1 % noise).
    """
    q = 1.0 / (truth.white_level - truth.black_level)
    sigma = np.sqrt((truth.noise_multiplicative * truth.patch_rgb) ** 2 + truth.noise_additive ** 2)
    return q + 4.0 * sigma / np.sqrt(np.maximum(counts, 1))


@pytest.mark.parametrize("camera", CAMERAS)
@pytest.mark.parametrize("illuminant", ["D65", "A", "FL2"])
def test_patch_means_match_synthesised_response(tmp_path, camera, illuminant):
    truth = scene_dng(tmp_path / "p.dng", camera, illuminant, H, W, seed=11, pattern="GBRG")
    with rawpy.imread(str(tmp_path / "p.dng")) as raw:
        means, counts = _patch_channel_means(raw.raw_image, truth)
    assert counts.min() >= 25
    tol = _mean_tolerance(truth, counts)
    err = np.abs(means - truth.patch_rgb)
    assert np.all(err <= tol), f"worst excess {np.max(err - tol):.2e}"


def test_noiseless_pixels_are_exact_to_half_a_dn(tmp_path):
    truth = scene_dng(tmp_path / "q.dng", "Sigma SDMerill (NPL)", "D50", H, W,
                      noise_multiplicative=0.0, noise_additive=0.0)
    with rawpy.imread(str(tmp_path / "q.dng")) as raw:
        v = (raw.raw_image.astype(np.float64) - BLACK) / (WHITE - BLACK)
    want = mosaic(truth.patch_rgb[truth.labels], truth.pattern)
    # half a DN from rounding, plus float32 arithmetic (24-bit mantissa)
    assert np.max(np.abs(v - want)) <= (0.5 + 1e-3) / (WHITE - BLACK)
    assert np.max(want) == pytest.approx(0.9)   # exposure: brightest value 0.9


@pytest.mark.parametrize("camera", CAMERAS)
@pytest.mark.parametrize("illuminant", ["D65", "A", "FL11", "D93"])
def test_light_from_gray_patch_matches_truth(tmp_path, camera, illuminant):
    """Recover the light from the ColorChecker's neutral 5 patch in the decoded
    raw data (mean R, both greens, B after black subtraction) and compare its
    direction with the true camera RGB of the light.

    Tolerance: the patch is not perfectly flat, so even noiseless its RGB is
    theta0 away from the light (computed from its reflectance, the truth);
    noise and quantisation move each channel mean by at most tol_c (see
    _mean_tolerance), i.e. by a relative delta_c = tol_c / mean_c, which turns
    the direction by at most |delta| radians.
    """
    truth = scene_dng(tmp_path / "g.dng", camera, illuminant, H, W, seed=5)
    g = truth.patch_index("neutral 5")
    with rawpy.imread(str(tmp_path / "g.dng")) as raw:
        means, counts = _patch_channel_means(raw.raw_image, truth)
    est = means[g]
    theta0 = float(angular_error(truth.patch_rgb[g], truth.light_rgb))
    bound = np.degrees(np.linalg.norm(_mean_tolerance(truth, counts)[g] / truth.patch_rgb[g]))
    assert theta0 < 1.5                                   # a gray patch really is near-neutral
    assert float(angular_error(est, truth.light_rgb)) <= theta0 + bound
    # and the light is known to far better than the spread of illuminants
    assert float(angular_error(est, truth.light_rgb)) < 2.0


def test_postprocess_with_camera_whitebalance_renders_gray_as_gray(tmp_path):
    """End to end through LibRaw: linear demosaic in camera space, white
    balance from AsShotNeutral. The gray patch's interior comes out in the
    ratios patch / light (near 1 : 1 : 1), to 1 % (noise, 16-bit output)."""
    from scipy.ndimage import binary_erosion

    truth = scene_dng(tmp_path / "pp.dng", "Canon EOS 5D Mark II", "A", H, W, seed=9)
    with rawpy.imread(str(tmp_path / "pp.dng")) as raw:
        default = raw.postprocess()
        lin = raw.postprocess(use_camera_wb=True, output_color=rawpy.ColorSpace.raw, gamma=(1, 1),
                              no_auto_bright=True, output_bps=16, user_flip=0,
                              demosaic_algorithm=rawpy.DemosaicAlgorithm.LINEAR)
    assert default.shape == (H, W, 3) and default.dtype == np.uint8
    assert lin.shape == (H, W, 3) and lin.dtype == np.uint16
    g = truth.patch_index("neutral 5")
    inner = binary_erosion(truth.labels == g, iterations=2)
    rgb = lin[inner].astype(float).mean(0)
    want = truth.patch_rgb[g] / truth.light_rgb_scene
    np.testing.assert_allclose(rgb / rgb[1], want / want[1], rtol=0.01)


# ---------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------

def test_scene_dng_matches_spectral_scene_mondrian(tmp_path):
    kw = dict(layout="mondrian", n_surfaces=8, surfaces="rawtoaces-190")
    truth = scene_dng(tmp_path / "m.dng", "Nikon 5100 (NPL)", "FL11", 50, 70, 4, pattern="BGGR", **kw)
    with rawpy.imread(str(tmp_path / "m.dng")) as raw:
        np.testing.assert_array_equal(raw.raw_image, _expected_cfa(truth, **kw))
    sc = spectral_scene("Nikon 5100 (NPL)", "FL11", 50, 70, 4, **kw)
    assert len(np.unique(sc.labels)) > 2
    assert np.all((sc.shading[:-1] >= 0.5) & (sc.shading[:-1] <= 1.0))
    np.testing.assert_allclose(sc.light_rgb_normalised, truth.light_rgb)


def test_spectral_scene_truth():
    sc = spectral_scene("Canon EOS 5D Mark II", "D65", 40, 60, 0, grid=(4, 6),
                        noise_multiplicative=0, noise_additive=0)
    assert sc.image.shape == (40, 60, 3) and sc.image.dtype == np.float32
    assert sc.reflectances.shape == (25, sc.wavelengths.size)
    assert sc.patch_names[-1].startswith("frame")
    np.testing.assert_allclose(sc.image, sc.patch_rgb[sc.labels].astype(np.float32))
    # rho = kappa * sum E S R dlambda (Wandell 1985, eq. 12)
    dl = models.wavelength_step(sc.wavelengths)
    p = sc.patch_index("dark skin")
    rho = sc.exposure_scale * (sc.illuminant_spd * sc.reflectances[p] * dl) @ sc.sensitivities
    np.testing.assert_allclose(sc.patch_rgb[p], rho, rtol=1e-12)
    np.testing.assert_allclose(sc.light_rgb, sc.exposure_scale * (sc.illuminant_spd * dl) @ sc.sensitivities)
    again = spectral_scene("Canon EOS 5D Mark II", "D65", 40, 60, 0)
    assert np.array_equal(again.image, spectral_scene("Canon EOS 5D Mark II", "D65", 40, 60, 0).image)


def test_mosaic_and_patterns():
    rgb = np.arange(4 * 6 * 3).reshape(4, 6, 3)
    m = mosaic(rgb, "GRBG")
    assert m[0, 0] == rgb[0, 0, 1] and m[0, 1] == rgb[0, 1, 0]
    assert m[1, 0] == rgb[1, 0, 2] and m[1, 1] == rgb[1, 1, 1]
    np.testing.assert_array_equal(mosaic(rgb, [[1, 0], [2, 1]]), m)
    for bad in ("RGGX", "RGB", "RRGG", [[0, 1], [1, 3]]):
        with pytest.raises(ValueError):
            cfa_colour_indices(bad)
    with pytest.raises(ValueError):
        mosaic(np.zeros((4, 4)), "RGGB")


def test_write_dng_rejects_bad_input(tmp_path):
    p = tmp_path / "x.dng"
    ok = np.full((32, 32), 100, np.uint16)
    with pytest.raises(ValueError):
        write_dng(p, np.zeros((4, 4, 3), np.uint16))
    with pytest.raises(ValueError):
        write_dng(p, np.full((32, 32), 300), bits=8)
    with pytest.raises(ValueError):
        write_dng(p, np.full((32, 32), -1))
    with pytest.raises(ValueError):
        write_dng(p, ok, black_level=5000, white_level=4095)
    with pytest.raises(ValueError):
        write_dng(p, ok, color_matrix1=np.zeros((3, 3)))
    with pytest.raises(ValueError):
        write_dng(p, ok, make="Ñikon")
    with pytest.raises(ValueError):
        write_dng(p, ok, as_shot_neutral=[1.0, 0.0, 1.0])
    with pytest.raises(ValueError):
        write_dng(p, ok, bits=12)


def test_large_dng_round_trip(tmp_path):
    """A 6000 x 4000 (24 Mpx) uint16 CFA goes out without a copy and comes back
    whole (the write takes well under a second; see the module notes)."""
    cfa = np.empty((4000, 6000), np.uint16)
    cfa[:] = (np.arange(6000, dtype=np.uint16) * 2 + 512)[None, :]
    cfa[::2, ::2] += 7
    write_dng(tmp_path / "big.dng", cfa, black_level=512, white_level=16383)
    with rawpy.imread(str(tmp_path / "big.dng")) as raw:
        assert raw.raw_image.shape == (4000, 6000)
        np.testing.assert_array_equal(raw.raw_image, cfa)


# ---------------------------------------------------------------------------
# What LibRaw raises for bad files (for the service's 4xx mapping)
# ---------------------------------------------------------------------------

def _good_dng_bytes(tmp_path) -> bytes:
    scene_dng(tmp_path / "ok.dng", "Nikon 5100 (NPL)", "D65", H, W)
    return (tmp_path / "ok.dng").read_bytes()


def _decode(data: bytes, tmp_path, via: str):
    """imread then unpack (raw_image) then postprocess: LibRaw's imread only
    parses the header; a short file fails when the pixels are read."""
    if via == "file":
        p = tmp_path / "in.bin"
        p.write_bytes(data)
        src = str(p)
    else:
        src = io.BytesIO(data)
    with rawpy.imread(src) as raw:
        raw.raw_image
        raw.postprocess()


@pytest.mark.parametrize("via", ["file", "buffer"])
def test_truncated_dng_raises_libraw_io_error(tmp_path, via):
    data = _good_dng_bytes(tmp_path)
    for cut in (len(data) // 2, len(data) - 64, 2000, 100):
        with pytest.raises(rawpy.LibRawIOError):
            _decode(data[:cut], tmp_path, via)
    # the header survives, so imread itself succeeds: the error is at unpack
    with rawpy.imread(io.BytesIO(data[: len(data) // 2])) as raw:
        with pytest.raises(rawpy.LibRawIOError):
            raw.unpack()
    assert issubclass(rawpy.LibRawIOError, rawpy.LibRawFatalError)
    assert issubclass(rawpy.LibRawFatalError, rawpy.LibRawError)


@pytest.mark.parametrize("via", ["file", "buffer"])
def test_empty_file_raises_libraw_io_error(tmp_path, via):
    with pytest.raises(rawpy.LibRawIOError):
        _decode(b"", tmp_path, via)


@pytest.mark.parametrize("via", ["file", "buffer"])
@pytest.mark.parametrize("kind", ["random", "jpeg", "png", "rgb-tiff", "tiny-dng"])
def test_non_raw_files_raise_file_unsupported(tmp_path, via, kind):
    import cv2
    import tifffile

    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, size=(32, 48, 3), dtype=np.uint8)
    if kind == "random":
        data = rng.integers(0, 256, size=20000, dtype=np.uint8).tobytes()
    elif kind in ("jpeg", "png"):
        data = cv2.imencode("." + ("jpg" if kind == "jpeg" else "png"), img)[1].tobytes()
    elif kind == "rgb-tiff":
        buf = io.BytesIO()
        tifffile.imwrite(buf, img)
        data = buf.getvalue()
    else:  # LibRaw refuses images smaller than 22 x 22
        buf = io.BytesIO()
        write_dng(buf, np.full((16, 40), 700, np.uint16))
        data = buf.getvalue()
    with pytest.raises(rawpy.LibRawFileUnsupportedError):
        _decode(data, tmp_path, via)
    assert issubclass(rawpy.LibRawFileUnsupportedError, rawpy.LibRawNonFatalError)
