"""Issues 12 and 16: the learnt default estimator on real photographs.

The method's pieces on arrays (no data needed), the shipped model, and,
on the development photographs (``../shared/data/real``: NUS 8-camera,
Cube+, INTEL-TAU field; skipped with a reason without them, failing when
``CI`` is set), leave-one-benchmark-out accuracy against shades of gray in
the same run, the calibration of the reported 90 % region and of the
confidence on each left-out benchmark, the same estimate whatever describes
the camera, the rebuild of the shipped model, and the same estimate
through ``/v1/analyze`` on a DNG written from a real thumbnail.
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from recovery import Camera, estimate_illuminant
from recovery import learned as L
from recovery.api import angular_error

from .conftest import SHARED, unavailable

REAL = SHARED / "data" / "real"

#: camera-description agreement bounds (degrees; see the test)
MEDIAN_FIT, P90_FIT, MEDIAN_PERT, P90_PERT = 0.16, 0.63, 0.31, 1.16


# --------------------------------------------------------------------------- the pieces
def test_log_chroma_round_trip_and_diagonal_shift():
    rgb = np.array([[0.2, 0.5, 0.3], [0.4, 0.4, 0.2]])
    np.testing.assert_allclose(L.uv_to_rgb(L.rgb_to_uv(rgb)), rgb / rgb.sum(1, keepdims=True), rtol=1e-12)
    # a light change by a diagonal matrix is a shift of (u, v) (the diagonal model)
    d = np.array([1.3, 1.0, 0.7])
    np.testing.assert_allclose(L.rgb_to_uv(rgb * d) - L.rgb_to_uv(rgb), np.tile(L.rgb_to_uv(d), (2, 1)), atol=1e-12)


def test_estimation_image_is_the_area_average_of_usable_pixels():
    rng = np.random.default_rng(0)
    img = rng.uniform(0.1, 1.0, (128, 192, 3))
    mask = np.ones(img.shape[:2], bool)
    mask[0, :2] = False                       # 2 of the 6 pixels of cell (0, 0) (rows 0-1, columns 0-2)
    mask[2:4, 3:6] = False                    # all of cell (1, 1)
    mask[4, 6:9] = False                      # 3 of 6 of cell (2, 2): half usable is enough
    mask[6:8, 9:11] = False                   # 4 of 6 of cell (3, 3): too few
    cells, ok = L.estimation_image(img, mask)
    assert cells.shape == (64, 64, 3) and ok.sum() == 64 * 64 - 2 and not ok[1, 1] and not ok[3, 3]
    # a cell is the mean of its usable pixels, not of the masked ones
    np.testing.assert_allclose(cells[0, 0], img[:2, :3][mask[:2, :3]].mean(0), rtol=1e-5)
    np.testing.assert_allclose(cells[2, 2], img[4:6, 6:9][mask[4:6, 6:9]].mean(0), rtol=1e-5)
    np.testing.assert_allclose(cells[5, 7], img[10:12, 21:24].reshape(-1, 3).mean(0), rtol=1e-5)
    # small images are kept as they are
    small, ok2 = L.estimation_image(img[:32, :40], mask[:32, :40])
    assert small.shape == (32, 40, 3) and ok2.sum() == mask[:32, :40].sum()


def test_fitted_colour_matrix_describes_a_measured_camera():
    """For a camera with measured sensitivities the Luther fit ``R ~ cmfs M^T``
    is what maps it to the canonical space; it must reproduce the camera's
    response to daylight-like lights within a few degrees (real cameras are
    not colorimetric, so not exactly)."""
    from models import illuminant, observer

    cam = Camera.named("Nikon 5100 (NPL)")
    m = L.camera_color_matrix(cam)
    assert m.shape == (3, 3) and np.isclose((m @ L._D65_XYZ).max(), 1.0)
    cmfs = observer("CIE 1931 2 Degree Standard Observer", cam.wavelengths)
    for name in ("D65", "A", "D50"):
        spd = illuminant(name, cam.wavelengths)
        xyz = cmfs.T @ (spd * cam.dlambda)
        assert angular_error(m @ xyz, cam.response(spd)) < 3.0, name


def test_uncertainty_law_is_calibrated_on_what_it_is_given():
    """fit_uncertainty sizes the region so that 90 % of the residuals it is
    given fall inside: on residuals drawn from the model it assumes
    (isotropic Gaussian whose variance grows with the spread), the fitted law
    must cover 90 % of fresh draws within the binomial spread (3 sigma)."""
    rng = np.random.default_rng(1)
    n = 4000
    spread = rng.uniform(0.005, 0.2, n)
    var = 0.0004 + 0.5 * spread ** 2
    d2 = var * rng.chisquare(2, n)
    sig = L.fit_uncertainty(spread, d2)
    spread2 = rng.uniform(0.005, 0.2, n)
    d2_new = (0.0004 + 0.5 * spread2 ** 2) * rng.chisquare(2, n)
    inside = np.mean(d2_new <= L.CHI2_90 * L.variance_from_spread(spread2, sig))
    assert abs(inside - 0.9) < 3 * np.sqrt(0.09 / n) + 0.01


def test_robust_ridge_reaches_the_unique_minimum_whatever_the_order_of_the_sums():
    """The fit is convex (fixed random features, a smooth Euclidean loss, a
    ridge), so the iterations reach one minimum: the same coefficients when
    the images are given in another order (every sum then runs in another
    order), to far below what an estimate could show (1e-6 in log-chroma is
    0.00003 degrees); and no nearby point has a lower objective."""
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3000, 8))
    y = np.c_[np.tanh(x[:, 0]) + 0.3 * x[:, 1], x[:, 2] * 0.5] + 0.05 * rng.standard_t(3, (3000, 2))
    w = rng.uniform(0.5, 1.5, 3000)
    a = L.fit_robust_ridge(x, y, w, hidden=40, ridge=0.01)
    p = rng.permutation(3000)
    b = L.fit_robust_ridge(x[p], y[p], w[p], hidden=40, ridge=0.01)
    np.testing.assert_allclose(a[2], b[2], atol=1e-6)
    pw, pb = L.random_expansion(8, 40, 0)
    Z = L.expand(x, a[0], a[1], pw, pb)
    ww = w / w.sum()

    def obj(B):
        return (ww * np.sqrt(((Z @ B - y) ** 2).sum(1) + 0.02 ** 2)).sum() + 0.01 * (B[:-1] ** 2).sum()

    f0 = obj(a[2])
    for _ in range(20):
        assert obj(a[2] + 1e-3 * rng.normal(size=a[2].shape)) >= f0 - 1e-9


def test_locus_coordinates_place_a_light_along_and_off_the_locus():
    """On the locus the off-locus distance is 0 and the first coordinate its
    mired / 100; a step perpendicular to the locus is the signed distance."""
    model = L.load_model()
    lu, lm = model.locus_uv, model.locus_mired
    j = len(lm) // 2
    c = L.locus_coordinates(lu[j], lu, lm)
    assert np.isclose(c[0], lm[j] / 100) and abs(c[1]) < 1e-12
    t = lu[j + 1] - lu[j - 1]
    n = np.array([t[1], -t[0]]) / np.linalg.norm(t)
    c2 = L.locus_coordinates(lu[j] + 0.01 * n, lu, lm)
    assert np.isclose(abs(c2[1]), 0.01, rtol=1e-3)


def test_shipped_model_loads_without_the_development_data_and_says_what_it_learnt():
    model = L.load_model()
    assert model.info["command"] == "python -m benchmarks.train_illuminant"
    assert set(model.info["benchmarks"]) == {"NUS 8-camera", "Cube+", "INTEL-TAU field"}
    assert len(model.info["cameras"]) == 12 and sum(model.info["cameras"].values()) == 7524
    assert model.info["features"] == list(L.FEATURE_NAMES)
    # no ridge is chosen: the model averages the fits over the whole grid
    assert model.info["selection"]["chosen_ridge"] == model.info["settings"]["ridge_grid"]
    assert model.info["settings"]["ridge_combination"] == "average"
    assert L.DEFAULT_MODEL_PATH.stat().st_size < 100_000      # a small data file


def test_learnt_estimate_has_a_physical_spectrum():
    from testing.scenes import mondrian_scene  # a synthetic scene: only the plumbing is checked here

    cam = Camera.named("Nikon 5100 (NPL)")
    scene = mondrian_scene(np.random.default_rng(3), 16, "Nikon 5100 (NPL)", "D65", size=64, step=10.0)
    img = scene.image
    est = estimate_illuminant(img, cam, "learned")
    assert est.method == "learned"
    d = est.diagnostics
    assert 0.0 <= d["confidence"] <= 1.0 and d["region90_deg"] > 0 and isinstance(d["low_confidence"], bool)
    assert np.all(np.isfinite(est.rgb)) and np.all(est.spectrum >= 0) and np.all(np.isfinite(est.spectrum))
    # the spectrum's camera response is the reported light
    assert angular_error(cam.response(est.spectrum), est.rgb) < 0.5
    assert estimate_illuminant(img, cam, "bayes").method == "bayes"       # the posterior stays by name


def test_auto_lets_the_posterior_decide_a_scene_of_uniform_patches_and_says_so():
    """A Mondrian is flat patches (most cells inside one): ``auto`` hands it
    to the light posterior, whose linear models hold there, and says what
    decided; the same image with texture (multiplicative 10 % noise per
    pixel, as real surfaces have) goes to the learnt estimator."""
    from testing.scenes import mondrian_scene

    cam = Camera.named("Nikon 5100 (NPL)")
    scene = mondrian_scene(np.random.default_rng(3), 8, "Nikon 5100 (NPL)", "D65", size=64, step=10.0)
    est = estimate_illuminant(scene.image, cam)
    d = est.diagnostics
    assert est.method == "bayes" and d["decision"].startswith("auto:") and "uniform patches" in d["decision"]
    assert d["uniform_patch_fraction"] >= 0.15 and {"confidence", "low_confidence", "region90_deg"} <= set(d)
    textured = scene.image * np.random.default_rng(4).uniform(0.8, 1.2, scene.image.shape[:2])[..., None]
    est2 = estimate_illuminant(np.clip(textured, 0, 1), cam)
    assert est2.method == "learned" and est2.diagnostics["decision"].startswith("auto:")
    assert est2.diagnostics["uniform_patch_fraction"] < 0.15


def test_auto_keeps_the_posteriors_accuracy_on_synthetic_mondrians():
    """Issue 16, item 4: where the linear models hold (the development
    benchmark's Mondrians, ``python -m benchmarks.synthetic``), ``auto`` is
    within 1.2x the posterior's median angular error at every K (measured
    on its 100 scenes per K: 1.00, 1.05, 1.03, 1.00 for K = 4, 8, 16, 32);
    here on its first 12 scenes per K."""
    from benchmarks.synthetic import draw_scene, named_camera

    for k in (4, 8, 16, 32):
        ea, eb = [], []
        for i in range(12):
            sc = draw_scene(0, k, i, 64)
            cam = named_camera(sc.camera_name)
            ea.append(angular_error(estimate_illuminant(sc.image, cam, white_level=1.0).rgb, sc.rgb_true))
            eb.append(angular_error(estimate_illuminant(sc.image, cam, "bayes", white_level=1.0).rgb, sc.rgb_true))
        assert np.median(ea) <= 1.2 * np.median(eb), (k, np.median(ea), np.median(eb))


def test_no_usable_cells_falls_back_declared():
    cam = Camera.named("Nikon 5100 (NPL)")
    img = np.full((40, 40, 3), 0.5)
    img[:, :, 1] = 1.0                         # every pixel saturated in green
    img[0, 0] = [0.3, 0.4, 0.2]
    est = estimate_illuminant(img, cam, white_level=1.0)
    assert est.method != "learned" and "fallback" in est.diagnostics["decision"]


# --------------------------------------------------------------------------- real photographs
@pytest.fixture(scope="module")
def real(load_real_once):
    for f in ("nus8.npz", "cubeplus.npz", "tau_field.npz", "cameras.json"):
        if not (REAL / f).is_file():
            unavailable(f"{REAL / f} is absent (the development photographs are not next to the project)")
    from benchmarks.train_illuminant import dataset_features

    rs = load_real_once(REAL)     # loaded once a session (test_bayes_spectra uses them too)
    feats, tuv, Ks, gam = dataset_features(rs)
    return rs, feats, tuv, Ks, gam


@pytest.fixture(scope="module")
def sog_errors(real):
    from benchmarks.realdata import usable_mask
    from recovery.estimators import shades_of_gray

    rs = real[0]
    return angular_error(np.array([shades_of_gray(im, usable_mask(im), 6.0) for im in rs.images]), rs.truth)


@pytest.fixture(scope="module")
def same_fits():
    """:func:`recovery.learned.fit_robust_ridge` computed once per distinct
    call in this module: a call with the same inputs (bytes of ``x``, ``y``
    and the weights) and settings as an earlier one gets that call's answer
    (copies). The fit is a deterministic function of its inputs (its
    docstring; ``test_rebuilding_the_model_gives_the_shipped_one`` relies on
    it), so this only saves time: the rebuild's inner leave-one-benchmark-out
    fits each ridge on two of the three benchmarks, exactly the fits
    :func:`lodo`'s outer folds make on their training benchmarks (12 of its
    16 fits, about half of its minute). Returns the record of the calls (the
    number computed and the number given again)."""
    import hashlib

    computed = L.fit_robust_ridge
    memo, record = {}, {"computed": 0, "again": 0}

    def digest(a):
        a = np.ascontiguousarray(a, np.float64)
        return a.shape, hashlib.sha256(a.tobytes()).hexdigest()

    def fit(x, y, weights=None, **kw):
        key = (digest(x), digest(y), None if weights is None else digest(weights), tuple(sorted(kw.items())))
        if key in memo:
            record["again"] += 1
        else:
            record["computed"] += 1
            memo[key] = computed(x, y, weights, **kw)
        mean, scale, coef, info = memo[key]
        return mean.copy(), scale.copy(), coef.copy(), dict(info)

    mp = pytest.MonkeyPatch()
    mp.setattr(L, "fit_robust_ridge", fit)
    yield record
    mp.undo()


@pytest.fixture(scope="module")
def lodo(real, sog_errors, same_fits):
    """Leave one benchmark out with the shipped ridges (the average of the
    fits over the grid, as the full command and the benchmark do), the
    uncertainty calibrated by the inner loop on the training benchmarks
    only."""
    from benchmarks.train_illuminant import SETTINGS, leave_one_benchmark_out, single_threaded

    rs, feats, tuv, Ks, gam = real
    settings = {**SETTINGS, "ridge_grid": [L.load_model().info["selection"]["chosen_ridge"]]}
    with single_threaded():
        return leave_one_benchmark_out(rs, feats, tuv, Ks, settings, log=lambda s: None, sog=sog_errors, gam=gam)


def test_leave_one_benchmark_out_beats_shades_of_gray(real, lodo, sog_errors):
    """A benchmark never seen in training, as a user's photographs are: the
    learnt default's mean is below shades of gray's on each left-out
    benchmark, and pooled over the three its mean and median are (measured
    in the same run; the issue's tighter ratio targets are reported by
    ``python -m benchmarks.real_photos``, not all met)."""
    from benchmarks.realdata import error_stats

    rs = real[0]
    err = np.zeros(len(rs.truth))
    for b, (_, res, te) in lodo.items():
        err[te] = res["err"]
        assert res["err"].mean() < sog_errors[te].mean(), (b, res["err"].mean(), sog_errors[te].mean())
    a, g = error_stats(err), error_stats(sog_errors)
    assert a["mean"] < g["mean"] and a["median"] < g["median"], (a, g)


def test_the_model_is_not_applied_beyond_the_out_of_gamut_fractions_it_was_trained_on(real, lodo):
    """A D65 colour matrix under tungsten light (Cube+'s Canon 550D indoors)
    sends many cells out of the canonical gamut, so the model's evidence is
    outside what it learnt from. Each left-out model's limit is the 99th
    percentile of its *training* images' fractions; beyond it the reference
    (bright pixels) stands and the diagnostics say so. On the development
    data this moves 69 of Cube+'s 1,707 images, 2 of NUS's and none of
    INTEL-TAU's; pooled over them the reference is better than the model
    (measured 4.1 -> 1.3 degrees; on NUS's two the model was the better,
    1.3 against 2.4, so the claim is on the pool, not each benchmark)."""
    from benchmarks.realdata import usable_mask
    from benchmarks.train_illuminant import SETTINGS, camera_errors, usable

    rs, feats, tuv, Ks, gam = real
    good = usable(feats)
    e_model, e_ref = [], []
    for b, (model, res, te) in lodo.items():
        tr = (rs.dataset != b) & good
        assert float(model.gamut_limit[0]) == pytest.approx(np.percentile(gam[tr], SETTINGS["gamut_quantile"]))
        out = model.outside(gam[te]) & good[te]
        assert out.sum() <= 0.1 * len(te), b
        i = te[out]
        if i.size:
            applied = feats[i, L.REFERENCE] + model.predict(model.inputs(feats[i]))
            e_model += list(camera_errors(applied, rs.truth[i], rs.camera[i], Ks))
            e_ref += list(camera_errors(feats[i, L.REFERENCE], rs.truth[i], rs.camera[i], Ks))
            np.testing.assert_allclose(res["uv"][out], feats[i, L.REFERENCE], atol=1e-12)
    assert len(e_ref) >= 20 and np.mean(e_ref) < np.mean(e_model), (len(e_ref), np.mean(e_ref), np.mean(e_model))
    # the product path says so, and gives the reference there
    model = L.load_model()
    i = int(np.flatnonzero(good & model.outside(gam))[0])
    r = L.estimate_learned(rs.images[i], usable_mask(rs.images[i]), rs.matrices[rs.camera[i]], model)
    assert r.diagnostics["outside_training_range"] and r.diagnostics["out_of_gamut_fraction"] > model.gamut_limit[0]
    np.testing.assert_allclose(r.uv, feats[i, L.REFERENCE], atol=1e-12)
    j = int(np.flatnonzero(good & ~model.outside(gam))[0])
    r = L.estimate_learned(rs.images[j], usable_mask(rs.images[j]), rs.matrices[rs.camera[j]], model)
    assert not r.diagnostics["outside_training_range"]
    assert r.diagnostics["out_of_gamut_fraction"] == pytest.approx(gam[j], abs=1e-12)


def test_where_the_reference_stands_it_reports_its_own_record(real, lodo):
    """Beyond the gamut limit the estimate is the bright-pixel reference, so
    its confidence and 90 % radius are the reference's record on the
    training images beyond the limit (it has no learnt parameters: those are
    held-out errors), not the model's spread law, which was fitted to the
    model's residuals and called these 0.25 likely within 3 degrees when 0.90
    were. Left out a benchmark at a time (69 of Cube+'s images, 2 of NUS's),
    measured: Cube+ predicted 0.56 (the other benchmarks' record) against
    0.90 observed; the radius (12.1 degrees for Cube+, from NUS and
    INTEL-TAU's 59 images) held all 69. Asserted: the calibration is that
    record, recomputed here; pooled over the left-out images it is nearer the
    observed fraction than the spread law's; the radius holds at least 80 %
    of them (90 % expected; 71 images give a binomial spread of 0.036)."""
    from benchmarks.realdata import usable_mask
    from benchmarks.train_illuminant import SETTINGS, camera_errors, usable

    rs, feats, tuv, Ks, gam = real
    good = usable(feats)
    pred_new, pred_old, obs, held = [], [], [], []
    for b, (model, res, te) in lodo.items():
        tr = np.flatnonzero((rs.dataset != b) & good)
        beyond = tr[gam[tr] > np.percentile(gam[tr], SETTINGS["gamut_quantile"])]
        e_tr = camera_errors(feats[beyond, L.REFERENCE], rs.truth[beyond], rs.camera[beyond], Ks)
        oc = model.outside_calibration
        assert oc[1] == pytest.approx((np.sum(e_tr < 3) + 1) / (len(e_tr) + 2), abs=1e-12)
        assert oc[2] == pytest.approx(np.quantile(e_tr, 0.9), abs=1e-9)
        tu = te[res["usable"]]
        out = model.outside(gam[tu])
        if not out.any():
            continue
        e = res["err_usable"][out]
        spread = L._spread(feats[tu[out]], res["uv"][res["usable"]][out])
        var = L.variance_from_spread(spread, model.sigma)
        old = [L.confidence(L.radius90(u, float(v), Ks[c]), model.confidence_coef)
               for u, v, c in zip(res["uv"][res["usable"]][out], var, rs.camera[tu[out]])]
        np.testing.assert_allclose(res["confidence"][out], oc[1])
        pred_new += list(res["confidence"][out])
        pred_old += old
        obs += list(e < 3.0)
        held += list(e <= res["radius90_deg"][out])
    assert len(obs) >= 20
    assert abs(np.mean(pred_new) - np.mean(obs)) < abs(np.mean(pred_old) - np.mean(obs)), (
        np.mean(pred_new), np.mean(pred_old), np.mean(obs))
    assert np.mean(held) >= 0.8, np.mean(held)
    # the product path reports the same record (its region, and the record as ``radius_confidence``); the
    # confidence it reports is the confidence law's (issue 27, recovery.confidence: the out-of-gamut
    # fraction is one of its inputs, and its left-out figures, docs/confidence.md, are measured that way)
    from recovery.confidence import load_flag_model

    model = L.load_model()
    i = int(np.flatnonzero(good & model.outside(gam))[0])
    r = L.estimate_learned(rs.images[i], usable_mask(rs.images[i]), rs.matrices[rs.camera[i]], model)
    assert r.diagnostics["radius_confidence"] == pytest.approx(model.outside_calibration[1])
    assert r.radius90_deg == pytest.approx(model.outside_calibration[2])
    fm = load_flag_model()
    x = np.array([[r.diagnostics["flag_inputs"][n] for n in fm.names]])
    assert r.confidence == pytest.approx(float(fm.confidence(x)[0]), abs=1e-12)


def test_reported_90_percent_region_holds_the_light_85_to_95_percent_of_each_left_out_benchmark(lodo):
    """Calibrated on the inner loop's out-of-fold residuals (training
    benchmarks only), the region holds the light for 85-95 % of the images
    of the benchmark left out."""
    for b, (_, res, _) in lodo.items():
        assert 0.85 <= res["inside90"].mean() <= 0.95, (b, res["inside90"].mean())


def test_confidence_is_calibrated_on_left_out_benchmarks(lodo):
    """``confidence`` is P(error < 3 deg): on a benchmark neither the model
    nor its confidence law saw, predicted and observed fractions agree
    within 0.08 (binomial spread on 1,700-4,000 images is under 0.012; the
    rest is benchmark-to-benchmark shift), and the images flagged low
    confidence are more often wrong than the others."""
    from recovery.api import LOW_CONFIDENCE

    for b, (_, res, _) in lodo.items():
        conf, ok = res["confidence"], res["err_usable"] < 3.0
        assert abs(conf.mean() - ok.mean()) < 0.08, (b, conf.mean(), ok.mean())
        low = conf < LOW_CONFIDENCE
        assert low.sum() < 0.3 * len(conf) and (low.sum() == 0 or ok[low].mean() < ok[~low].mean()), b


def test_same_estimate_whatever_describes_the_camera(real):
    """One camera, three descriptions of it: LibRaw's matrix; the
    sensitivities a matrix implies (``camera_from_matrix``: negative lobes
    clipped, so not colorimetric) described by their own Luther fit, as a
    camera with measured sensitivities is; and the matrix in error by 3 %
    per element (a DNG ColorMatrix against LibRaw's table). On 240 images
    (20 per camera) the estimates agree: median angle between them measured
    0.081 (Luther fit) and 0.155 degrees (perturbed matrix), 90th percentile
    0.31 and 0.58; the bounds are twice that. Mean error measured 2.37
    (matrix), 2.36 (Luther fit), 2.41 (perturbed): it may move by under 0.1
    degrees. (With the reference's absolute chromaticity among the inputs,
    ``absolute_inputs``, the perturbed matrix moved estimates by a median
    0.8 degrees: why the shipped model leaves it out.)"""
    from benchmarks.realdata import usable_mask
    from recovery.cameras import camera_from_matrix

    rs = real[0]
    rng = np.random.default_rng(5)
    idx = np.concatenate([rng.choice(np.flatnonzero(rs.camera == c), 20, replace=False) for c in rs.cameras])
    model = L.load_model()
    d_fit, d_pert, errs = [], [], {"matrix": [], "fit": [], "perturbed": []}
    for i in idx:
        m = rs.matrices[rs.camera[i]]
        sens = camera_from_matrix(m)
        fitted = L.camera_color_matrix(Camera(sens.wavelengths, sens.sensitivities, "measured-like", "measured"))
        pert = m @ (np.eye(3) + 0.03 * np.random.default_rng(int(i)).normal(size=(3, 3)))
        img, mask = rs.images[i], usable_mask(rs.images[i])
        try:
            a = L.estimate_learned(img, mask, m, model).rgb
        except L.InsufficientSurfaceVariation:
            continue
        b = L.estimate_learned(img, mask, fitted, model).rgb
        c = L.estimate_learned(img, mask, pert, model).rgb
        d_fit.append(angular_error(a, b))
        d_pert.append(angular_error(a, c))
        for k, e in (("matrix", a), ("fit", b), ("perturbed", c)):
            errs[k].append(angular_error(e, rs.truth[i]))
    d_fit, d_pert = np.array(d_fit), np.array(d_pert)
    assert np.median(d_fit) < MEDIAN_FIT and np.percentile(d_fit, 90) < P90_FIT, np.percentile(d_fit, [50, 90])
    assert np.median(d_pert) < MEDIAN_PERT and np.percentile(d_pert, 90) < P90_PERT, np.percentile(d_pert, [50, 90])
    for k in ("fit", "perturbed"):
        assert abs(np.mean(errs[k]) - np.mean(errs["matrix"])) < 0.1, (k, np.mean(errs[k]), np.mean(errs["matrix"]))


def test_auto_gives_almost_every_real_photograph_to_the_learnt_estimator(real):
    """The scene-level choice of ``auto`` must not take real photographs
    away from the learnt estimator: of the 7,524 development photographs
    3 reach the uniform-patch threshold (measured); at most 0.1 % may."""
    from benchmarks.realdata import usable_mask
    from recovery.api import UNIFORM_PATCH_SCENE

    rs = real[0]
    frac = np.array([L.uniform_patch_fraction(*L.estimation_image(im, usable_mask(im))) for im in rs.images])
    assert np.sum(frac >= UNIFORM_PATCH_SCENE) <= 0.001 * len(frac), np.sort(frac)[-10:]


def test_rebuilding_the_model_gives_the_shipped_one(real, same_fits):
    """The command is deterministic and the same on any machine: rebuilding
    from the same data (the shipped procedure, inner cross-validation
    included) gives the shipped settings and estimates. The fit is convex and
    iterated to a tolerance far above rounding, so the order of the sums does
    not move it. Measured with ``python -m benchmarks.rebuild_spread``
    (rebuilt under OpenBLAS's Haswell, SkylakeX and Prescott kernels,
    ``OPENBLAS_CORETYPE``, each in its own process, 300 sampled images):
    largest angle between any two rebuilds' (or the shipped model's)
    estimates 1.5e-12 degrees, of the 90 % radius 3.3e-12 degrees, of a
    coefficient 2.4e-14, the same ridge chosen (re-measured with the gamut
    limit and the ridge average: 5.2e-13 and 3.9e-13 degrees). The bounds, 1e-6 degrees,
    leave a million times that for other libm/SIMD builds of tanh and exp,
    and are still far below anything an estimate could show."""
    from benchmarks.realdata import usable_mask
    from benchmarks.train_illuminant import dataset_regions, shipped_model, single_threaded
    from recovery.confidence import load_flag_model

    rs, feats, tuv, Ks, gam = real
    with single_threaded():
        new = shipped_model(rs, feats, tuv, Ks, log=lambda s: None, gam=gam, regions=dataset_regions(rs))
    old = L.load_model()
    assert new.info["selection"] == old.info["selection"]
    # the confidence and flag (recovery/data/learned_confidence.json, `--flag-only`) rebuilt with it: the
    # same threshold and stumps (their inputs, thresholds and values to rounding), so the same confidences
    flag = load_flag_model()
    assert new.flag is not None and flag is not None
    assert new.flag.threshold == flag.threshold
    assert (new.flag.stumps is None) == (flag.stumps is None)
    if flag.stumps is not None:
        assert new.flag.stumps.shape == flag.stumps.shape
        np.testing.assert_array_equal(new.flag.stumps[:, 0], flag.stumps[:, 0])
        np.testing.assert_allclose(new.flag.stumps[:, 1:], flag.stumps[:, 1:], rtol=1e-9, atol=1e-12)
    assert (new.flag.trees is None) == (flag.trees is None)
    if flag.trees is not None:                   # the trees' inputs exactly, thresholds and values to rounding
        assert new.flag.trees.shape == flag.trees.shape
        np.testing.assert_array_equal(new.flag.trees[:, [0, 2, 4]], flag.trees[:, [0, 2, 4]])
        np.testing.assert_allclose(new.flag.trees, flag.trees, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(new.flag.coef, flag.coef, rtol=1e-9, atol=1e-12)
    for i in range(0, len(rs.truth), 251):
        m = rs.matrices[rs.camera[i]]
        try:
            a = L.estimate_learned(rs.images[i], usable_mask(rs.images[i]), m, new)
        except L.InsufficientSurfaceVariation:
            continue
        b = L.estimate_learned(rs.images[i], usable_mask(rs.images[i]), m, old)
        assert angular_error(a.rgb, b.rgb) < 1e-6
        assert abs(a.radius90_deg - b.radius90_deg) < 1e-6
        assert abs(a.confidence - b.confidence) < 1e-9
    np.testing.assert_allclose(new.outside_calibration, old.outside_calibration, rtol=1e-9)


def test_analyze_on_a_dng_of_a_real_thumbnail_gives_the_python_estimate(real, tmp_path):
    """The same evidence on every path: a DNG written from a real thumbnail
    (each pixel a 2 x 2 RGGB cell, so LibRaw's cells are the thumbnail's
    pixels, 16-bit) with its camera's colour matrix, through the real app,
    gives the Python API's estimate on the thumbnail."""
    from fastapi.testclient import TestClient

    from recovery.cameras import camera_from_matrix
    from service.app import app
    from testing.dngwriter import mosaic, write_dng

    rs = real[0]
    with TestClient(app) as client:
        for i in (3, 1900, 2900, 5000):
            thumb = rs.images[i].astype(float)
            cam_name = rs.camera[i]
            matrix = rs.matrices[cam_name]
            dn = np.round(thumb * 65535).astype(np.uint16)
            full = np.repeat(np.repeat(dn, 2, axis=0), 2, axis=1)
            buf = io.BytesIO()
            write_dng(buf, mosaic(full), black_level=0, white_level=65535, color_matrix1=matrix,
                      calibration_illuminant1=21, make="Thumb", model=cam_name)
            r = client.post("/v1/analyze", files={"file": ("t.dng", buf.getvalue())}, data={"camera": "matrix"})
            assert r.status_code == 200, r.text
            body = r.json()
            assert body["method"] == "learned"
            py = estimate_illuminant(dn.astype(float) / 65535, camera_from_matrix(matrix), white_level=1.0)
            assert angular_error(body["illuminant"]["camera_rgb"], py.rgb) < 0.05, (i, body["illuminant"], py.rgb)
            assert angular_error(py.rgb, rs.truth[i]) < 15
