"""The second, differently built estimators tried as confidence evidence
(``benchmarks.flag_variants --histogram``; docs/confidence.md, "A second,
differently built estimator"): the log-chroma histogram against a hand
computation, and the histogram ridge regression against a law it must
recover."""

import math

import numpy as np

from benchmarks import flag_variants as V


def test_the_histogram_is_the_hand_computed_one():
    """Four cells in a row, the third unusable. 4 x 4 bins over [-1, 1) on
    both axes (width 0.5); ``u = log g/r``, ``v = log g/b``.

    * a = (1, 1, 1): u = 0, v = 0, bin (2, 2), weight r + g + b = 3;
    * b = 2 (e^0.75, 1, e^-0.3): u = -0.75 -> bin 0, v = 0.3 -> bin 2, weight 2 (e^0.75 + 1 + e^-0.3);
    * c: unusable (counts nowhere, and is nobody's neighbour);
    * d = (e^-2, 1, 1): u = 2, beyond the range -> the last bin 3, v = 0 -> bin 2, weight e^-2 + 2.

    Edges (mean absolute difference with the usable ones of the 8 neighbours):
    a and b each have only the other, so both are |a - b| = (2 e^0.75 - 1, 1, 2 e^-0.3 - 1);
    d has no usable neighbour. |a - b| has u = -log(2 e^0.75 - 1) = -1.17, below the range -> bin 0,
    and v = -log(2 e^-0.3 - 1) = 0.73 -> bin 3: all the edge histogram's weight in bin (0, 3)."""
    e = math.exp
    cells = np.array([[[1.0, 1.0, 1.0], [2 * e(0.75), 2.0, 2 * e(-0.3)], [5.0, 0.1, 7.0], [e(-2.0), 1.0, 1.0]]])
    ok = np.array([[True, True, False, True]])
    h = V.log_chroma_histogram(cells, ok, bins=4, limits=((-1.0, 1.0), (-1.0, 1.0)))
    wa, wb, wd = 3.0, 2 * (e(0.75) + 1 + e(-0.3)), e(-2.0) + 2.0
    s = wa + wb + wd
    want_cells = np.zeros((4, 4))
    want_cells[2, 2], want_cells[0, 2], want_cells[3, 2] = wa / s, wb / s, wd / s
    assert -math.log(2 * e(0.75) - 1) < -1.0 and 0.5 <= -math.log(2 * e(-0.3) - 1) < 1.0   # the bins said above
    want_edges = np.zeros((4, 4))
    want_edges[0, 3] = 1.0
    np.testing.assert_allclose(h, np.sqrt(np.concatenate([want_cells.ravel(), want_edges.ravel()])), rtol=1e-12,
                               atol=0)
    # unit norm per histogram (square roots of a distribution)
    assert abs(np.linalg.norm(h[:16]) - 1.0) < 1e-12 and abs(np.linalg.norm(h[16:]) - 1.0) < 1e-12


def test_no_usable_cell_gives_zero_histograms():
    h = V.log_chroma_histogram(np.ones((3, 3, 3)), np.zeros((3, 3), bool), bins=4)
    assert h.shape == (32,) and not h.any()


def test_the_ridge_recovers_an_exact_linear_law_and_prefers_the_smaller_ridge_there():
    """Noiseless ``y = X B + c``: with a negligible ridge the fit is the
    least-squares solution, exactly ``B`` and ``c`` up to the conditioning
    (X is 200 x 12 standard normal, condition ~2, so 1e-8 is generous for a
    ridge of 1e-12); among the grid the smallest ridge predicts the held-out
    cameras best, so it is chosen."""
    rng = np.random.default_rng(1)
    X = rng.normal(size=(200, 12))
    B = rng.normal(size=(12, 2))
    c = np.array([0.3, -0.7])
    y = X @ B + c
    w = rng.uniform(0.5, 2.0, 200)
    cams = rng.integers(0, 3, 200)
    b, c_fit, r = V.fit_histogram_ridge(X, y, w, cams, ridges=(1e-12, 1.0, 10.0))
    assert r == 1e-12
    np.testing.assert_allclose(b, B, atol=1e-8)
    np.testing.assert_allclose(c_fit, c, atol=1e-8)
    # a heavy ridge shrinks the slopes towards zero, not the intercept: the prediction at the weighted mean input
    b2, c2, _ = V.fit_histogram_ridge(X, y, w, cams, ridges=(1e6,))
    ww = w / w.sum()
    assert np.abs(b2).max() < 1e-3
    np.testing.assert_allclose((ww @ X) @ b2 + c2, ww @ y, atol=1e-12)


def _result(conf_lobo, conf_loco, fail, grp):
    return {"fold": {"conf": {"lobo": conf_lobo, "loco": conf_loco}, "fail": fail, "grp": grp}}


def test_the_paired_bootstrap_gain_is_the_difference_of_the_printed_areas():
    """Against itself the gain is zero in every resample; a confidence that
    ranks every failure below every success gains 1 - the reference's area
    (per inner benchmark, then averaged), exactly at the point estimate."""
    from recovery import confidence as C

    rng = np.random.default_rng(2)
    n = 300
    grp = np.repeat(np.array(["A", "B"]), n // 2)
    fail = rng.random(n) < 0.2
    ref_c = rng.random(n) - 0.3 * fail
    ref = _result(ref_c, ref_c, fail, grp)
    same = V.paired_bootstrap(ref, ref, resamples=20)
    assert all(v["gain"] == 0.0 and v["se"] == 0.0 for v in same.values())
    perfect = np.where(fail, 0.1, 0.9)
    got = V.paired_bootstrap(_result(perfect, perfect, fail, grp), ref, resamples=20)
    want = np.mean([1.0 - C.auroc(-ref_c[grp == g], fail[grp == g]) for g in ("A", "B")])
    assert abs(got["lobo"]["gain"] - want) < 1e-12 and got["lobo"]["positive"] == 1.0
