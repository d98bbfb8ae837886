"""The metamer set's extent (recovery.metamers; issue 31 item 2's "range of the metamer set"):
linear programmes, checked against what the mathematics says they must give."""

from __future__ import annotations

import json

import numpy as np
import pytest

import models
from recovery.metamers import metamer_range
from recovery.surface_prior import lighting_operator

WL = models.wavelength_grid(400, 700, 10)
DL = models.wavelength_step(WL)


def _camera(name="Nikon 5100 (NPL)"):
    return models.camera_sensitivities(models.canonical_camera_name(name), WL)


def test_every_true_reflectance_lies_inside_its_metamer_range():
    """A reflectance in [0, 1] whose response is given exactly is one of its own metamers, so at every
    wavelength it lies between the least and the greatest of them (24 ColorChecker patches under A and D65)."""
    R = models.reflectance_set("colorchecker", WL)
    for light in ("A", "D65"):
        A = lighting_operator(_camera(), models.illuminant(light, WL), DL)
        y = R @ A.T
        mr = metamer_range(A, y, 1e-6 * np.abs(y).max())
        assert np.all(mr.physical) and np.all(mr.slack == 0)
        assert np.all(mr.lower <= R + 1e-7) and np.all(R <= mr.upper + 1e-7)
        assert np.all((mr.lower >= 0) & (mr.upper <= 1) & (mr.lower <= mr.upper))
        # three sensors leave most of the spectrum open: the range is wide on average, narrow nowhere near 0
        assert 0.3 < mr.width.mean() < 1.0


def test_as_many_independent_channels_as_wavelengths_fix_the_reflectance_to_the_tolerance():
    """With A the identity every channel sees one wavelength: the metamer set is the box |r - y| <= t, so
    the range is exactly [y - t, y + t] clipped to [0, 1]."""
    y = np.array([[0.2, 0.5, 0.95, 0.01, 0.7]])
    t = 0.03
    mr = metamer_range(np.eye(5), y, t)
    np.testing.assert_allclose(mr.lower, np.clip(y - t, 0, 1), atol=1e-7)
    np.testing.assert_allclose(mr.upper, np.clip(y + t, 0, 1), atol=1e-7)


def test_more_channels_can_only_narrow_the_range():
    """A six-channel camera (the three channels, and the same behind a long-pass filter) constrains a
    superset of what the three do: its metamer set is a subset, so its range lies inside."""
    S3 = _camera()
    edge = 1.0 / (1.0 + np.exp(-(WL - 550.0) / 15.0))
    S6 = np.hstack([S3, S3 * edge[:, None]])
    E = models.illuminant("D50", WL)
    R = models.reflectance_set("colorchecker", WL)[::4]
    A3, A6 = lighting_operator(S3, E, DL), lighting_operator(S6, E, DL)
    y3, y6 = R @ A3.T, R @ A6.T
    m3 = metamer_range(A3, y3, 1e-6 * np.abs(y3).max(axis=1, keepdims=True))
    m6 = metamer_range(A6, y6, np.hstack([m3.tolerance, m3.tolerance]))
    assert np.all(m6.lower >= m3.lower - 1e-7) and np.all(m6.upper <= m3.upper + 1e-7)
    assert m6.width.mean() < m3.width.mean() - 0.05


def test_a_response_brighter_than_white_is_a_matter_of_scale_not_of_colour():
    """Twice the response of a perfect white, 1 % tolerance: no reflectance in [0, 1] gives it, but its colour
    is a white's, so ``scale`` is the factor by which it exceeds the brightest white within the tolerance
    (2 / 1.01 ... 2 / 0.99: 1.99 at most) and ``slack`` stays 0; the range is the dimmest fitting copy's
    multiplied back, which is the white scaled (every bound near ``scale``) and nothing NaN."""
    A = lighting_operator(_camera(), models.illuminant("D65", WL), DL)
    white = A @ np.ones(WL.size)
    mr = metamer_range(A, 2 * white, 0.01 * white)
    assert mr.slack[0] == 0 and not mr.physical[0]
    assert 2 / 1.01 - 1e-6 <= mr.scale[0] <= 2 / 0.99 + 1e-6
    assert np.all(np.isfinite(mr.lower)) and np.all(np.isfinite(mr.upper))
    assert np.all(mr.upper <= mr.scale[0] + 1e-9) and np.median(mr.lower) > 0.9 * mr.scale[0]


