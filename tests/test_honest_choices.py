"""Issue 13, item 5 (rest): camera=generic on a file with a colour matrix is
compared with the matrix-based estimate and its confidence lowered; the
literal method's failure (by its own tests) is flagged in the answer the
page reads."""

from __future__ import annotations

import io

import numpy as np
import pytest
import tifffile
from fastapi.testclient import TestClient

import models
from recovery import angular_error
from service import pipeline
from service.app import app
from testing.dngwriter import scene_dng

WL = models.wavelength_grid(400, 700, 10)


@pytest.fixture(scope="module")
def client():
    with TestClient(app) as c:
        yield c


def _post(client, data, name="s.dng", **fields):
    return client.post("/v1/analyze", files={"file": (name, data, "application/octet-stream")}, data=fields)


@pytest.fixture(scope="module")
def dng(tmp_path_factory):
    p = tmp_path_factory.mktemp("honest") / "s.dng"
    scene_dng(p, models.camera_names()[0], "A", 96, 144, seed=7)
    return p.read_bytes()


def test_generic_is_compared_with_the_matrix_estimate(client, dng):
    g = _post(client, dng, camera="generic", method="auto").json()
    m = _post(client, dng, camera="matrix", method="auto").json()
    assert g["camera"]["source"] == "generic" and m["camera"]["source"] == "matrix-derived"
    d = g["diagnostics"]
    # the reported angle is the one between the two answers the service gives
    ang = angular_error(g["illuminant"]["camera_rgb"], m["illuminant"]["camera_rgb"])
    assert d["generic_vs_matrix_deg"] == pytest.approx(ang, abs=0.05)
    factor = 1 / (1 + (ang / pipeline.VISIBLE_WB_ERROR_DEG) ** 2)
    assert d["confidence_factor_generic"] == pytest.approx(factor, rel=1e-3)
    assert d["confidence"] == pytest.approx(d["confidence_before_cross_check"] * factor, rel=1e-6)
    if ang > pipeline.VISIBLE_WB_ERROR_DEG:
        assert any("camera=generic" in w for w in g["warnings"])
    # the matrix camera itself is not cross-checked
    assert "generic_vs_matrix_deg" not in m["diagnostics"]


def test_generic_cross_check_lowers_confidence_by_the_disagreement():
    """The rule on its own: agreement keeps the confidence, 3 degrees halves it."""
    import types

    from recovery import Camera

    est = types.SimpleNamespace(rgb=np.array([0.5, 1.0, 0.6]), diagnostics={"confidence": 0.8}, warnings=[])
    run = pipeline.EstimateRun(est, types.SimpleNamespace(channels=3, source="generic"), [])
    for ang, want in ((0.0, 0.8), (3.0, 0.4)):
        rot = _rotate(est.rgb, ang)
        ref = types.SimpleNamespace(rgb=rot)
        est.diagnostics = {"confidence": 0.8}
        est.warnings = []
        import recovery.cameras as cameras

        from service import estimation

        orig = (cameras.resolve_camera, estimation.estimate_illuminant)
        try:
            cameras.resolve_camera = lambda d, c: (types.SimpleNamespace(source="matrix-derived", channels=3), [])
            estimation.estimate_illuminant = lambda *a, **k: ref
            pipeline.generic_cross_check(None, run, None, None, "auto", {})
        finally:
            cameras.resolve_camera, estimation.estimate_illuminant = orig
        assert est.diagnostics["generic_vs_matrix_deg"] == pytest.approx(ang, abs=1e-6)
        assert est.diagnostics["confidence"] == pytest.approx(want, rel=1e-6)
    assert Camera is not None


def _rotate(v, deg):
    """``v`` turned by ``deg`` degrees (about an axis perpendicular to it)."""
    v = np.asarray(v, float) / np.linalg.norm(v)
    p = np.cross(v, [1.0, 0.0, 0.0])
    p /= np.linalg.norm(p)
    t = np.radians(deg)
    return np.cos(t) * v + np.sin(t) * p


def test_generic_without_a_matrix_is_not_compared(client):
    rng = np.random.default_rng(1)
    img = (rng.uniform(0.05, 0.6, (48, 64, 3)) * 65535).astype(np.uint16)
    buf = io.BytesIO()
    tifffile.imwrite(buf, img, photometric="rgb")
    body = _post(client, buf.getvalue(), name="x.tif", camera="generic").json()
    assert body["camera"]["source"] == "generic"
    assert "generic_vs_matrix_deg" not in body["diagnostics"]


def test_literal_method_failure_is_flagged(client, tmp_path):
    """One flat grey everywhere: no surface variation, the literal method's
    own tests fail (a fallback, or a fit outside the subspace: the noise is
    all the variation there is); the answer says so (the page shows it as
    a flag on the corrected image)."""
    flat = np.full((4, WL.size), 0.5)
    scene_dng(tmp_path / "f.dng", models.camera_names()[0], "D6500", 64, 96, seed=1, surfaces=flat,
              wavelengths=WL, grid=(2, 2))
    body = _post(client, (tmp_path / "f.dng").read_bytes(), method="maloney-wandell").json()
    assert body["method_failed"]["method"] == "maloney-wandell"
    assert body["method_failed"]["reasons"], body["diagnostics"]
    d = body["diagnostics"]
    assert d.get("failure") or d.get("subspace_fit_ratio", 0) > pipeline.LITERAL_FIT_TOLERANCE


def test_literal_method_success_is_not_flagged(client, dng):
    body = _post(client, dng, method="maloney-wandell").json()
    assert body["method"] == "maloney-wandell"
    if body["diagnostics"].get("subspace_fit_ratio", 0) <= pipeline.LITERAL_FIT_TOLERANCE:
        assert "method_failed" not in body
    assert "method_failed" not in _post(client, dng, method="gray-world").json()
