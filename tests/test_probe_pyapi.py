"""Probe of the Python API at the numerical extremes (docs/probe_pyapi.md).

Each test pins one fault the probe found: it failed with the code before its
fix and passes after it. The contract is the one of ``tests/test_stability.py``:
every result of the public API is finite or an explicit
:class:`recovery.RecoveryError` naming what was wrong.
"""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

import models
from recovery import Camera, InputError, analyze, estimate_illuminant, render

WL = models.DEFAULT_WAVELENGTHS


def mondrian(cam: Camera, size: int = 32, k: int = 16, block: int = 4, seed: int = 0) -> np.ndarray:
    """``k`` shipped reflectances under D65 in ``block``-pixel squares, shaded, scaled to 0.9, with
    the development benchmark's noise (1 % multiplicative, 0.0005 additive), clipped to [0, 1]."""
    rng = np.random.default_rng(seed)
    refl = models.reflectance_set("all", cam.wavelengths)
    idx = rng.choice(len(refl), k, replace=False)
    labels = rng.integers(0, k, (size // block, size // block)).repeat(block, 0).repeat(block, 1)
    rho = cam.response(refl[idx] * models.illuminant("D65", cam.wavelengths)) * rng.uniform(0.5, 1.0, k)[:, None]
    img = rho[labels]
    img = img / img.max() * 0.9
    img = img * (1 + 0.01 * rng.standard_normal(img.shape)) + 0.0005 * rng.standard_normal(img.shape)
    return np.clip(img, 0.0, 1.0)


@pytest.fixture(scope="module")
def nikon() -> Camera:
    return Camera.named("Nikon 5100 (NPL)")


@pytest.fixture(scope="module")
def scene(nikon) -> np.ndarray:
    img = mondrian(nikon)
    img.flags.writeable = False
    return img


# --------------------------------------------------------------------------- 1: SLSQP segfault
def test_adjust_light_with_one_pixel_1e300_times_the_rest_does_not_crash_the_interpreter():
    """``render(..., gamut="adjust-light")`` of an image with one pixel at
    1e300 (the rest near 1) killed the Python process with a segmentation
    fault inside SciPy's SLSQP: the gamut constraints of the other pixels were
    rows of 1e-300. Run in a child process so a crash fails this test, not the
    suite. The answer is the documented error (the rendering exceeds float32)."""
    code = textwrap.dedent(f"""
        import numpy as np
        from recovery import Camera, InputError, estimate_illuminant, render
        from tests.test_probe_pyapi import mondrian
        cam = Camera.named("Nikon 5100 (NPL)")
        img = mondrian(cam)
        img[0, 0] = 1e300
        est = estimate_illuminant(img, cam, "auto")
        try:
            render(img, cam, est, "D65", "sRGB", gamut="adjust-light")
        except InputError as e:
            print("InputError:", e)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         cwd=str(__import__("pathlib").Path(__file__).resolve().parents[1]))
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    assert "InputError: rendered values exceed the float32 range" in out.stdout, out.stdout



# --------------------------------------------------------------------------- 2: rgb of norm overflow
def test_an_estimate_whose_rgb_norm_overflows_is_still_unit_norm(nikon, scene):
    """Gray edge on an image with one pixel at -1e300 (masked as dark, but its
    edges reach past the mask's erosion) gives a camera rgb near 1e299 whose
    norm overflows to inf: ``rgb / norm`` was [0, 0, 0], ``wb_multipliers``
    NaN, while ``rgb`` is documented as unit norm."""
    img = np.array(scene)
    img[0, 0] = -1e300
    est = estimate_illuminant(img, nikon, "gray-edge")
    assert np.all(np.isfinite(est.rgb)) and abs(np.linalg.norm(est.rgb) - 1) < 1e-12, est.rgb
    assert np.all(np.isfinite(est.wb_multipliers)) and np.all(est.wb_multipliers > 0), est.wb_multipliers


# --------------------------------------------------------------------------- 3: points
@pytest.fixture(scope="module")
def results(nikon, scene):
    return {est: analyze(scene, nikon, "gray-world", surface_estimator=est) for est in ("prior", "pinv")}


@pytest.mark.parametrize("estimator", ["prior", "pinv"])
@pytest.mark.parametrize("points", [[(1, 2, 3), (4, 5, 6)], [(1.7, 2.2)], [(np.nan, 0)], [(np.inf, 0)],
                                    [(10 ** 30, 0)], [(1e30, 0)], [("a", "b")], None, 5, [1, 2, 3], [(1 + 1j, 2)]],
                         ids=["P-by-3", "fraction", "nan", "inf", "huge-int", "huge-float", "str", "None", "scalar",
                              "odd", "complex"])
def test_points_that_are_not_integer_pairs_are_an_input_error(results, estimator, points):
    """``reflectance``/``surface_estimates`` took ``np.asarray(points,
    int).reshape(-1, 2)``: a (2, 3) array was read as three made-up pairs
    (an answer for points not asked for), ``(1.7, 2.2)`` as pixel (1, 2), and
    NaN, inf, 10**30, strings or None raised numpy's ValueError /
    OverflowError / TypeError instead of the documented InputError."""
    res = results[estimator]
    for fn in (res.reflectance, res.surface_estimates):
        with pytest.raises(InputError, match="points"):
            fn(points)


@pytest.mark.parametrize("points", [[(3, 4)], (3, 4), np.array([[3.0, 4.0]]), np.array([[3, 4]], np.uint8)])
def test_integer_points_in_any_form_give_the_same_answer(results, points):
    """What was accepted and meant stays: a list of pairs, one pair,
    integral floats, unsigned integers."""
    for res in results.values():
        np.testing.assert_array_equal(res.reflectance(points), res.reflectance([(3, 4)]))
    assert results["prior"].reflectance([]).shape == (0, WL.size)


# --------------------------------------------------------------------------- 4: masks
@pytest.mark.parametrize("quality", [None, "balanced"])
@pytest.mark.parametrize("mask", ["nan", "str", "object", "flat", "scalar"])
def test_a_mask_that_is_not_booleans_of_the_image_shape_is_an_input_error(nikon, mask, quality):
    """A NaN or string mask was taken as True everywhere (``np.asarray(mask,
    bool)``), silently; with ``quality`` (block averaging first) a flat or
    scalar mask raised numpy's IndexError and a string mask a ValueError."""
    img = np.repeat(np.repeat(mondrian(nikon), 12, 0), 12, 1)      # 384 x 384: block-averaged by "balanced"
    h, w = img.shape[:2]
    mk = {"nan": np.full((h, w), np.nan), "str": np.full((h, w), "x"), "object": np.full((h, w), None, object),
          "flat": np.ones(h * w, bool), "scalar": True}[mask]
    with pytest.raises(InputError, match="mask"):
        estimate_illuminant(img, nikon, "gray-world", mask=mk, quality=quality)


def test_a_numeric_mask_means_the_same_with_and_without_block_averaging(nikon):
    """Numbers are read as nonzero = use, before block averaging too: under
    ``quality`` a 2 x 2 block of a uint8 0/255 mask with one 255 averaged to
    127.5 > 1 and was kept, where the same mask as booleans (and the docs: "a
    block is masked out if any of its pixels is") leaves it out, so the two
    masks gave different lights."""
    img = np.repeat(np.repeat(mondrian(nikon), 12, 0), 12, 1)
    img[:, 192:] *= np.array([1.0, 0.6, 0.3])                        # the right half under another light
    keep = np.zeros(img.shape[:2], bool)
    keep[:, :191] = True                                              # the 2 x 2 blocks at cols 190-191: half kept
    for quality in (None, "balanced"):
        as_bool = estimate_illuminant(img, nikon, "gray-world", mask=keep, quality=quality, spatial=False)
        as_u8 = estimate_illuminant(img, nikon, "gray-world", mask=keep.astype(np.uint8) * 255, quality=quality,
                                    spatial=False)
        np.testing.assert_array_equal(as_u8.rgb, as_bool.rgb)


# --------------------------------------------------------------------------- 5: numerical options
@pytest.mark.parametrize("option, value", [("p", 0), ("p", -1), ("p", float("nan")), ("p", "6"),
                                           ("sigma", 0), ("sigma", -1), ("sigma", float("nan")), ("sigma", 1e6),
                                           ("overlap", 1), ("overlap", -0.5), ("overlap", float("nan")),
                                           ("region_size", 3.5), ("region_size", -4), ("region_size", "16")])
def test_numerical_options_out_of_range_are_an_input_error_naming_them(nikon, scene, option, value):
    """``p=0`` raised ZeroDivisionError; ``sigma`` <= 0 or NaN and ``overlap``
    outside [0, 1) the filters' / tiler's bare ValueError; ``region_size=3.5`` a
    TypeError from slicing; ``sigma=1e6`` ran a 8,000,001-tap filter (39 s on a
    32 x 32 image). Each is now an InputError naming the option, before any
    estimate."""
    for method in ("shades-of-gray", "gray-edge", "maloney-wandell"):
        with pytest.raises(InputError, match=option):
            estimate_illuminant(scene, nikon, method, spatial=True, **{option: value})


@pytest.mark.parametrize("value", [-5, 2.5, float("nan"), float("inf"), "abc"])
def test_analysis_pixels_that_is_not_a_pixel_count_is_an_input_error(nikon, scene, value):
    """``analysis_pixels=-5`` or NaN raised ValueError ("cannot convert float
    NaN to integer") from the block factor; inf an OverflowError; a string a
    ValueError from ``int()``."""
    with pytest.raises(InputError, match="analysis_pixels"):
        estimate_illuminant(scene, nikon, "gray-world", analysis_pixels=value)


@pytest.mark.parametrize("dtype", [str, object, complex])
def test_a_non_real_image_with_a_quality_is_refused_like_without(nikon, scene, dtype):
    """With ``quality`` (block averaging first) a str or object image raised
    numpy's TypeError from ``np.isfinite``, and a complex image was averaged
    as its real part (a ComplexWarning) and analysed, where without
    ``quality`` all three are the documented InputError."""
    img = np.repeat(np.repeat(np.array(scene), 4, 0), 4, 1).astype(dtype)
    for quality in ("fast", None):
        with pytest.raises(InputError, match="dtype"):
            estimate_illuminant(img, nikon, "gray-world", quality=quality)


def test_a_large_minkowski_p_gives_finite_multipliers_and_p_inf_is_white_patch(nikon, scene):
    """``p=1e6`` made every channel below the common maximum underflow to 0
    (``(x / max) ** 1e6``): shades-of-gray's rgb had zeros and
    ``wb_multipliers`` inf. ``p=inf``, documented as white patch, gave
    ``[max, max, max]`` (grey, whatever the image)."""
    for method in ("shades-of-gray", "gray-edge"):
        est = estimate_illuminant(scene, nikon, method, p=1e6)
        assert np.all(np.isfinite(est.wb_multipliers)) and np.all(est.rgb > 0), (method, est.rgb)
    wp = estimate_illuminant(scene, nikon, "white-patch")
    inf = estimate_illuminant(scene, nikon, "shades-of-gray", p=float("inf"))
    np.testing.assert_allclose(inf.rgb, wp.rgb, rtol=1e-12)
    assert not np.allclose(inf.rgb, 3 ** -0.5)


# --------------------------------------------------------------------------- 6: cameras
@pytest.mark.parametrize("case", ["unsorted", "repeated", "nan", "tiny", "huge"])
def test_a_camera_outside_the_documented_domain_is_an_input_error(nikon, case):
    """Unsorted or repeated wavelengths raised the grid's bare ValueError; a
    NaN wavelength was accepted; sensitivities peaking at 1e-300 gave a bare
    LinAlgError ("Singular matrix") from ``analyze(method="auto")`` and at
    1e300 NaN surface estimates (mean, std, expected_rmse)."""
    wl, s = nikon.wavelengths, nikon.sensitivities
    args = {"unsorted": (wl[::-1], s), "repeated": (np.r_[wl[:1], wl[:-1]], s), "nan": (np.r_[np.nan, wl[1:]], s),
            "tiny": (wl, s * 1e-300), "huge": (wl, s * 1e300)}[case]
    with pytest.raises(InputError, match="wavelengths|sensitivities"):
        Camera(*args)


def test_a_camera_sensitivities_scale_within_the_bounds_still_analyses(nikon, scene):
    """Inside the bounds a camera's scale does not matter (the light and the
    reflectance are the same for sensitivities times 1e-90 or 1e90)."""
    base = analyze(scene, nikon, "gray-world").reflectance([(3, 4)])
    for gain in (1e-90, 1e90):
        cam = Camera(nikon.wavelengths, nikon.sensitivities * gain)
        res = analyze(scene, cam, "gray-world")
        assert np.all(np.isfinite(res.reflectance([(3, 4)])))
        np.testing.assert_allclose(res.reflectance([(3, 4)]), base, rtol=1e-6, atol=1e-9)
