"""Sampling strategies (models.sampling), Kment's filters (models.filters) and
his findings reproduced on colour-science's reflectances (Kment 2011 [docs/references.md#seed-001],
Tables 6.1, 6.2, 7.1, A.1, A.2; evaluation as in benchmarks.sampling).

Where our data disagree with the thesis the test asserts what the data show
and says why.
"""

from __future__ import annotations

import csv

import numpy as np
import pytest

from benchmarks.sampling import (FLUORESCENT, KMENT_WAVELENGTHS, NON_FLUORESCENT, kment_data, main, report_rows,
                                 rule_errors)
from models.filters import filter_names, filter_window, lowpass_matrix
from models.sampling import (composite_rule, detect_spikes, fourier_rule, fourier_terms, pca_rule,
                             riemann_rule, sampling_rule, strategy_names, uniform_rule)

WL = KMENT_WAVELENGTHS  # 380-780 nm at 5 nm


@pytest.fixture(scope="module")
def data():
    return kment_data("all")


def mean_error(data, make_rule, lights) -> float:
    """Mean CIEDE2000 over all reflectances and the given lights (Kment's 'mean average')."""
    return float(np.mean(np.concatenate(
        [rule_errors(make_rule(name), data.lights[name], data.reflectances, data.cmfs) for name in lights])))


def ps(n, **kw):
    """Kment's point sampling: n nodes, both ends of 380-780 nm included (sec. 6.1)."""
    return lambda light: uniform_rule(n, WL, placement="endpoints", **kw)


# --- filters: Kment eq. 4.13-4.19 -------------------------------------------------

def test_windows_follow_kments_equations():
    # half-width = extent / 2 = 2.5 samples; u = x / 2.5
    x = np.array([0.0, 1.25, 2.5, 3.0])
    np.testing.assert_allclose(filter_window("box", x, 5), [1, 1, 1, 0])               # eq. 4.13
    np.testing.assert_allclose(filter_window("tent", x, 5), [1, 0.5, 0, 0])            # eq. 4.14
    np.testing.assert_allclose(filter_window("welch", x, 5), [1, 0.75, 0, 0])          # eq. 4.15
    np.testing.assert_allclose(filter_window("hann", x, 5), [1, 0.5, 0, 0], atol=1e-15)  # eq. 4.19, a=0.5
    # Hamming (a = 0.54) does not reach 0 at the border: the discontinuity Kment blames
    assert filter_window("hamming", [2.4999], 5)[0] == pytest.approx(0.08, abs=1e-4)
    # Gauss (eq. 4.16): the border value is subtracted, so w -> 0 at the border
    assert filter_window("gauss", [2.4999], 5, alpha=0.5)[0] == pytest.approx(0.0, abs=1e-4)
    assert filter_window("gauss", [0.0], 5, alpha=0.5)[0] == pytest.approx(1 - np.exp(-0.5 * 2.5**2))


def test_mitchell_netravali_special_cases():
    # extent 8 -> the cubic's unit is 2 samples; t = x / 2
    t = np.array([0.0, 1.0, 2.0])
    # b=1, c=0: cubic B-spline, k(0)=4/6, k(1)=1/6, k(2)=0 (Mitchell & Netravali 1988)
    np.testing.assert_allclose(filter_window("mitchell", 2 * t, 8, b=1, c=0), [4 / 6, 1 / 6, 0], atol=1e-15)
    # b=0, c=0.5: Catmull-Rom interpolates: k(0)=1, k(1)=0
    np.testing.assert_allclose(filter_window("mitchell", 2 * t, 8, b=0, c=0.5), [1, 0, 0], atol=1e-15)


def test_lanczos_has_tau_cycles_per_half_window():
    # zeros of sinc(tau u) at u = k / tau: tau = 2, half-width 5 -> zeros at x = 2.5
    assert filter_window("lanczos", [2.5], 10, tau=2.0)[0] == pytest.approx(0.0, abs=1e-15)
    assert filter_window("lanczos", [0.0], 10, tau=2.0)[0] == pytest.approx(1.0)


