"""The reported light spectrum is one plausible light (issue 19 item 5).

A mixture of every candidate light weighted by its probability put
tri-phosphor lines (545, 610 nm) into the spectrum of an overcast daylight
while ``best_candidate`` said daylight. The spectrum now comes from one kind
of light (:func:`recovery.bayes.plausible_spectrum`): daylight or Planckian
unless a spiky kind holds at least ``SPIKY_MARGIN`` times their posterior
mass, always with the camera response of the estimate.

Narrow peaks are measured by the largest second difference relative to the
mean spectrum; the bound is derived from the CIE D-series themselves (the
most peaked D-series spectrum on the same grid, times 1.5 for the smooth
modulation that matches the camera response). A tri-phosphor lamp is far
above it (FL11: about 25 times).
"""

from __future__ import annotations

import numpy as np
import pytest

import models
from recovery import Camera
from recovery.api import estimate_illuminant
from recovery.bayes import SPIKY_MARGIN
from recovery.illuminant_prior import SMOOTH_KINDS, default_candidates, light_kinds
from tests.conftest import unavailable

from testing.scenes import mondrian_scene


def peakiness(spd) -> float:
    s = np.asarray(spd, float)
    return float(np.abs(np.diff(s, 2)).max() / s.mean())


def d_series_bound(wl) -> float:
    """1.5 times the most peaked CIE daylight (4000-25000 K) on ``wl``."""
    return 1.5 * max(peakiness(models.daylight(float(t), wl)) for t in 1e6 / np.arange(40.0, 250.1, 5.0))


def response_error(camera, est) -> float:
    r = camera.response(est.spectrum)
    return float(np.abs(r / np.linalg.norm(r) - est.rgb).max())


def test_bound_separates_daylight_from_fluorescent():
    wl = models.DEFAULT_WAVELENGTHS
    bound = d_series_bound(wl)
    assert peakiness(models.blackbody(3000.0, wl)) < bound
    for lamp in ("FL2", "FL11", "FL3.2"):
        assert peakiness(models.illuminant(lamp, wl)) > 3 * bound, lamp


def test_light_kinds():
    assert light_kinds("daylight 5000 K", "daylight") == [("daylight", 1.0)]
    assert light_kinds("D65", "named") == [("daylight", 1.0)]
    assert light_kinds("A", "named") == [("planckian", 1.0)]
    assert light_kinds("FL11", "named") == [("fluorescent", 1.0)]
    assert light_kinds("0.25 D50 + 0.75 FL11", "mixture") == [("daylight", 0.25), ("fluorescent", 0.75)]


@pytest.fixture(scope="module")
def nikon():
    return Camera.named("Nikon 5100 (NPL)")


@pytest.mark.parametrize("light", ["D50", "D65"])
@pytest.mark.parametrize("method", ["auto", "learned", "bayes"])
def test_synthetic_daylight_scene_has_a_smooth_spectrum(nikon, light, method):
    scene = mondrian_scene(np.random.default_rng(3), 24, "Nikon 5100 (NPL)", light, 64)
    est = estimate_illuminant(scene.image, nikon, method=method)
    d = est.diagnostics
    assert d["spectrum_family"] in SMOOTH_KINDS and d["spectrum_rule"]
    assert peakiness(est.spectrum) < d_series_bound(nikon.wavelengths), d["spectrum_rule"]
    assert response_error(nikon, est) < 1e-6
    # best_candidate is a light of the spectrum's kind
    cands = default_candidates(nikon.wavelengths)
    family = dict(zip(cands.names, cands.families))[d["best_candidate"]]
    assert light_kinds(d["best_candidate"], family) == [(d["spectrum_family"], 1.0)]


def test_fluorescent_scene_with_the_light_posterior(nikon):
    """Under FL11 the image's colours, at the estimate's chromaticity, are
    over ``SPIKY_MARGIN`` times as likely under a fluorescent lamp as under
    the best smooth light, and its most favourable colours say so clearly:
    the spiky kind is reported, that lamp, still with the estimate's
    response."""
    scene = mondrian_scene(np.random.default_rng(3), 24, "Nikon 5100 (NPL)", "FL11", 64)
    est = estimate_illuminant(scene.image, nikon, method="bayes")
    d = est.diagnostics
    assert d["spectrum_family"] == "fluorescent", d["spectrum_rule"]
    assert f"at least {SPIKY_MARGIN:g})" in d["spectrum_rule"] and "estimate's chromaticity" in d["spectrum_rule"]
    assert d["best_candidate"].startswith("FL")
    assert peakiness(est.spectrum) > d_series_bound(nikon.wavelengths)
    assert response_error(nikon, est) < 1e-6


@pytest.fixture(scope="module")
def cubeplus():
    from benchmarks.realdata import BENCHMARKS, REAL_DIR, load_real

    if not ((REAL_DIR / BENCHMARKS["Cube+"]).is_file() and (REAL_DIR / "cameras.json").is_file()):
        unavailable(f"{REAL_DIR / BENCHMARKS['Cube+']} is absent (the development photographs are not next to "
                    "the project)")
    return load_real(REAL_DIR, ["Cube+"])


@pytest.mark.parametrize("index", [0, 5, 10, 50])
def test_real_daylight_thumbnail_has_a_smooth_spectrum(cubeplus, index):
    from benchmarks.realdata import usable_mask
    from recovery.cameras import camera_from_matrix

    rs = cubeplus
    im, mat = rs.images[index], rs.matrices[rs.camera[index]]
    cam = camera_from_matrix(mat).with_color_matrix(mat)
    est = estimate_illuminant(np.where(usable_mask(im)[..., None], im, 0), cam)
    d = est.diagnostics
    assert est.method == "learned"
    assert d["spectrum_family"] == "daylight", d["spectrum_rule"]
    assert d["best_candidate"].startswith("daylight")
    assert peakiness(est.spectrum) < d_series_bound(cam.wavelengths), d["spectrum_rule"]
    assert response_error(cam, est) < 1e-6
