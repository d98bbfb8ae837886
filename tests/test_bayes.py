"""The Bayesian estimator over plausible lights (:mod:`recovery.bayes`) and
its candidate set (:mod:`recovery.illuminant_prior`).

Each check follows from the model, not from benchmark numbers:

* noise-free pixels of the very surfaces the statistics are built from,
  under one candidate light, are each a kernel centre of that candidate's
  density: the posterior must concentrate on it (or on candidates of the
  same camera chromaticity), so the error is a fraction of the kernel width;
* with a single candidate the posterior is a point mass: the answer is that
  light's camera response, exactly;
* only chromaticities and lightness relative to the brightest pixel enter,
  so multiplying the image by any constant changes nothing, and neither does
  the order of the pixels;
* the posterior mean of lights is a mixture of lights, so the reported
  spectrum's camera response has exactly the reported direction.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

import models
from recovery import Camera, angular_error
from recovery.bayes import bayes_model, estimate_bayes, helmert
from recovery.illuminant_prior import FAMILIES, candidate_lights, default_candidates, random_lights

from .conftest import gaussian_sensors

WL = models.DEFAULT_WAVELENGTHS


@pytest.fixture(scope="module")
def nikon():
    return Camera.named("Nikon 5100 (NPL)")


@pytest.fixture(scope="module")
def library():
    return models.reflectance_set("all", WL)


def _plain(diag: dict) -> None:
    for k, v in diag.items():
        assert isinstance(v, (bool, int, float, str, type(None))), (k, type(v))
        if isinstance(v, float):
            assert math.isfinite(v), k


def _scene(camera, spd, refl, shading=None):
    """Noise-free pixels rho = R^T (E * S) (eq. 12), one row per surface."""
    rho = camera.response(refl * spd)
    if shading is not None:
        rho = rho * shading[:, None]
    return rho


# --------------------------------------------------------------------------- candidates
def test_candidate_set_families_and_prior():
    c = default_candidates(WL)
    assert set(c.families) == set(FAMILIES)
    assert abs(c.prior.sum() - 1) < 1e-12 and np.all(c.prior > 0)
    assert np.allclose(c.spectra.mean(axis=1), 1.0) and np.all(c.spectra >= 0)
    # every colour-science illuminant is a candidate
    assert set(models.illuminant_names()) <= set(c.names)
    # excluding a family removes exactly it and renormalises the prior
    no_led = c.select(lambda n, f: not n.startswith("LED"))
    assert not any(n.startswith("LED") for n in no_led.names)
    assert abs(no_led.prior.sum() - 1) < 1e-12


def test_random_lights_are_physical():
    spd, names = random_lights(np.random.default_rng(1), 5, WL)
    assert spd.shape == (5, WL.size) and len(names) == 5
    assert np.all(spd >= 0) and np.allclose(spd.mean(axis=1), 1.0)


def test_helmert_is_an_orthonormal_sum_zero_basis():
    for c in (3, 4, 6):
        h = helmert(c)
        assert np.allclose(h @ h.T, np.eye(c - 1), atol=1e-14)
        assert np.allclose(h @ np.ones(c), 0, atol=1e-14)


# --------------------------------------------------------------------------- in-model recovery
@pytest.mark.parametrize("light", ["D65", "A", "FL11", "LED-B3"])
def test_training_surfaces_under_a_candidate_give_that_light(nikon, library, light):
    spd = models.illuminant(light, WL)
    shading = np.random.default_rng(3).uniform(0.5, 1.0, library.shape[0])
    rho = _scene(nikon, spd, library, shading)
    rgb, spectrum, diag = estimate_bayes(rho, None, nikon)
    truth = nikon.response(spd)
    # a kernel unit is ~4-5 degrees for this camera; 267 exact kernel centres
    # pin the light to a small fraction of it
    assert angular_error(rgb, truth) < 0.5
    assert diag["method"] == "bayes" and diag["distinct_colours"] > 50
    _plain(diag)


def test_light_off_the_candidate_set_is_interpolated(nikon, library):
    # a random daylight / blackbody mixture is not a candidate; the posterior
    # mean over neighbouring candidates (mixtures are lights) recovers it
    spd = random_lights(np.random.default_rng(11), 1, WL)[0][0]
    rgb, _, diag = estimate_bayes(_scene(nikon, spd, library), None, nikon)
    assert angular_error(rgb, nikon.response(spd)) < 1.5


def test_single_candidate_is_returned_exactly(nikon, library):
    spd = models.illuminant("FL2", WL)
    cands = candidate_lights(spd[None], WL, names=["only"])
    rho = _scene(nikon, models.illuminant("D65", WL), library[:20])
    rgb, spectrum, diag = estimate_bayes(rho, None, nikon, candidates=cands)
    want = nikon.response(spd)
    assert angular_error(rgb, want) < 1e-9
    assert diag["best_candidate"] == "only" and abs(diag["best_candidate_probability"] - 1) < 1e-12
    assert np.allclose(spectrum, spd / spd.mean())


def test_spectrum_response_matches_rgb(nikon, library):
    rho = _scene(nikon, models.illuminant("D50", WL), library[::3])
    rgb, spectrum, _ = estimate_bayes(rho, None, nikon)
    assert spectrum.shape == WL.shape and np.all(spectrum >= 0) and abs(spectrum.mean() - 1) < 1e-12
    assert angular_error(nikon.response(spectrum), rgb) < 1e-9


# --------------------------------------------------------------------------- invariances
def test_scale_invariance(nikon, library):
    rng = np.random.default_rng(5)
    img = _scene(nikon, models.illuminant("A", WL), library[rng.choice(library.shape[0], 16, replace=False)])
    img = np.repeat(img, 8, axis=0).reshape(16, 8, 3) * (1 + 0.01 * rng.standard_normal((16, 8, 3)))
    ref, _, d0 = estimate_bayes(img, None, nikon)
    for f in (1e-6, 1e6):
        rgb, _, d = estimate_bayes(img * f, None, nikon)
        assert angular_error(rgb, ref) < 1e-9
        assert d["best_candidate"] == d0["best_candidate"]


def test_pixel_order_and_mask(nikon, library):
    rng = np.random.default_rng(7)
    px = _scene(nikon, models.illuminant("D75", WL), library[:40])
    px = np.repeat(px, 5, axis=0) * (1 + 0.01 * rng.standard_normal((200, 3)))
    ref, _, _ = estimate_bayes(px, None, nikon)
    perm = rng.permutation(px.shape[0])
    assert angular_error(estimate_bayes(px[perm], None, nikon)[0], ref) < 1e-9
    # a mask selects exactly the pixels it keeps
    mask = np.zeros(px.shape[0], bool)
    mask[:120] = True
    junk = px.copy()
    junk[~mask] = [1.0, 0.01, 0.01]
    a = estimate_bayes(junk, mask, nikon)[0]
    b = estimate_bayes(px[:120], None, nikon)[0]
    assert angular_error(a, b) < 1e-9


# --------------------------------------------------------------------------- degenerate inputs
@pytest.mark.parametrize("img", [
    np.full((1, 1, 3), 0.5),
    np.full((8, 8, 3), 0.3),
    np.zeros((4, 4, 3)),
    np.array([[[np.nan, 1.0, 1.0], [np.inf, 0.2, 0.3]]]),
    -np.ones((3, 3, 3)),
])
def test_degenerate_inputs_are_finite(nikon, img):
    rgb, spectrum, diag = estimate_bayes(img, None, nikon)
    assert rgb.shape == (3,) and np.all(np.isfinite(rgb)) and abs(np.linalg.norm(rgb) - 1) < 1e-12
    assert np.all(rgb >= 0)
    assert spectrum is None or np.all(np.isfinite(spectrum))
    assert 0.0 <= diag["confidence"] <= 1.0
    assert isinstance(diag["decided_by"], str) and diag["decided_by"]
    _plain(diag)


def test_too_few_pixels_declares_the_fallback(nikon):
    rgb, spectrum, diag = estimate_bayes(np.array([[0.2, 0.4, 0.3]]), None, nikon)
    assert diag["method"] == "shades-of-gray" and "fallback" in diag["decided_by"]
    assert spectrum is None and diag["confidence"] == 0.0
    # with one pixel, shades of gray is that pixel
    assert angular_error(rgb, [0.2, 0.4, 0.3]) < 1e-9


def test_all_equal_image_uses_the_prior(nikon):
    rgb, spectrum, diag = estimate_bayes(np.full((16, 16, 3), 0.4), None, nikon)
    assert diag["method"] == "bayes" and diag["distinct_colours"] <= 1.0
    assert np.all(np.isfinite(spectrum)) and diag["confidence"] < 0.9


def test_diagnostics(nikon, library):
    rho = _scene(nikon, models.illuminant("D65", WL), library[::10])
    _, _, diag = estimate_bayes(rho, None, nikon)
    for key in ("confidence", "posterior_entropy", "best_candidate", "decided_by", "posterior_spread_deg",
                "distinct_colours", "pixels_used"):
        assert key in diag
    assert 0 <= diag["confidence"] <= 1 and diag["posterior_entropy"] >= 0
    assert diag["best_candidate"] in default_candidates(WL).names
    _plain(diag)


# --------------------------------------------------------------------------- other cameras
def test_six_channel_camera(library):
    cam = Camera(WL, gaussian_sensors([420, 470, 520, 570, 620, 670], 25.0), "six", "generic")
    spd = models.illuminant("FL3.8", WL)
    rho = _scene(cam, spd, library[::2])
    rgb, spectrum, diag = estimate_bayes(rho, None, cam)
    assert rgb.shape == (6,) and spectrum.shape == WL.shape
    assert angular_error(rgb, cam.response(spd)) < 0.5
    assert diag["lightness_term"] is False
    _plain(diag)


def test_matrix_derived_camera(library):
    # sensitivities implied by an XYZ -> camera matrix (negative lobes
    # clipped), the way matrix-derived cameras are made
    cmfs = models.observer("CIE 1931 2 Degree Standard Observer", WL)
    m = np.array([[1.2, -0.3, -0.1], [-0.4, 1.3, 0.1], [0.0, -0.2, 1.1]])
    r = np.clip(cmfs @ m.T, 0, None)
    cam = Camera(WL, r / r.max(), "matrix", "matrix-derived")
    spd = models.illuminant("D55", WL)
    rgb, _, diag = estimate_bayes(_scene(cam, spd, library), None, cam)
    assert angular_error(rgb, cam.response(spd)) < 0.5


def test_model_is_cached(nikon):
    a = bayes_model(nikon)
    b = bayes_model(Camera.named("Nikon 5100 (NPL)"))
    assert a is b


@pytest.fixture
def disk_cache(tmp_path, monkeypatch):
    """The model disk cache on, in a folder of its own, the in-memory cache
    emptied before and after (issue 19)."""
    from recovery import bayes

    monkeypatch.setenv("WANDELL_MODEL_CACHE_DIR", str(tmp_path))
    saved = dict(bayes._MODEL_CACHE)
    bayes._MODEL_CACHE.clear()
    bayes.enable_disk_cache(True)
    yield tmp_path
    bayes.enable_disk_cache(None)
    bayes._MODEL_CACHE.clear()
    bayes._MODEL_CACHE.update(saved)


def _same_model(a, b):
    from recovery import bayes

    for k in bayes._ARRAYS:
        x, y = getattr(a, k), getattr(b, k)
        assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), k
    assert (a.table_step, a.log_floor, a.settings) == (b.table_step, b.log_floor, b.settings)
    assert a.cache.keys() == b.cache.keys()
    for key in a.cache:
        for part in a.cache[key]:
            assert np.array_equal(a.cache[key][part], b.cache[key][part]), (key, part)


def test_model_from_disk_is_the_built_model(disk_cache, nikon, library):
    # a fresh process reads the model a build wrote: the same arrays bit for
    # bit, so the same estimate, every number of it but the timings
    from recovery import bayes

    built = bayes_model(nikon)
    assert built.loaded_from is None
    (key,) = bayes._MODEL_CACHE
    files = list(disk_cache.glob("bayes-*.npz"))
    assert len(files) == 1
    bayes._MODEL_CACHE.clear()                 # as a new process
    loaded = bayes_model(nikon)
    assert loaded is not built and loaded.loaded_from == str(files[0])
    _same_model(built, loaded)
    img = _scene(nikon, models.illuminant("A", WL), library[::3])
    timing = ("ms", "ms_after_model", "model_build_ms")
    outs = []
    for m in (built, loaded):
        bayes._MODEL_CACHE.clear()
        bayes._MODEL_CACHE[key] = m
        rgb, spectrum, diag = estimate_bayes(img, None, nikon)
        outs.append((rgb, spectrum, {k: v for k, v in diag.items() if k not in timing}))
    assert np.array_equal(outs[0][0], outs[1][0]) and np.array_equal(outs[0][1], outs[1][1])
    assert repr(outs[0][2]) == repr(outs[1][2])


def test_model_disk_cache_survives_bad_files(disk_cache, nikon, monkeypatch):
    # a truncated file is rebuilt and replaced; an unwritable folder only
    # means no file (the estimate never depends on the cache)
    from recovery import bayes

    built = bayes_model(nikon)
    (path,) = disk_cache.glob("bayes-*.npz")
    path.write_bytes(path.read_bytes()[:1000])
    bayes._MODEL_CACHE.clear()
    again = bayes_model(nikon)
    assert again.loaded_from is None
    _same_model(built, again)
    bayes._MODEL_CACHE.clear()
    assert bayes_model(nikon).loaded_from == str(path)
    bayes._MODEL_CACHE.clear()
    blocked = disk_cache / "file"
    blocked.write_text("not a folder")
    monkeypatch.setenv("WANDELL_MODEL_CACHE_DIR", str(blocked / "sub"))
    assert bayes_model(nikon).loaded_from is None
    monkeypatch.setenv("WANDELL_MODEL_CACHE_DIR", "off")
    assert bayes.disk_cache_dir() is None


def test_off_set_lights_option(nikon, library):
    # lights between and around the candidates (diagonal model), opt-in
    spd = models.illuminant("D65", WL)
    rgb, spectrum, diag = estimate_bayes(_scene(nikon, spd, library[::4]), None, nikon, off_set_prior=0.1)
    assert np.all(np.isfinite(rgb)) and np.all(np.isfinite(spectrum)) and np.all(spectrum >= 0)
    assert 0.0 <= diag["off_set_posterior_mass"] <= 1.0
    assert angular_error(rgb, nikon.response(spd)) < 1.0
    _plain(diag)
