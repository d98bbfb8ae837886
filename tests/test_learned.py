"""Issue 12: the learnt default estimator on real photographs.

The method's pieces on arrays (no data needed), the shipped model, and,
on the development photographs (``../shared/data/real``; skipped with a
reason without them, failing when ``CI`` is set), leave-one-camera-out
accuracy against the peers in the same run, the calibration of the
reported 90 % region, the rebuild of the shipped model, and the same
estimate through ``/v1/analyze`` on a DNG written from a real thumbnail.
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


def test_shipped_model_loads_without_the_development_data_and_says_what_it_learnt():
    model = L.load_model()
    assert model.info["command"] == "python -m benchmarks.train_illuminant"
    assert len(model.info["cameras"]) == 10 and sum(model.info["cameras"].values()) == 3560
    assert model.info["features"] == list(L.FEATURE_NAMES)
    assert L.DEFAULT_MODEL_PATH.stat().st_size < 100_000      # a small data file


def test_default_estimate_is_the_learnt_one_with_a_physical_spectrum():
    from testing.scenes import mondrian_scene  # a synthetic scene: only the plumbing is checked here

    cam = Camera.named("Nikon 5100 (NPL)")
    scene = mondrian_scene(np.random.default_rng(3), 16, "Nikon 5100 (NPL)", "D65", size=64, step=10.0)
    img = scene.image
    est = estimate_illuminant(img, cam)
    assert est.method == "learned"
    d = est.diagnostics
    assert 0.0 <= d["confidence"] <= 1.0 and d["region90_deg"] > 0
    assert np.all(np.isfinite(est.rgb)) and np.all(est.spectrum >= 0) and np.all(np.isfinite(est.spectrum))
    # the spectrum's camera response is the reported light
    assert angular_error(cam.response(est.spectrum), est.rgb) < 0.5
    assert estimate_illuminant(img, cam, "bayes").method == "bayes"       # the posterior stays by name


def test_no_usable_cells_falls_back_declared():
    cam = Camera.named("Nikon 5100 (NPL)")
    img = np.full((40, 40, 3), 0.5)
    img[:, :, 1] = 1.0                         # every pixel saturated in green
    img[0, 0] = [0.3, 0.4, 0.2]
    est = estimate_illuminant(img, cam, white_level=1.0)
    assert est.method != "learned" and "fallback" in est.diagnostics["decision"]


# --------------------------------------------------------------------------- real photographs
@pytest.fixture(scope="module")
def real():
    if not (REAL / "nus8.npz").is_file():
        unavailable(f"{REAL} is absent (the development photographs are not next to the project)")
    from benchmarks.realdata import load_real
    from benchmarks.train_illuminant import dataset_features

    rs = load_real(REAL)
    feats, tuv, Ks = dataset_features(rs)
    return rs, feats, tuv, Ks


@pytest.fixture(scope="module")
def loco(real):
    from benchmarks.train_illuminant import leave_one_camera_out

    from benchmarks.train_illuminant import single_threaded

    rs, feats, tuv, Ks = real
    with single_threaded():
        return leave_one_camera_out(rs, feats, tuv, Ks, log=lambda s: None)


def test_leave_one_camera_out_beats_shades_of_gray_on_real_photographs(real, loco):
    """The issue's gap: on real photographs the default must beat the
    one-line peers. Measured together in this run: pooled mean and median
    and, per camera, the mean on at least 8 of the 10 held-out cameras."""
    from benchmarks.realdata import error_stats, usable_mask
    from recovery.estimators import shades_of_gray

    rs = real[0]
    err = loco[2]
    sog = np.array([shades_of_gray(im, usable_mask(im), 6.0) for im in rs.images])
    e_sog = angular_error(sog, rs.truth)
    a, b = error_stats(err), error_stats(e_sog)
    assert a["mean"] < b["mean"] and a["median"] < b["median"] and a["worst25"] < b["worst25"], (a, b)
    wins = sum(err[rs.camera == c].mean() < e_sog[rs.camera == c].mean() for c in rs.cameras)
    assert wins >= 8, wins


def test_reported_90_percent_region_holds_the_light_85_to_95_percent(real, loco):
    """Each camera's region calibrated on the other cameras' held-out
    residuals; pooled over the images, the truth is inside for 85-95 %."""
    from benchmarks.train_illuminant import coverage_by_camera

    rs, feats, tuv, Ks = real
    uv, spread, err = loco
    cov = coverage_by_camera(rs, uv, tuv, spread)
    pooled = sum(cov[c] * np.sum(rs.camera == c) for c in rs.cameras) / len(rs.truth)
    assert 0.85 <= pooled <= 0.95, cov


def test_confidence_is_calibrated_on_held_out_cameras(real, loco):
    """``confidence`` is P(error < 3 deg): on images of cameras neither the
    network nor the confidence law saw, the predicted and observed
    fractions agree overall within 0.05 (binomial spread on 3,560 images is
    0.008; the rest is camera-to-camera shift), and the images flagged low
    confidence are more often wrong than the others."""
    from benchmarks.train_illuminant import held_out_confidence
    from recovery.api import LOW_CONFIDENCE

    rs, feats, tuv, Ks = real
    uv, spread, err = loco
    conf = held_out_confidence(rs, uv, tuv, spread, err, Ks)
    ok = err < 3.0
    assert abs(conf.mean() - ok.mean()) < 0.05, (conf.mean(), ok.mean())
    low = conf < LOW_CONFIDENCE
    assert 0 < low.sum() < 0.25 * len(conf) and ok[low].mean() < ok[~low].mean() - 0.1


def test_rebuilding_the_model_gives_the_shipped_one(real, tmp_path):
    """The command is deterministic up to the BLAS kernel: the same data
    give the shipped model's estimates. The training holds BLAS to one thread,
    but which kernel OpenBLAS picks (``OPENBLAS_CORETYPE``, set on some
    machines of this kind) still orders sums differently, and L-BFGS on the
    non-convex network carries that into the parameters. Measured with
    ``python -m benchmarks.rebuild_spread`` (rebuilds under Haswell, SkylakeX
    and Prescott kernels, each in its own process, 10 sampled images):
    largest angle between any two rebuilds' estimates 0.096 degrees
    (Haswell vs Prescott; SkylakeX, this machine's own kernel, reproduced the
    shipped model exactly), largest change of a recorded leave-one-camera-out
    figure 0.032 degrees. The bounds are twice those: 0.2 and 0.065 degrees."""
    from benchmarks import train_illuminant

    out = tmp_path / "m.npz"
    assert train_illuminant.main(["--data", str(REAL), "--out", str(out)]) == 0
    new, old = L.load_model(str(out)), L.load_model()
    rs = real[0]
    for i in range(0, len(rs.truth), 359):
        m = rs.matrices[rs.camera[i]]
        from benchmarks.realdata import usable_mask

        a = L.estimate_learned(rs.images[i], usable_mask(rs.images[i]), m, new).rgb
        b = L.estimate_learned(rs.images[i], usable_mask(rs.images[i]), m, old).rgb
        assert angular_error(a, b) < 0.2
    for k, v in old.info["leave_one_camera_out"].items():
        assert abs(new.info["leave_one_camera_out"][k] - v) < 0.065, k


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
        for i in (3, 1900, 2900):
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