@pytest.mark.parametrize("name", filter_names())
def test_lowpass_keeps_constants_and_removes_the_new_nyquist(name):
    # DC gain 1 away from the ends (the rows are normalised on the lattice) ...
    nodes = np.linspace(450.0, 700.0, 11)  # 25 nm apart, far from the zero-padded ends
    A = lowpass_matrix(nodes, WL, name)
    np.testing.assert_allclose(A @ np.ones(WL.size), 1.0, atol=1e-12)
    # ... and a cosine at the Nyquist rate of the new 25 nm spacing (period 50 nm),
    # which plain point sampling passes with gain 1, is attenuated. The weakest is the
    # box one spacing wide: its response there is sinc(1/2) = 2/pi = 0.64 (the 5-sample
    # discrete box: (1 + 2 cos 36 deg + 2 cos 72 deg) / 5 = 0.647), Kment's "worst
    # possible filter"; the tapered windows at their default widths reach below 0.5.
    s = np.cos(2 * np.pi * (WL - 450.0) / 50.0)
    gain = np.max(np.abs(A @ s))
    if name == "box":
        assert gain == pytest.approx((1 + 2 * np.cos(np.pi / 5) + 2 * np.cos(2 * np.pi / 5)) / 5, abs=1e-12)
    else:
        assert gain < 0.5
    assert np.max(np.abs(np.interp(nodes, WL, s))) == pytest.approx(1.0)


def test_zero_padding_at_the_ends_as_kment():
    # Kment sec. 6.1: values outside 380-780 nm count as 0, so the end rows lose weight
    A = lowpass_matrix([380.0, 580.0], WL, "box", extent=5)
    assert A[0].sum() == pytest.approx(3 / 5)
    assert A[1].sum() == pytest.approx(1.0)
    B = lowpass_matrix([380.0], WL, "box", extent=5, edge="renormalise")
    assert B.sum() == pytest.approx(1.0)


@pytest.mark.parametrize("kwargs, words", [
    ({"filter": "sinc"}, "unknown filter 'sinc'"),
    ({"filter": "mitchell", "tau": 2.0}, "takes no parameter ['tau']"),
    ({"filter": "lanczos", "tau": -1.0}, "tau must be > 0"),
    ({"filter": "box", "extent": 0}, "extent must be > 0"),
    ({"extent": 5}, "need filter=<name>"),
])
def test_bad_filter_options_are_named(kwargs, words):
    with pytest.raises(ValueError, match=words.replace("[", r"\[").replace("]", r"\]")):
        sampling_rule("uniform", 16, WL, **kwargs)


# --- the rules ---------------------------------------------------------------------

def test_all_local_strategies_build_through_the_factory():
    for name in ("uniform", "riemann", "fourier", "pca", "composite"):
        rule = sampling_rule(name, 9, WL)
        assert rule.n == 9 and rule.strategy == name and rule.defined
    with pytest.raises(ValueError, match="unknown sampling strategy"):
        sampling_rule("spline", 4, WL)
    assert {"uniform", "riemann", "fourier", "pca", "composite"} <= set(strategy_names())


@pytest.mark.parametrize("name, n", [("uniform", 0), ("riemann", None), ("fourier", 81), ("pca", 2.5),
                                     ("composite", -1)])
def test_bad_sizes_are_rejected_with_the_strategy_named(name, n):
    with pytest.raises(ValueError, match=name):
        sampling_rule(name, n, WL)


def test_riemann_sums_keep_the_area_and_multiply_elementwise():
    rule = riemann_rule(7, WL)  # 7 bins do not align with the 5 nm cells: fractional overlaps
    rng = np.random.default_rng(1)
    s = rng.random((5, WL.size))
    # the bins tile the cells, so the rebuilt spectrum has exactly the dense integral (eq. 5.3)
    np.testing.assert_allclose(rule.reconstruct(rule.coefficients(s)).sum(axis=1), s.sum(axis=1), rtol=1e-12)
    np.testing.assert_allclose(rule.coefficients(np.full(WL.size, 0.3)), 0.3, rtol=1e-12)
    # the weights (bin widths) add up to the range the dense samples cover, 81 x 5 nm
    assert rule.weights.sum() == pytest.approx(WL.size * 5.0)
    a, b = rule.coefficients(s[0]), rule.coefficients(s[1])
    assert rule.multiplicative
    np.testing.assert_allclose(rule.product(a, b), a * b)