def test_a_colour_out_of_reach_widens_the_tolerance_and_says_so():
    """A response with a negative channel (no reflectance, at any brightness, gives it): ``scale`` stays 1,
    ``slack`` > 0 (the tolerance grown until a reflectance fits), the bounds in [0, 1]."""
    A = lighting_operator(_camera(), models.illuminant("D65", WL), DL)
    white = A @ np.ones(WL.size)
    mr = metamer_range(A, np.array([-1.0, 1.0, 1.0]) * white, 0.01 * white)
    assert mr.slack[0] > 0 and mr.scale[0] == 1 and not mr.physical[0]
    assert np.all((mr.lower >= 0) & (mr.upper <= 1) & (mr.lower <= mr.upper))


def test_a_dimmer_response_is_left_as_it_is():
    """Half a white fits: scale 1, slack 0, physical; the half-white reflectance lies inside."""
    A = lighting_operator(_camera(), models.illuminant("D65", WL), DL)
    white = A @ np.ones(WL.size)
    mr = metamer_range(A, 0.5 * white, 0.001 * white)
    assert mr.physical[0] and mr.scale[0] == 1 and mr.slack[0] == 0
    assert np.all(mr.lower <= 0.5 + 1e-7) and np.all(mr.upper >= 0.5 - 1e-7)


@pytest.mark.parametrize("args, words", [
    ((np.ones((3, 31)), np.ones(3), 0.0), "tolerance"),
    ((np.ones((3, 31)), np.array([1.0, np.nan, 1.0]), 0.1), "finite"),
    ((np.ones((3, 31)), np.ones(4), 0.1), "does not match"),
])
def test_bad_arguments_are_named(args, words):
    with pytest.raises(ValueError, match=words):
        metamer_range(*args)


def _chart_image(cam, light="A"):
    wl = cam.wavelengths
    R = models.reflectance_set("colorchecker", wl)
    E = models.illuminant(light, wl)
    rho = R @ (cam.sensitivities.T * (E * cam.dlambda)).T
    img = np.repeat(np.repeat(rho.reshape(4, 6, 3), 20, 0), 20, 1)
    return img / img.max() * 0.8, R, [(10 + 20 * i, 10 + 20 * j) for i in range(4) for j in range(6)]


def test_analysis_gives_the_metamer_range_of_its_own_light_camera_and_scale():
    """``analyze(...).metamer_range`` is :func:`metamer_range` of the pixel's response divided by the
    surfaces' exposure, under the nominal camera and light the estimates use, at 2 noise standard deviations
    (recomputed here from those documented ingredients); the estimate and (on this chart, whose light the
    posterior finds within a degree) the true reflectances on the estimate's scale lie inside it."""
    from recovery import Camera, analyze
    from recovery.api import METAMER_POINTS
    from recovery.errors import InputError
    from recovery.surface_prior import _noise_var

    cam = Camera.named("Nikon 5100 (NPL)")
    img, R, pts = _chart_image(cam)
    res = analyze(img, cam, spatial=False)
    mr = res.metamer_range(pts)
    A = lighting_operator(res.prior_sensitivities[0], res.prior_lights[0], cam.dlambda)
    y = img[tuple(np.array(pts).T)] / res.prior_exposure
    tol = 2.0 * np.sqrt(_noise_var(res.prior, A, None))
    ref = metamer_range(A, y, tol)
    np.testing.assert_allclose(mr.lower, ref.lower, atol=1e-9)
    np.testing.assert_allclose(mr.upper, ref.upper, atol=1e-9)
    est = res.surface_estimates(pts).mean
    assert np.mean((est >= mr.lower - 1e-6) & (est <= mr.upper + 1e-6)) > 0.99
    k = np.sum(est * R) / np.sum(R * R)
    assert np.mean((R * k >= mr.lower - 1e-6) & (R * k <= mr.upper + 1e-6)) > 0.99
    with pytest.raises(InputError, match="at most"):
        res.metamer_range([pts[0]] * (METAMER_POINTS + 1))
    # the literal method has its own scale; the range is defined there too
    lit = analyze(img, cam, spatial=False, surface_estimator="pinv").metamer_range(pts[:3])
    assert np.all((lit.lower >= 0) & (lit.upper <= 1) & (lit.lower <= lit.upper))


