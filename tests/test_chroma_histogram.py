"""The histogram stage of the learnt estimator (recovery/chroma_histogram.py)
and its fit (benchmarks/train_illuminant.fit_histogram)."""

import numpy as np
import pytest

from recovery import chroma_histogram as CH

SMALL = CH.Grid(1.0 / 8.0, -1.0, -1.0, 16, 24)


def _scene(rng, n=64):
    """An n x n canonical image of patches of 64 random surfaces (grey on
    average) under a grey light, shaded."""
    refl = rng.uniform(0.2, 0.8, (64, 3))
    lab = rng.integers(0, 64, (n // 4, n // 4))
    img = refl[np.kron(lab, np.ones((4, 4), int))]
    return img * rng.uniform(0.5, 1.0, (n, n, 1))


def test_scores_are_the_circular_convolution_of_each_histogram_with_its_filter():
    """Barron & Tsai's eq. 6 by FFT equals the sum written out."""
    rng = np.random.default_rng(0)
    x = rng.random((2, SMALL.nu, SMALL.nv))
    f = rng.normal(size=(2, SMALL.nu, SMALL.nv))
    b = rng.normal(size=(SMALL.nu, SMALL.nv))
    h = CH.scores(x, f, b)
    direct = b.copy()
    for i in range(SMALL.nu):
        for j in range(SMALL.nv):
            for c in range(2):
                direct[i, j] += sum(x[c, p, q] * f[c, (i - p) % SMALL.nu, (j - q) % SMALL.nv]
                                    for p in range(SMALL.nu) for q in range(SMALL.nv))
    np.testing.assert_allclose(h, direct, atol=1e-10)


def test_a_change_of_light_shifts_the_histograms_and_the_scores():
    """The diagonal model: a light k bins bluer moves every pixel's
    log-chroma by k bins, so the histograms, and the scores of any filter,
    move by k bins (on the torus)."""
    rng = np.random.default_rng(1)
    img = _scene(rng)
    ok = np.ones(img.shape[:2], bool)
    g = CH.DEFAULT_GRID
    ku, kv = 3, -5
    # u = log g/r, v = log g/b: scaling r by e^{-ku step} raises u by ku steps
    lit = img * np.exp(np.array([-ku * g.step, 0.0, -kv * g.step]))
    h0, h1 = CH.histograms(img, ok, g), CH.histograms(lit, ok, g)
    np.testing.assert_allclose(np.roll(h0, (ku, kv), axis=(1, 2)), h1, atol=1e-12)
    f = rng.normal(size=(2, g.nu, g.nv))
    z = np.zeros((g.nu, g.nv))
    np.testing.assert_allclose(np.roll(CH.scores(h0, f, z), (ku, kv), axis=(0, 1)), CH.scores(h1, f, z), atol=1e-9)
    for h in (h0, h1):
        assert h[0].sum() == pytest.approx(1.0) and h[1].sum() == pytest.approx(1.0)


def test_fusion_with_a_flat_likelihood_returns_the_first_stage_and_follows_a_sharp_one():
    """With no histogram evidence (flat scores) the fused estimate is the
    first stage's, wherever it lies on the torus (to the window's
    truncation of a Gaussian of sd 1.6 bins: < 1e-4); with a likelihood far
    sharper than the first stage's Gaussian it is the likelihood's peak."""
    g = CH.DEFAULT_GRID
    flat = np.zeros((g.nu, g.nv))
    for uv in ([0.1, 0.5], [-1.19, 3.18], [0.79, -0.79], [0.3, 3.5]):     # the last beyond the period
        got, cov = CH.fuse(flat, np.array(uv), 0.05 ** 2, g)
        np.testing.assert_allclose(got, uv, atol=1e-4)
        assert np.all(np.linalg.eigvalsh(cov) > 0)
    cu, cv = CH.bin_centres(g)
    peak = np.array([cu[20] + 0.01, cv[70] - 0.005])
    sharp = -((cu[:, None] - peak[0]) ** 2 + (cv[None, :] - peak[1]) ** 2) / (2 * 0.02 ** 2)
    got, _ = CH.fuse(sharp, peak + [0.05, -0.04], 0.2 ** 2, g)
    np.testing.assert_allclose(got, peak, atol=0.01)


def test_edge_image_is_the_mean_absolute_deviation_from_usable_neighbours():
    img = np.ones((4, 4, 3))
    img[1, 1] = [2.0, 3.0, 4.0]
    ok = np.ones((4, 4), bool)
    ok[3, 3] = False
    e, eok = CH.edge_image(img, ok)
    np.testing.assert_allclose(e[1, 1], [1.0, 2.0, 3.0])          # all 8 neighbours are 1
    np.testing.assert_allclose(e[0, 0], np.array([1.0, 2.0, 3.0]) / 3)   # 3 neighbours, one of them differs
    np.testing.assert_allclose(e[2, 2], np.array([1.0, 2.0, 3.0]) / 7)   # 7 usable neighbours
    assert not eok[3, 3] and eok[2, 2]


def test_fit_recovers_a_light_from_evidence_it_was_trained_on_and_its_gradient_is_exact():
    """On synthetic scenes (random surfaces, grey on average, under random
    lights) the fitted filters find the light on new scenes as well as gray
    world does (the right estimator for such scenes; measured 0.083-0.089
    against gray world's 0.086 log-chroma, median, for penalties from 1e-5
    to 1e-3), far inside the lights' own spread (0.5); and the
    objective's gradient agrees with central differences (a wrong adjoint
    would still descend, slowly, to a wrong answer): step 1e-4, whose
    truncation error is ~1e-8 of the curvature, rounding ~1e-12; 1e-5
    relative is asserted."""
    import scipy.fft as sfft

    from benchmarks.train_illuminant import _penalty_spectrum, _splat, fit_histogram, histogram_objective

    rng = np.random.default_rng(2)
    g = SMALL
    n = 300
    uv = np.c_[rng.uniform(-0.6, 0.4, n), rng.uniform(-0.5, 1.5, n)]
    hist = np.zeros((n, 2, g.nu, g.nv))
    gw = np.zeros((n, 2))
    for i in range(n):
        img = _scene(rng, 32) * np.exp(-np.array([uv[i, 0], 0.0, uv[i, 1]]))     # a light of log-chroma uv
        hist[i] = CH.histograms(img, np.ones((32, 32), bool), g)
        m = img.reshape(-1, 3).mean(axis=0)
        gw[i] = [np.log(m[1] / m[0]), np.log(m[1] / m[2])]
    tr, te = np.arange(250), np.arange(250, n)
    st = {"grid": tuple(g), "tv": (1e-4, 1e-4), "l2": (1e-6, 1e-6), "bias": False, "maxiter": 300, "gtol": 1e-8}
    f, b, info = fit_histogram(hist[tr], uv[tr], np.ones(tr.size), st)
    got = np.array([CH.posterior_mean(CH.scores(hist[i], f, b), g)[0] for i in te])
    err = np.median(np.linalg.norm(got - uv[te], axis=1))
    bias = (gw[tr] - uv[tr]).mean(axis=0)
    err_gw = np.median(np.linalg.norm(gw[te] - bias - uv[te], axis=1))
    assert err < 1.25 * err_gw and err < 0.2, (err, err_gw, info)

    P = np.stack([1 / np.sqrt(_penalty_spectrum(g, 1e-4, 1e-6))] * 3)
    fg, _ = histogram_objective(sfft.rfft2(hist[:40]), _splat(uv[:40], g), np.full(40, 1 / 40), P, True)
    z = rng.normal(0, 0.01, 3 * g.nu * g.nv)
    _, grad = fg(z)
    for k in rng.choice(z.size, 8, replace=False):
        e = np.zeros_like(z)
        e[k] = 1e-4
        fd = (fg(z + e)[0] - fg(z - e)[0]) / 2e-4
        assert fd == pytest.approx(grad[k], rel=1e-5, abs=1e-9), (k, fd, grad[k])
