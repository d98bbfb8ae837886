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
