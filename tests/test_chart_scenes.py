"""Issue 27, item 3: chart and flat scenes from a RAW whose camera is known
only by its colour matrix. ``auto`` must not hand such a scene to the model
that is worse for it (``python -m benchmarks.chart_scenes`` measures the
whole set; here four of its Mondrians through the real app)."""

from __future__ import annotations

import numpy as np
from fastapi.testclient import TestClient

from benchmarks.chart_scenes import angle, scene_bytes
from service.app import app


def test_auto_on_matrix_described_mondrians_does_not_pick_the_worse_model():
    """Four Mondrian DNGs (measured reflectances and lights, two shipped
    cameras' measured sensitivities) whose Make/Model name no known camera,
    so the service knows the camera only by ColorMatrix1 (``source ==
    "matrix-derived"``). On the benchmark's 300 such scenes the posterior's
    mean error was 1.14-1.27 degrees against the learnt estimator's
    2.45-4.51; here ``auto`` must be within the issue's 1.1 x the better of
    the two on these scenes' mean, and say in its diagnostics what decided
    (the uniform patches and the camera's description)."""
    errs = {m: [] for m in ("auto", "learned", "bayes")}
    with TestClient(app, base_url="http://localhost") as c:
        for cam in ("Nikon 5100 (NPL)", "Canon EOS 5D Mark II"):
            for light in ("A", "D50"):
                data, truth = scene_bytes(cam, light, "mondrian", 0, matrix_only=True)
                for m in errs:
                    r = c.post("/v1/analyze", files={"file": ("scene.dng", data)}, data={"method": m})
                    assert r.status_code == 200, r.text
                    body = r.json()
                    assert body["camera"]["source"] == "matrix-derived"
                    errs[m].append(angle(body["illuminant"]["camera_rgb"], truth))
                    if m == "auto":
                        choice = body["diagnostics"]["auto_choice"]
                        assert "uniform patches" in choice and "matrix-derived" in choice, choice
    mean = {m: float(np.mean(v)) for m, v in errs.items()}
    assert mean["auto"] <= 1.1 * min(mean["learned"], mean["bayes"]), mean


def test_auto_keeps_the_better_model_with_lights_and_surfaces_the_posterior_never_saw():
    """The chart scenes above use lights and reflectances the light posterior is built from. Here the
    lights are measured sources outside its candidates (colour-science's light sources: TL-84, metal
    halide, a white LED, ...) and the surfaces outside its surface density (the preferred-memory-colour
    patches and the CIE 2017 samples), two shipped cameras described only by a least-squares matrix.
    ``python -m benchmarks.chart_scenes --heldout`` measured 1.76 degrees for the posterior against the
    learnt estimator's 3.68 on 120 such scenes; here too ``auto`` must be within 1.1 x the better."""
    import models
    from benchmarks.chart_scenes import heldout_content, least_squares_matrix, matrix_scene
    from recovery import estimate_illuminant
    from recovery.cameras import camera_from_matrix

    wl = models.wavelength_grid(400, 700, 5)
    lights, surf = heldout_content(wl)
    assert len(lights) == 10 and surf.shape == (129, wl.size)
    errs = {m: [] for m in ("auto", "learned", "bayes")}
    for name in ("Nikon 5100 (NPL)", "Canon EOS 5D Mark II"):
        sens = models.camera_sensitivities(models.canonical_camera_name(name), wl)
        cam = camera_from_matrix(least_squares_matrix(sens), wl)
        for light in ("Philips TL-84", "Metal Halide", "Phosphor LED YAG"):
            for layout in ("grid", "mondrian"):
                img, truth = matrix_scene(sens, lights[light], layout, 0, surf)
                for m in errs:
                    est = estimate_illuminant(np.clip(img, 0, 1), cam, m, spatial=False, white_level=1.0)
                    errs[m].append(angle(est.rgb, truth))
    mean = {m: float(np.mean(v)) for m, v in errs.items()}
    assert all(np.isfinite(v) for v in mean.values())
    assert mean["auto"] <= 1.1 * min(mean["learned"], mean["bayes"]), mean


