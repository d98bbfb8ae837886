"""The Maloney-Wandell analysis (Wandell 1985, eq. 26-36): the tests the
issue fixes, with tolerances from the mathematics.

In-model, noise-free data satisfy eq. 26 exactly, so the only error is
floating-point rounding amplified by the conditioning of the SVD steps
(eq. 30, 35): relative errors of order 1e-16 * cond, far below the 1e-6
degree and 1e-8 relative bounds.
"""

from __future__ import annotations

import numpy as np
import pytest

import models
from recovery import (Camera, InsufficientSurfaceVariation, ModelDimensionError, analyze, angular_error,
                      estimate_illuminant)
from recovery.lighting import lighting_matrix, lighting_tensor
from recovery.subspace import surface_weights

from .conftest import gaussian_sensors, in_model_scene

WL = models.DEFAULT_WAVELENGTHS


def _check_exact(cam, S, E, eps_true, rng):
    img, sig_true = in_model_scene(rng, cam, S, eps_true, E)
    est = estimate_illuminant(img, cam, method="maloney-wandell", surface_basis=S, light_basis=E,
                              dark_fraction=-np.inf, on_failure="raise")
    assert est.method == "maloney-wandell"
    true_rgb = cam.response(E @ eps_true)
    assert angular_error(est.rgb, true_rgb) < 1e-6
    assert angular_error(est.light_weights, eps_true) < 1e-6
    # surfaces (eq. 36) up to the one free scale alpha of eq. 27-28
    alpha = (est.light_weights @ eps_true) / (eps_true @ eps_true)
    T = lighting_tensor(E, S, cam.sensitivities, cam.dlambda)
    sig, cond = surface_weights(lighting_matrix(est.light_weights, T), img.reshape(-1, cam.channels))
    assert np.isfinite(cond)
    rel = np.linalg.norm(sig * alpha - sig_true) / np.linalg.norm(sig_true)
    assert rel < 1e-8
    return est


@pytest.mark.parametrize("d_e", [2, 3])
@pytest.mark.parametrize("camera", models.camera_names())
def test_in_model_exactness_rgb(camera, d_e, rng):
    cam = Camera.named(camera)
    S = models.surface_pca_model(2).basis
    E = models.daylight_model(d_e).basis
    eps_true = np.array([1.0, 0.4, -0.2])[:d_e]
    est = _check_exact(cam, S, E, eps_true, rng)
    assert est.diagnostics["subspace_fit_ratio"] < 1e-10
    assert not any("not confined" in w for w in est.warnings)


@pytest.mark.parametrize("d_s", [2, 3, 4, 5])
def test_in_model_exactness_six_channels(d_s, rng):
    cam = Camera(WL, gaussian_sensors([420, 460, 500, 540, 590, 640], 28.0), "six-channel", "uploaded")
    S = models.surface_pca_model(d_s).basis
    d_e = d_s + 1
    E = models.illuminant_pca_model(d_e).basis
    eps_true = models.illuminant_pca_model(d_e).project(models.illuminant("D50"))
    _check_exact(cam, S, E, eps_true, rng)
    # D(E) < D(S) + 1 works too
    _check_exact(cam, S, E[:, : d_s], eps_true[:d_s], rng)