def test_surfaces_endpoint_gives_metamer_ranges_within_a_bounded_cost():
    """``POST /v1/surfaces`` with ``metamers=true``: each surface carries ``metamer_lower`` <=
    ``metamer_upper`` in [0, ``metamer_scale``] per wavelength and ``metamer_slack``, the answer says what they
    mean; the CSV gains slack and scale columns and two per wavelength; more than 64 surfaces is a 413 naming the limit; a value that
    is not a boolean is a 422 naming the field."""
    from fastapi.testclient import TestClient

    from benchmarks.chart_scenes import scene_bytes
    from service.app import app

    data, _ = scene_bytes("Nikon 5100 (NPL)", "D50", "grid", 0, matrix_only=False)
    with TestClient(app, base_url="http://localhost") as c:
        r = c.post("/v1/surfaces", files={"file": ("s.dng", data)},
                   data={"points": "[[30, 40], [60, 90]]", "metamers": "true"})
        assert r.status_code == 200, r.text
        body = json.loads(r.text, parse_constant=lambda x: pytest.fail(f"non-finite {x} in the answer"))
        assert "metamer" in body["metamers"]
        n = len(body["wavelengths"])
        for s in body["surfaces"]:
            lo, hi = np.array(s["metamer_lower"]), np.array(s["metamer_upper"])
            assert lo.shape == hi.shape == (n,) and np.all((0 <= lo) & (lo <= hi) & (hi <= s["metamer_scale"]))
            assert s["metamer_slack"] >= 0 and s["metamer_scale"] >= 1
        plain = c.post("/v1/surfaces", files={"file": ("s.dng", data)}, data={"points": "[[30, 40]]"}).json()
        assert "metamer_lower" not in plain["surfaces"][0] or plain["surfaces"][0]["metamer_lower"] is None
        csv = c.post("/v1/surfaces", files={"file": ("s.dng", data)},
                     data={"points": "[[30, 40]]", "metamers": "true", "format": "csv"})
        head, row = csv.text.splitlines()[:2]
        assert len(head.split(",")) == len(row.split(",")) == 3 + n + 1 + n + 2 + 2 * n
        assert head.split(",")[-1] == "max 700"
        big = c.post("/v1/surfaces", files={"file": ("s.dng", data)}, data={"grid": "9x9", "metamers": "true"})
        assert big.status_code == 413 and "at most 64" in big.json()["detail"]
        bad = c.post("/v1/surfaces", files={"file": ("s.dng", data)}, data={"points": "[[30, 40]]", "metamers": "x"})
        assert bad.status_code == 422 and "metamers" in bad.json()["detail"]


def test_a_white_card_at_the_scenes_exposure_is_not_called_a_wrong_light():
    """Probe round 8b: a correctly exposed ColorChecker DNG under D65 (the light right), its white patch put
    at a reflectance of about 1.16 by the surfaces' exposure, was told "no physical reflectance ... the light,
    the exposure or the camera is wrong here" (slack 144). Brighter than white is a matter of scale: no patch
    of the chart may now get a slack, and the white one says it is a matter of scale."""
    import io

    from fastapi.testclient import TestClient

    from service.app import app
    from testing.dngwriter import scene_dng

    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", 64, 96, seed=1)
    with TestClient(app, base_url="http://127.0.0.1") as c:
        j = c.post("/v1/surfaces", files={"file": ("a.dng", buf.getvalue())},
                   data={"metamers": "true", "grid": "4x6"}).json()
    assert [s["where"] for s in j["surfaces"] if s["metamer_slack"] > 0] == []
    bright = [s for s in j["surfaces"] if s["metamer_scale"] > 1]
    assert bright and all(any("brighter than a perfect white" in w for w in s["warnings"]) for s in bright)
    assert not any("the light or the camera is wrong" in w for s in j["surfaces"] for w in s["warnings"])