def test_fourier_rule_is_exact_on_its_own_trigonometric_polynomials():
    rule = fourier_rule(5, WL)  # a0, a1, b1, a2, b2 (Kment's "CS5" without the spikes)
    coef = np.array([0.5, 0.1, -0.2, 0.05, 0.03])
    s = fourier_terms(5, WL) @ coef
    np.testing.assert_allclose(rule.coefficients(s), coef, atol=1e-12)
    assert not rule.multiplicative
    assert rule.diagnostics["basis_condition"] < 10  # nearly orthogonal terms on a regular grid


def test_pca_rule_reconstructs_its_training_set_as_its_energy_says():
    R = kment_data("colorchecker", ("D65",)).reflectances
    rule = pca_rule(8, WL, training=R)
    rel = np.linalg.norm(R - rule.reconstruct(rule.coefficients(R))) / np.linalg.norm(R)
    # uncentred SVD: the residual energy fraction is 1 - captured energy, exactly
    assert rel**2 == pytest.approx(1 - rule.diagnostics["energy_captured"], rel=1e-9)


def test_spike_detection_finds_the_mercury_lines():
    from models import illuminant

    groups = detect_spikes(illuminant("FL2", WL), WL, threshold=0.2)
    centres = [WL[g][np.argmax(illuminant("FL2", WL)[g])] for g in groups]
    # Hg lines at 404.7, 435.8 and 546.1 nm, on a 5 nm grid: 405, 435, 545
    assert centres == [405.0, 435.0, 545.0]
    for smooth_light in NON_FLUORESCENT:
        assert detect_spikes(illuminant(smooth_light, WL), WL) == []


def test_composite_keeps_line_energy_and_reverts_without_lines():
    from models import illuminant

    e = illuminant("FL7", WL)
    rule = composite_rule(20, WL, light="FL7")
    d = rule.diagnostics
    assert d["n_spikes"] + d["n_smooth"] == rule.n == 20 and d["n_spikes"] > 0
    # lines are stored exactly and the Riemann smooth part keeps its area: the
    # light's integral survives the representation to rounding
    assert rule.reconstruct(rule.coefficients(e)).sum() == pytest.approx(e.sum(), rel=1e-12)
    assert rule.multiplicative  # enhanced Riemann: element-wise products (Kment sec. 5.5)
    # a smooth light has no lines: the rule is plain Riemann sums
    plain = composite_rule(20, WL, light="D65")
    np.testing.assert_allclose(plain.analysis, riemann_rule(20, WL).analysis)
    with pytest.raises(ValueError, match=r"composite: n=5 cannot hold the light's 6 line samples"):
        composite_rule(5, WL, light="FL7")  # FL7 has 6 line samples: 5 cannot hold them


# --- Kment's findings: non-fluorescent lights (Table 6.1) ------------------------------

def test_non_fluorescent_point_sampling_32_beats_riemann_32(data):
    # Table 6.1: PS32 0.149 < RS32 0.194. Ours (267 reflectances, A/C/D65): 0.09 < 0.18.
    ps32 = mean_error(data, ps(32), NON_FLUORESCENT)
    rs32 = mean_error(data, lambda _: riemann_rule(32, WL), NON_FLUORESCENT)
    assert ps32 < rs32 < 1.0  # and both below a just-noticeable difference, as in the thesis


def test_non_fluorescent_errors_fall_with_more_samples(data):
    for make in (lambda n: ps(n), lambda n: (lambda _: riemann_rule(n, WL))):
        errs = [mean_error(data, make(n), NON_FLUORESCENT) for n in (4, 8, 16, 32)]
        assert all(a > b for a, b in zip(errs, errs[1:])), errs