def _real_scene(rng, k=12, size=48, camera="Nikon 5100 (NPL)", light="D50"):
    """A Mondrian of real reflectances under a real light (not in the model)."""
    cam = Camera.named(camera)
    refl = models.reflectance_set("all")[rng.choice(267, k, replace=False)]
    spd = models.illuminant(light)
    labels = rng.integers(0, k, size=(size // 8, size // 8)).repeat(8, 0).repeat(8, 1)
    shade = rng.uniform(0.5, 1.0, k)
    rho = cam.response(refl * spd)[labels] * shade[labels][..., None]
    return cam, rho / rho.max() * 0.9, cam.response(spd)


@pytest.mark.parametrize("method", ["maloney-wandell", "auto", "gray-world", "gray-edge"])
def test_scale_invariance(method, rng):
    cam, img, _ = _real_scene(rng)
    ref = estimate_illuminant(img, cam, method=method)
    for s in (1e-6, 1e6):
        est = estimate_illuminant(img * s, cam, method=method)
        assert est.method == ref.method
        assert angular_error(est.rgb, ref.rgb) < 1e-9


def test_noise_gives_finite_results_growing_with_noise(rng):
    cam = Camera.named("Sigma SDMerill (NPL)")
    S = models.surface_pca_model(2).basis
    E = models.daylight_model(3).basis
    errs = {0.0: [], 0.01: [], 0.05: []}
    for trial in range(12):
        eps = np.array([1.0, rng.uniform(-1, 1), rng.uniform(-0.5, 0.5)])
        img, _ = in_model_scene(rng, cam, S, eps, E)
        true_rgb = cam.response(E @ eps)
        for level in errs:
            noisy = img * (1 + level * rng.standard_normal(img.shape))
            est = estimate_illuminant(noisy, cam, method="maloney-wandell", surface_basis=S, light_basis=E)
            assert np.all(np.isfinite(est.rgb)) and np.all(np.isfinite(est.spectrum))
            assert all(np.all(np.isfinite(v)) for v in est.diagnostics.values() if isinstance(v, (float, list)))
            errs[level].append(angular_error(est.rgb, true_rgb))
    m0, m1, m5 = (np.mean(errs[k]) for k in (0.0, 0.01, 0.05))
    assert m0 < 1e-6 < m1 < m5


def test_one_surface_is_reported_with_declared_fallback(rng):
    cam = Camera.named("Nikon 5100 (NPL)")
    refl = models.reflectance_set("colorchecker")[5]
    img = np.broadcast_to(cam.response(refl * models.illuminant("A")), (16, 16, 3)).copy()
    with pytest.raises(InsufficientSurfaceVariation, match="surface variation"):
        estimate_illuminant(img, cam, method="maloney-wandell", on_failure="raise")
    est = estimate_illuminant(img, cam, method="maloney-wandell")
    assert est.method == "shades-of-gray"
    assert est.diagnostics["decision"].startswith("fallback to shades-of-gray")
    assert any("could not run" in w for w in est.warnings)


def test_data_filling_sensor_space_warns(rng):
    cam = Camera.named("Nikon 5100 (NPL)")
    img = rng.uniform(0.05, 1.0, size=(32, 32, 3))
    est = estimate_illuminant(img, cam, method="maloney-wandell")
    assert any("not confined to a subspace" in w for w in est.warnings)
    assert est.diagnostics["subspace_fit_ratio"] > 0.1
    auto = estimate_illuminant(img, cam, method="auto")
    assert auto.method != "maloney-wandell" and auto.diagnostics["decision"]


def test_dimension_rules_are_refused_by_name(rng):
    cam = Camera.named("Nikon 5100 (NPL)")
    img = rng.uniform(0.05, 1.0, size=(8, 8, 3))
    with pytest.raises(ModelDimensionError, match=r"D\(E\) <= D\(S\) \+ 1"):
        estimate_illuminant(img, cam, method="maloney-wandell", surface_dim=1, light_dim=3)
    with pytest.raises(ModelDimensionError, match=r"D\(S\) < C"):
        estimate_illuminant(img, cam, method="maloney-wandell", surface_dim=3, light_dim=3)
    six = Camera(WL, gaussian_sensors([420, 460, 500, 540, 590, 640]), "six")
    with pytest.raises(ModelDimensionError, match=r"D\(S\) < C"):
        estimate_illuminant(rng.uniform(0.1, 1, (8, 8, 6)), six, method="maloney-wandell", surface_dim=6)


def test_two_light_gradient_light_map(rng):
    """In-model, noise-free, the light mixes linearly from A (left) to D65
    (right). Each region sees a nearly constant light; the map must match the
    true light within 1 degree at every region centre."""
    cam = Camera.named("Canon EOS 5D Mark II")
    S = models.surface_pca_model(2).basis
    Em = models.daylight_model(3)
    e_a, e_b = Em.project(models.illuminant("A")), Em.project(models.illuminant("D65"))
    h, w = 96, 256
    sig = rng.normal(scale=0.3, size=(h * w, 2))
    sig[:, 0] = 1 + np.abs(sig[:, 0])
    t = np.tile(np.linspace(0, 1, w), h)
    eps = (1 - t)[:, None] * e_a + t[:, None] * e_b
    spd = eps @ Em.basis.T
    img = cam.response((sig @ S.T) * spd).reshape(h, w, 3)
    res = analyze(img, cam, method="maloney-wandell", spatial=True, region_size=32, overlap=0.5,
                  surface_basis=S, light_basis=Em.basis, dark_fraction=-np.inf, on_failure="raise")
    lm = res.illuminant.light_map
    assert lm is not None and lm.used.all()
    rr, cc = np.meshgrid(lm.centres_r, lm.centres_c, indexing="ij")
    est_rgb = cam.response(lm.spectra_at(rr.ravel(), cc.ravel()))
    tc = cc.ravel() / (w - 1)
    true_rgb = cam.response(((1 - tc)[:, None] * e_a + tc[:, None] * e_b) @ Em.basis.T)
    errs = angular_error(est_rgb, true_rgb)
    assert errs.max() < 1.0
    # and the map really follows the gradient: the ends differ by much more
    assert angular_error(cam.response(Em.basis @ e_a), cam.response(Em.basis @ e_b)) > 10


def test_user_bases_and_peers_on_real_scene(rng):
    cam, img, truth = _real_scene(rng, k=16)
    for m in ("gray-world", "white-patch", "shades-of-gray", "gray-edge", "maloney-wandell", "auto"):
        est = estimate_illuminant(img, cam, method=m)
        assert est.rgb.shape == (3,) and np.all(np.isfinite(est.rgb))
        assert est.spectrum.shape == WL.shape and np.all(np.isfinite(est.spectrum))
        assert angular_error(est.rgb, truth) < 45
    fourier = models.fourier_model(2).basis
    est = estimate_illuminant(img, cam, method="maloney-wandell", surface_basis=fourier,
                              light_basis="illuminant-pca")
    assert est.diagnostics["surface_model"] == "user-surface-2"


def test_analyze_reflectance_recovers_in_model_surfaces(rng):
    """With the light known exactly and surfaces inside the 3-term model the
    reflectance estimate (eq. 36 with D(S) = C) is exact up to the scale."""
    cam = Camera.named("Nikon 5100 (NPL)")
    S3 = models.surface_pca_model(3).basis
    refl = models.reflectance_set("colorchecker")
    refl_in = models.surface_pca_model(3).fit(refl)
    spd = models.illuminant("D65")
    rho = cam.response(refl_in * spd)
    img = rho.reshape(4, 6, 3)
    res = analyze(img, cam, method="gray-world", surface_estimator="pinv")
    # replace the estimate by the true light to isolate eq. 36
    res.illuminant.spectrum = spd
    got = res.reflectance([(r, c) for r in range(4) for c in range(6)])
    scale = np.sum(got * refl_in) / np.sum(got * got)
    assert np.allclose(got * scale, refl_in, atol=1e-10)
    assert S3.shape == (31, 3)


def test_every_method_is_one_registry_entry_with_one_signature(rng):
    """Issue 18: recovery.methods names every method, its description and the
    kind of estimator that runs it; ESTIMATORS is built from it, every
    estimator takes one EstimatorInput (evidence, camera, options), and a
    method added to the table is dispatched without touching the core."""
    import inspect

    from recovery import api, methods

    assert tuple(methods.METHODS) == api.METHODS == methods.METHOD_NAMES
    assert all(m.description and m.runs in api.ESTIMATOR_KINDS for m in methods.METHODS.values())
    for fn in api.ESTIMATOR_KINDS.values():
        assert list(inspect.signature(fn).parameters)[0] == "run"
    cam = Camera.named("Nikon 5100 (NPL)")
    img = rng.uniform(0.05, 0.9, (16, 16, 3)) * cam.response(models.illuminant("D65"))
    seen = {}

    def probe(run):
        seen["run"] = run
        return api.ESTIMATOR_KINDS["peer"](run)

    old = dict(api.ESTIMATORS)
    try:
        api.ESTIMATORS["gray-world"] = probe
        est = estimate_illuminant(img, cam, "gray-world", spatial=False)
    finally:
        api.ESTIMATORS.clear()
        api.ESTIMATORS.update(old)
    run = seen["run"]
    assert isinstance(run.evidence, api.Evidence) and isinstance(run.options, api.EstimationOptions)
    assert run.camera is cam and run.options.method == "gray-world" and est.method == "gray-world"
