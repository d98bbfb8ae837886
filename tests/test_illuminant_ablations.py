"""The extra estimates of ``benchmarks.illuminant_ablations`` (issue 16's
record of what was tried and not kept) do what their references say."""

import numpy as np

from benchmarks.illuminant_ablations import dominant_estimate, pca_estimate
from recovery import learned as L


def test_pca_estimate_of_gray_surfaces_is_the_light():
    # achromatic surfaces of many reflectances under one light: every
    # normalised colour is the light's direction, so is the first component
    rng = np.random.default_rng(0)
    light = np.array([0.5, 0.3, 0.2])
    px = rng.uniform(0.01, 1.0, (500, 1)) * light
    est = pca_estimate(px, 0.035)
    a, b = est / np.linalg.norm(est), light / np.linalg.norm(light)
    angle = np.degrees(2 * np.arctan2(np.linalg.norm(a - b), np.linalg.norm(a + b)))
    assert angle < 1e-6     # rounding only: float64 eigenvectors of a rank-one matrix


def test_dominant_estimate_finds_the_most_common_chromaticity_within_a_bin():
    rng = np.random.default_rng(1)
    main = np.array([0.4, 0.35, 0.25])
    px = np.concatenate([main * rng.uniform(0.2, 1.0, (300, 1)), rng.uniform(0.05, 1.0, (100, 3))])
    uv, uv_main = L.rgb_to_uv(dominant_estimate(px)), L.rgb_to_uv(main)
    full = L.rgb_to_uv(px)
    bin_width = (full.max(axis=0) - full.min(axis=0)) / 32
    assert np.all(np.abs(uv - uv_main) <= bin_width)


def test_density_ratio_recovers_a_known_gaussian_shift():
    # training N(0, 1), test N(0.5, 1): p_test / p_train = exp(0.5 x - 0.125),
    # which a logistic regression on x models exactly; with 4000 points the
    # slope's standard error is about 1 / sqrt(4000 * 0.25) = 0.03, so 0.15 is
    # five of them
    from benchmarks.illuminant_ablations import density_ratio

    rng = np.random.default_rng(2)
    xtr, xte = rng.normal(0.0, 1.0, (2000, 1)), rng.normal(0.5, 1.0, (2000, 1))
    r = density_ratio(xtr, xte)
    assert abs(r.mean() - 1.0) < 1e-12
    slope = np.polyfit(xtr[:, 0], np.log(r), 1)[0]
    assert abs(slope - 0.5) < 0.15
    assert np.all(np.isfinite(r)) and np.all(r > 0)


def test_oracle_camera_offset_removes_each_cameras_median_residual():
    from benchmarks.illuminant_ablations import oracle_camera_offset

    rng = np.random.default_rng(3)
    tuv = rng.normal(0.0, 0.1, (60, 2))
    cams = np.repeat(np.array(["a", "b", "c"]), 20)
    uv = tuv + rng.normal(0.0, 0.02, (60, 2)) + np.repeat([[0.05, 0.0], [0.0, -0.03], [0.01, 0.01]], 20, axis=0)
    good = np.ones(60, bool)
    good[0] = False                       # not usable: left as it is
    out = oracle_camera_offset(uv, tuv, cams, good)
    assert np.array_equal(out[0], uv[0])
    for c in "abc":
        m = (cams == c) & good
        assert np.allclose(np.median(tuv[m] - out[m], axis=0), 0.0, atol=1e-15)


def test_fit_model_with_uniform_sample_weights_is_the_unweighted_fit():
    # the weights are renormalised, so a constant factor changes nothing but rounding (measured: the
    # same predictions bit for bit under OpenBLAS's Haswell, SkylakeX and Prescott kernels)
    from benchmarks import train_illuminant as T

    rng = np.random.default_rng(4)
    n = 300
    true = rng.normal([0.0, 0.3], 0.1, (n, 2))
    feats = true[:, None, :] + rng.normal(0.0, 0.05, (n, len(L.FEATURE_NAMES), 2))
    ds = np.repeat(np.array(["x", "y"]), n // 2)
    cams = np.repeat(np.array(["p", "q", "r"]), n // 3)
    loc = T.locus()
    a = T.fit_model(feats, true, ds, cams, 1.0, loc)
    b = T.fit_model(feats, true, ds, cams, 1.0, loc, sample_weight=np.full(n, 3.0))
    assert np.allclose(T.predict(a, feats), T.predict(b, feats), atol=1e-9, rtol=0)