def test_auto_keeps_the_better_model_under_lights_tinted_off_the_locus():
    """Lights tinted off the Planckian locus (D65 and A through a plus- or minus-green filter, Duv about
    +-0.02 to +-0.04: a poor fluorescent or LED, a film gel) are outside the light posterior's candidates,
    which held it at 7.3 degrees on these 16 chart and Mondrian scenes (the learnt estimator 5.2), so
    ``auto`` missed item 3's 1.1 x. On scenes of flat patches with near-neutral surfaces (the charts here) the
    posterior now admits lights off its set (``recovery.api.OFF_SET_LIGHTS``, ``NEAR_NEUTRAL_SHARE``;
    ``python -m benchmarks.chart_scenes --off-set``): measured 4.3 here (the grids gain, the Mondrians keep the
    candidates). Required: within 1.1 x the better of the learnt estimator and the candidates-only posterior,
    and under 0.7 x the latter (measured 0.60)."""
    import models
    from benchmarks.chart_scenes import least_squares_matrix, matrix_scene, tinted_lights
    from recovery import estimate_illuminant
    from recovery.bayes import estimate_bayes
    from recovery.cameras import camera_from_matrix

    wl = models.wavelength_grid(400, 700, 5)
    lights = tinted_lights(wl)
    errs = {"auto": [], "learned": [], "candidates alone": []}
    for name in ("Nikon 5100 (NPL)", "Canon EOS 5D Mark II"):
        sens = models.camera_sensitivities(models.canonical_camera_name(name), wl)
        cam = camera_from_matrix(least_squares_matrix(sens), wl)
        for light in ("D65 tint +0.8", "D65 tint -0.8", "A tint +0.8", "A tint -0.8"):
            for layout in ("grid", "mondrian"):
                img = np.clip(matrix_scene(sens, lights[light], layout, 0)[0], 0, 1)
                truth = matrix_scene(sens, lights[light], layout, 0)[1]
                est = estimate_illuminant(img, cam, "auto", spatial=False, white_level=1.0)
                assert est.method == "bayes"
                if layout == "grid":      # the chart's grey patches pin the light: lights off the set admitted
                    assert est.diagnostics["off_set_lights"] is True, est.diagnostics["off_set_rule"]
                errs["auto"].append(angle(est.rgb, truth))
                errs["learned"].append(angle(estimate_illuminant(img, cam, "learned", spatial=False,
                                                                 white_level=1.0).rgb, truth))
                errs["candidates alone"].append(angle(estimate_bayes(img, None, cam, white_level=1.0)[0], truth))
    mean = {m: float(np.mean(v)) for m, v in errs.items()}
    assert mean["auto"] <= 1.1 * min(mean["learned"], mean["candidates alone"]), mean
    assert mean["auto"] <= 0.7 * mean["candidates alone"], mean


def _switch_rows():
    """Three sets of lights whose best switch is known: in "tinted" the scenes hold 45 % near-neutral cells
    (at every window) and lights off the set are 3 degrees better; in "common" 20 % and 2 degrees worse; in
    "one hue" 45 % too, but the scene's colours sit 20 degrees from the light (one hue dominates) and lights
    off the set are 4 degrees worse; one scene of "common" is not flat (``share`` None: never consulted)."""
    degs = (3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 15.0)
    rows = [{"set": "tinted", "camera": f"c{i % 2}", "layout": "grid", "never": 4.0, "always": 1.0,
             "share": dict.fromkeys(degs, 0.45), "balance": 3.0} for i in range(4)]
    rows += [{"set": "common", "camera": f"c{i % 2}", "layout": "mondrian", "never": 1.0, "always": 3.0,
              "share": dict.fromkeys(degs, 0.2), "balance": 2.0} for i in range(4)]
    rows.append({"set": "common", "camera": "c0", "layout": "grid", "never": 1.0, "always": 9.0, "share": None})
    rows += [{"set": "one hue", "camera": f"c{i % 2}", "layout": "grid", "never": 2.0, "always": 6.0,
              "share": dict.fromkeys(degs, 0.45), "balance": 20.0} for i in range(4)]
    return rows