def test_non_fluorescent_point_sampling_16_near_kment(data):
    # Table 6.1: PS16 0.605, PS8 2.295. Different reflectances (NCS vs colour-science's
    # 267, which include saturated CQS samples) and his lights A/B/C vs our A/C/D65: we ask
    # only for the same regime, within a factor 2.5 (ours: 0.30 and 3.4; our 8-sample
    # figure is higher because the 57 nm spacing misses the narrow CQS reflectance features).
    assert 0.605 / 2.5 < mean_error(data, ps(16), NON_FLUORESCENT) < 0.605 * 2.5
    assert 2.295 / 2.5 < mean_error(data, ps(8), NON_FLUORESCENT) < 2.295 * 2.5


# --- Kment's findings: fluorescent lights (Table 6.2) ----------------------------------

def test_fluorescent_point_sampling_16_fails_as_in_the_thesis(data):
    # Table 6.2: PS16 11.198. The error is the aliasing of the lights' lines (the same
    # CIE FL2/FL7/FL11 data in both studies), so the reflectance set matters little:
    # ours is 12.3, within 15 %.
    assert mean_error(data, ps(16), FLUORESCENT) == pytest.approx(11.198, rel=0.15)


def test_fluorescent_composite_wins_at_equal_storage(data):
    # Table 6.2: composite methods (Sun's CS, Kment's RE) beat RS and PS. Storage here is
    # every stored number, lines included (Kment's CS counts only Fourier terms).
    cs = lambda n: (lambda light: composite_rule(n, WL, smooth="fourier", light=light))  # noqa: E731
    rs = lambda n: (lambda _: riemann_rule(n, WL))  # noqa: E731
    fo = lambda n: (lambda _: fourier_rule(n, WL))  # noqa: E731
    for n in (24, 32):
        for light in ("FL2", "FL7"):
            c = mean_error(data, cs(n), [light])
            assert c < mean_error(data, rs(n), [light]) and c < mean_error(data, ps(n), [light])
            # and the lines are worth their storage: plain Fourier with the same n loses
            assert c < mean_error(data, fo(n), [light])
    c32 = mean_error(data, cs(32), FLUORESCENT)
    assert c32 < mean_error(data, rs(32), FLUORESCENT) < mean_error(data, ps(32), FLUORESCENT)
    # Kment's enhanced Riemann (RE) wins over RS once its smooth part has enough bins:
    re = lambda n: (lambda light: composite_rule(n, WL, smooth="riemann", light=light))  # noqa: E731
    for light in ("FL2", "FL7"):
        assert mean_error(data, re(40), [light]) < mean_error(data, rs(40), [light])


def test_fluorescent_fl11_bands_cost_the_enhanced_riemann_its_bins(data):
    # Where the data disagree with the thesis: FL11's three tri-phosphor bands are 15-30 nm
    # wide at 5 nm, so the 20 % slope rule keeps 21 line samples; at equal storage 32 the
    # enhanced Riemann has 11 bins left for the smooth part and loses to 32 plain bins
    # (Kment counts RE32 as 32 bins plus the lines, i.e. more storage).
    re32 = composite_rule(32, WL, light="FL11")
    assert re32.diagnostics["n_spikes"] >= 15
    re_err = mean_error(data, lambda _: re32, ["FL11"])
    assert re_err > mean_error(data, lambda _: riemann_rule(32, WL), ["FL11"])
    # Sun's composite keeps 18 band samples (30 % slope) and 14 Fourier terms: plain
    # Fourier with 32 terms does better on FL11. Its least-squares projection of the light
    # keeps the low frequencies, which is nearly all a smooth reflectance times a CMF
    # responds to; the band samples instead read the reflectance exactly at a few
    # wavelengths but leave too few terms for the rest of the spectrum.
    cs32 = composite_rule(32, WL, smooth="fourier", light="FL11")
    assert cs32.diagnostics["n_spikes"] == 18
    assert mean_error(data, lambda _: cs32, ["FL11"]) > mean_error(data, lambda _: fourier_rule(32, WL), ["FL11"])


# --- Kment's findings: low-pass filters before point sampling (Tables 7.1, A.2) --------