def test_a_six_channel_camera_on_an_image_larger_than_the_analysis_grid_is_analysed():
    """Issue 31's more-than-three-channel cameras through ``analyze`` on an image larger than the 64 x 64
    analysis grid: OpenCV's resize refused more than 4 channels (a bare cv2.error), and the light posterior's
    lights off its set built a 5-dimensional grid (34 GiB, MemoryError). Now the cells are resized channel
    by channel, lights off the set are for 3-channel cameras only (asked for with 6, an InputError), and the
    six channels' surfaces, bands and metamer ranges come out finite."""
    from recovery import Camera, analyze
    from recovery.bayes import estimate_bayes
    from recovery.errors import InputError

    cam = Camera.named("Nikon 5100 (NPL)")
    wl = cam.wavelengths
    edge = 1.0 / (1.0 + np.exp(-(wl - 550.0) / 15.0))
    cam6 = Camera(wl, np.hstack([cam.sensitivities, cam.sensitivities * edge[:, None]]), name="six")
    R = models.reflectance_set("colorchecker", wl)
    E = models.illuminant("A", wl)
    rho = R @ (cam6.sensitivities.T * (E * cam.dlambda)).T
    img = np.repeat(np.repeat(rho.reshape(4, 6, 6), 20, 0), 20, 1)
    img = img / img.max() * 0.8
    pts = [(10 + 20 * (i // 6), 10 + 20 * (i % 6)) for i in range(24)]
    for spatial in (False, "auto"):
        res = analyze(img, cam6, spatial=spatial)
        assert res.illuminant.diagnostics.get("off_set_lights") is False
        pe = res.surface_estimates(pts)
        assert pe.mean.shape == (24, wl.size) and np.all(np.isfinite(pe.mean)) and np.all(np.isfinite(pe.std))
    mr = res.metamer_range(pts[:4])
    assert np.all(mr.lower <= mr.upper) and np.all(mr.slack == 0)
    with pytest.raises(InputError, match="3-channel"):
        estimate_bayes(img, None, cam6, off_set_prior=0.03)


# --------------------------------------------------------------------------- within measured surfaces
def test_a_surface_model_holds_every_reflectance_it_was_built_from():
    """With the largest residual (quantile 1), each reflectance the model was built from is ``B w + e`` with
    ``|e|`` within the allowance and in [0, 1]: one of its own model metamers, so inside its range at every
    wavelength; and the model's set is a subset of the physical one, so its range lies inside the physical
    range (both computed at the same tolerance, neither needing slack or a scale)."""
    from recovery.metamers import surface_model

    R = models.reflectance_set("colorchecker", WL)
    model = surface_model(R, 4, 1.0)
    np.testing.assert_allclose(model.basis.T @ model.basis, np.eye(4), atol=1e-12)
    np.testing.assert_allclose(model.residual, np.abs(R - R @ model.basis @ model.basis.T).max(0), atol=1e-12)
    A = lighting_operator(_camera(), models.illuminant("D65", WL), DL)
    y = R @ A.T
    t = 1e-4 * np.abs(y).max()
    inner, outer = metamer_range(A, y, t, model), metamer_range(A, y, t)
    assert np.all(inner.slack == 0) and np.all(inner.scale == 1) and np.all(outer.physical)
    assert np.all(inner.lower <= R + 1e-7) and np.all(R <= inner.upper + 1e-7)
    assert np.all(outer.lower <= inner.lower + 1e-7) and np.all(inner.upper <= outer.upper + 1e-7)
    assert inner.width.mean() < outer.width.mean() - 0.1


def test_a_surface_model_of_one_term_and_no_residual_is_a_line():
    """One term, no residual (a set of one reflectance, rounding aside): the model holds only multiples of
    that reflectance, so its metamer set is the one multiple that gives the response; the range collapses
    to it (within the tolerance's reach)."""
    from recovery.metamers import surface_model

    r = models.reflectance_set("colorchecker", WL)[5]
    model = surface_model(r[None], 1, 0.0)
    assert np.all(model.residual < 1e-12)
    A = lighting_operator(_camera(), models.illuminant("A", WL), DL)
    y = A @ (0.5 * r)
    mr = metamer_range(A, y, 1e-6 * y.max(), model)
    np.testing.assert_allclose(mr.lower[0], 0.5 * r, atol=1e-5)
    np.testing.assert_allclose(mr.upper[0], 0.5 * r, atol=1e-5)


@pytest.mark.parametrize("args, words", [
    ((np.ones((4, 31)), 5, 1.0), "dims must be in 1..4"),
    ((np.ones((10, 31)), 0, 1.0), "dims must be"),
    ((np.ones((10, 31)), 2, 1.5), "quantile must be"),
    ((np.full((10, 31), np.nan), 2, 1.0), "finite"),
])
def test_bad_surface_models_are_named(args, words):
    from recovery.metamers import surface_model

    with pytest.raises(ValueError, match=words):
        surface_model(*args)


def test_a_surface_model_on_other_wavelengths_is_refused():
    from recovery.metamers import surface_model

    model = surface_model(np.random.default_rng(0).uniform(0, 1, (10, 16)), 3)
    with pytest.raises(ValueError, match="16 wavelengths, the operators on 31"):
        metamer_range(np.ones((3, 31)), np.ones(3), 0.1, model)


def test_the_measured_model_range_through_the_api_and_the_endpoint():
    """``metamer_range(points, model="measured")`` is :func:`metamer_range` within
    :func:`recovery.api.measured_surface_model`, inside the physical range and narrower; through
    ``POST /v1/surfaces`` ``metamer_model=measured`` gives the same kind of answer, says what it holds, and
    a value that is neither model is a 422 naming the field."""
    from fastapi.testclient import TestClient

    from benchmarks.chart_scenes import scene_bytes
    from recovery import Camera, analyze
    from recovery.api import METAMER_MODEL_DIMS, measured_surface_model
    from recovery.errors import InputError
    from service.app import app

    cam = Camera.named("Nikon 5100 (NPL)")
    img, R, pts = _chart_image(cam, "D65")
    res = analyze(img, cam, spatial=False)
    inner, outer = res.metamer_range(pts[:6], model="measured"), res.metamer_range(pts[:6])
    model = measured_surface_model(tuple(cam.wavelengths))
    assert model.basis.shape == (cam.wavelengths.size, METAMER_MODEL_DIMS)
    ok = (inner.slack == 0) & (outer.slack == 0)
    assert ok.sum() >= 5
    assert np.all(outer.lower[ok] <= inner.lower[ok] + 1e-6) and np.all(inner.upper[ok] <= outer.upper[ok] + 1e-6)
    assert inner.width[ok].mean() < outer.width[ok].mean()
    with pytest.raises(InputError, match="model must be one of"):
        res.metamer_range(pts[:1], model="smooth")

    data, _ = scene_bytes("Nikon 5100 (NPL)", "D50", "grid", 0, matrix_only=False)
    with TestClient(app, base_url="http://localhost") as c:
        ask = lambda **kw: c.post("/v1/surfaces", files={"file": ("s.dng", data)},
                                  data={"points": "[[30, 40], [60, 90]]", "metamers": "true", **kw})
        phys, meas = ask().json(), ask(metamer_model="measured")
        assert meas.status_code == 200, meas.text
        meas = json.loads(meas.text, parse_constant=lambda x: pytest.fail(f"non-finite {x} in the answer"))
        assert "measured surfaces" in meas["metamers"] and "measured surfaces" not in phys["metamers"]
        for p, m in zip(phys["surfaces"], meas["surfaces"]):
            lo, hi = np.array(m["metamer_lower"]), np.array(m["metamer_upper"])
            assert np.all((0 <= lo) & (lo <= hi) & (hi <= m["metamer_scale"]))
            if p["metamer_slack"] == 0 and m["metamer_slack"] == 0 and p["metamer_scale"] == m["metamer_scale"] == 1:
                assert np.all(np.array(p["metamer_lower"]) <= lo + 1e-6)
                assert np.all(hi <= np.array(p["metamer_upper"]) + 1e-6)
        bad = ask(metamer_model="smooth")
        assert bad.status_code == 422 and "metamer_model" in bad.json()["detail"]


def test_the_model_choice_is_the_narrowest_that_holds_the_truth_on_every_left_out_set():
    """``benchmarks.metamers.model_choice``: among models whose worst left-out set holds at least
    ``MODEL_CV_LEVEL`` of the true values, the narrowest on average; when none does, the one whose worst set
    holds the most."""
    from benchmarks.metamers import MODEL_CV_LEVEL, model_choice

    lo, hi = MODEL_CV_LEVEL - 0.01, min(1.0, MODEL_CV_LEVEL + 0.005)
    cv = {(3, 0.95): {"a": (lo, 0.3), "b": (1.0, 0.3)},        # narrowest, but one set below the level
          (5, 0.95): {"a": (hi, 0.5), "b": (1.0, 0.4)},        # mean width 0.45: chosen
          (8, 1.0): {"a": (1.0, 0.6), "b": (1.0, 0.6)}}
    assert model_choice(cv) == (5, 0.95)
    cv = {(3, 0.95): {"a": (0.90, 0.3)}, (8, 1.0): {"a": (0.95, 0.6)}}
    assert model_choice(cv) == (8, 1.0)