def test_switch_choice_separates_the_sets_where_the_shares_and_the_balance_do():
    """Any share in (20 %, 45 %] with a balance threshold in [3, 20) degrees switches exactly the scenes it
    should (every set at its best); every rule but the minimax must find one, and the tie-break takes the
    largest such share (fewer scenes off the set), the smallest such balance and the narrowest window: 40 %
    within 3 degrees, balance <= 4 degrees. Without the balance (window and share only) the one-hue charts
    cannot be told from the tinted ones. The errors of a switch are read scene by scene."""
    from benchmarks.chart_scenes import SWITCH_RULES, switch_choice, switch_errors

    rows = _switch_rows()
    assert list(switch_errors(rows, 8.0, 0.3, 10.0)) == [1.0] * 8 + [1.0] + [2.0] * 4
    assert list(switch_errors(rows, 8.0, 0.3)) == [1.0] * 8 + [1.0] + [6.0] * 4       # balance not consulted
    assert list(switch_errors(rows, 8.0, 0.1, 10.0)) == [1.0] * 4 + [3.0] * 4 + [1.0] + [2.0] * 4
    assert list(switch_errors(rows, 8.0, float("inf"))) == [4.0] * 4 + [1.0] * 5 + [2.0] * 4
    for rule in set(SWITCH_RULES) - {"max-ratio"}:
        assert switch_choice(rows, rule) == (3.0, 0.4, 4.0), rule
    # the worst set's ratio is 1 whatever the switch ("common" cannot beat its candidates), so the minimax rule
    # ties everywhere and its tie-break keeps the candidates alone
    assert switch_choice(rows, "max-ratio")[1] == float("inf")
    # with the balance left out the choice must trade "tinted" against "one hue"
    assert switch_choice(rows, "mean", balances=(float("inf"),))[2] == float("inf")


def test_switch_cv_scores_the_left_out_set_with_the_switch_chosen_without_it():
    """Left out "common": chosen on the others, 40 % within 3 degrees and the smallest balance that keeps
    "tinted", so "common" keeps the candidates (1.0, against 3.0 for always off the set). Left out "one hue":
    chosen on "tinted" and "common", where no scene has its balance, so the smallest balance threshold that
    keeps "tinted" (4 degrees) is taken and "one hue" keeps the candidates (2.0). Left out "tinted": chosen on
    the two where never switching is best, so "tinted" gets the candidates' 4.0: what a set never seen in the
    choice costs."""
    from benchmarks.chart_scenes import switch_cv

    res = {r["left out"]: r for r in switch_cv(_switch_rows(), "set", "ratio")}
    assert res["common"]["chosen"] == (3.0, 0.4, 4.0) and res["common"]["cv"] == 1.0
    assert abs(res["common"]["always"] - 21.0 / 5) < 1e-12 and res["common"]["never"] == 1.0
    assert res["one hue"]["chosen"] == (3.0, 0.4, 4.0) and res["one hue"]["cv"] == 2.0
    assert res["tinted"]["chosen"][1] == float("inf") and res["tinted"]["cv"] == 4.0


def test_chroma_shape_does_not_depend_on_the_light():
    """A von Kries change of light multiplies every cell by the same three gains: a translation in
    log-chromaticity, which leaves the covariance of the cells' log-chromaticities, hence the isotropy and
    the spread, exactly as they were; a chart of many hues is isotropic, a line of one hue is not."""
    from recovery.api import chroma_shape

    rng = np.random.default_rng(3)
    lc = rng.normal(0.0, 0.3, (32, 32, 2))              # log(r/g), log(b/g) independent, equal spread
    cells = 0.5 * np.stack([np.exp(lc[..., 0]), np.ones((32, 32)), np.exp(lc[..., 1])], axis=2)
    ok = np.ones((32, 32), bool)
    iso, spread = chroma_shape(cells, ok)
    iso2, spread2 = chroma_shape(cells * np.array([2.0, 1.0, 0.4]), ok)
    assert abs(iso - iso2) < 1e-9 and abs(spread - spread2) < 1e-9
    assert iso > 0.8 and abs(spread - 0.3 * np.sqrt(2)) < 0.05      # 1,024 draws: within a few % of the law
    t = rng.uniform(0, 1, (32, 32, 1))                   # one hue from grey to saturated red: a line
    line = np.concatenate([0.3 + 0.6 * t, 0.3 + 0.05 * t, 0.3 + 0.02 * t], axis=2)
    assert chroma_shape(line, ok)[0] < 0.01