def test_lowpass_filtering_cuts_fluorescent_ps16_error_by_more_than_half(data):
    none = mean_error(data, ps(16), FLUORESCENT)
    # Table 7.1 with Kment's best parameters of Table A.2 (extent 19, b=-0.4, c=1.0 for
    # Mitchell; 21, tau 2.5 Lanczos; 7 tent): -85 %, -84 %, -77 % in the thesis.
    mitchell = mean_error(data, ps(16, filter="mitchell", extent=19, b=-0.4, c=1.0), FLUORESCENT)
    lanczos = mean_error(data, ps(16, filter="lanczos", extent=21, tau=2.5), FLUORESCENT)
    tent = mean_error(data, ps(16, filter="tent", extent=7), FLUORESCENT)
    assert 1 - mitchell / none > 0.5  # ours: -92 %
    assert 1 - lanczos / none > 0.5  # ours: -93 %
    assert 1 - tent / none > 0.5  # ours: -80 %
    # the tent filter has one parameter and the same extent in both studies: 2.598 in
    # Table A.2, ours 2.48; the lights' lines dominate, so within 15 % as above
    assert tent == pytest.approx(2.598, rel=0.15)


def test_every_filter_helps_point_sampling_under_fluorescent_light(data):
    # Table A.2: "any low pass filter improves the result" (16 samples), here with each
    # filter at its natural width for the 26.7 nm spacing (models.filters.default_extent)
    none = mean_error(data, ps(16), FLUORESCENT)
    for name in filter_names():
        assert mean_error(data, ps(16, filter=name), FLUORESCENT) < 0.25 * none, name


# --- the trade-off report --------------------------------------------------------------

def test_report_rows_cover_every_strategy(tmp_path):
    small = kment_data("colorchecker")
    rows = report_rows(small, sizes=(6, 12), timing_spectra=2000)
    by_strategy = {r["strategy"] for r in rows}
    assert set(strategy_names()) <= by_strategy
    for r in rows:
        if r["status"] == "ok":
            assert np.isfinite(r["mean"]) and np.isfinite(r["p95"]) and r["time_s_per_1e6"] > 0
            assert r["mean"] <= r["max"]
        else:
            assert r["status"]  # a reason, e.g. "not available (models.quadrature missing)"
    # the full calculation row costs more than 6 stored coefficients (81 vs 6 multiply-adds)
    assert any(r["variant"] == "full" for r in rows)


def test_report_command_writes_csv_and_png(tmp_path, capsys):
    assert main(["--out", str(tmp_path), "--sizes", "8", "--timing-spectra", "2000"]) == 0
    out = capsys.readouterr().out
    assert "mean dE00" in out and "fluorescent" in out
    with open(tmp_path / "sampling_tradeoff.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["variant"] for r in rows} >= {"uniform", "riemann", "composite-fourier"}
    assert (tmp_path / "sampling_tradeoff.png").stat().st_size > 10_000


def test_mitchell_and_lanczos_are_the_best_filters_after_a_parameter_search(data):
    # Table A.2 (16 samples, fluorescent lights): with each filter's best parameters the
    # Mitchell (1.644) and Lanczos (1.804) filters beat every one-parameter window
    # (box 2.424 ... Hamming 2.636). A coarse version of his search (extents 5-21, a few
    # parameter values) finds the same ranking on our data (ours: Lanczos 0.40, Mitchell
    # 0.44, best one-parameter window Hann 1.03); and the best box extent is 5 samples in
    # both studies (one 25 nm window for a 26.7 nm spacing: the Riemann interval).
    extents = (5, 9, 13, 17, 21)

    def best(name, grid=({},)):
        return min((mean_error(data, ps(16, filter=name, extent=e, **p), FLUORESCENT), e)
                   for e in extents for p in grid)

    simple = {name: best(name) for name in ("box", "tent", "welch", "hann", "hamming")}
    lanczos = best("lanczos", [{"tau": t} for t in (1.0, 2.0, 3.0)])
    mitchell = best("mitchell", [{"b": b, "c": c} for b, c in ((0, 0.5), (1 / 3, 1 / 3), (-0.4, 1.0))])
    assert max(lanczos[0], mitchell[0]) < min(v[0] for v in simple.values())
    assert simple["box"][1] == 5
