"""Issue 13, task A: the exposure rule (service.pipeline.exposure_gain) is
LibRaw's auto-brightness, the same for every file, with a user override."""

from __future__ import annotations

import json
import types

import numpy as np
import pytest

from service import options, pipeline
from service.errors import ServiceError


def _decoded(img):
    return types.SimpleNamespace(estimation=np.asarray(img, np.float32))


def _scene(rng, scale=1.0):
    """Grey-world-ish camera RGB: lognormal brightness, a few glints."""
    lum = np.clip(rng.lognormal(np.log(0.08), 0.8, (200, 300)), 0, 1)
    img = lum[..., None] * np.array([0.9, 1.0, 0.8])
    return np.clip(img * scale, 0, 1)


def test_auto_gain_sends_the_99th_percentile_to_white(rng):
    img = _scene(rng)
    g, info = pipeline.exposure_gain(_decoded(img), np.eye(3))
    assert info["rule"] == "auto"
    lvl = np.percentile(img.reshape(-1, 3), 99, axis=0).max()
    assert g == pytest.approx(1 / lvl, rel=1e-3)
    # after the gain exactly 1 % of the pixels reach white in the brightest channel
    frac = np.mean((img.reshape(-1, 3) * g).max(axis=1) > 1.0)
    assert 0.005 < frac <= 0.0101


def test_auto_gain_follows_the_content_not_the_file(rng):
    """Half the light -> one more EV: the rule is a property of the image."""
    img = _scene(rng)
    g1, _ = pipeline.exposure_gain(_decoded(img), np.eye(3))
    g2, _ = pipeline.exposure_gain(_decoded(img * 0.5), np.eye(3))
    assert np.log2(g2 / g1) == pytest.approx(1.0, abs=1e-3)


def test_auto_gain_never_darkens_and_is_bounded(rng):
    bright = np.ones((50, 50, 3))                               # all saturated: LibRaw leaves it (gain 1)
    assert pipeline.exposure_gain(_decoded(bright), np.eye(3))[0] == 1.0
    black = np.full((50, 50, 3), 1e-6)                          # nothing there: at most 256 (8 EV)
    assert pipeline.exposure_gain(_decoded(black), np.eye(3))[0] == 256.0
    assert pipeline.exposure_gain(object(), np.eye(3))[1]["rule"] == "none"


@pytest.mark.parametrize("value,expected", [(None, None), ("", None), ("auto", None), ("AUTO", None),
                                            ("1.5", 1.5), (-2, -2.0), ("0", 0.0)])
def test_parse_exposure_accepts(value, expected):
    assert options.parse_exposure(value) == expected


@pytest.mark.parametrize("value", ["bright", "nan", "inf", "100", "-11", "1,5"])
def test_parse_exposure_refuses(value):
    with pytest.raises(ServiceError) as e:
        options.parse_exposure(value)
    assert e.value.status == 422 and "exposure" in e.value.detail


def test_user_exposure_overrides(rng):
    g, info = pipeline.exposure_gain(_decoded(_scene(rng)), np.eye(3), exposure=2.0)
    assert g == 4.0 and info == {"rule": "user", "ev": 2.0}


def test_display_curve_is_libraws_bt709_read_as_srgb():
    """0 and 1 fixed; sRGB-encoding the curve gives BT.709's code values
    (what LibRaw writes and a display shows as sRGB)."""
    x = np.array([0.0, 0.01, 0.18, 0.5, 1.0])
    y = pipeline.display_curve(x)
    assert y[0] == 0 and y[-1] == pytest.approx(1.0)
    enc = np.where(y <= 0.0031308, 12.92 * y, 1.055 * y ** (1 / 2.4) - 0.055)
    bt709 = np.where(x < 0.018, 4.5 * x, 1.099 * x ** 0.45 - 0.099)
    assert np.allclose(enc, bt709, atol=1e-6)
    assert 0.13 < y[2] < 0.15                                    # mid-grey darker than linear


@pytest.fixture(scope="module")
def client():
    from fastapi.testclient import TestClient

    from service.app import app

    with TestClient(app) as c:
        yield c


@pytest.fixture(scope="module")
def small_dng(tmp_path_factory):
    import models
    from testing.dngwriter import scene_dng

    p = tmp_path_factory.mktemp("exp") / "s.dng"
    scene_dng(p, models.camera_names()[0], "D6500", 64, 96, seed=3)
    return p.read_bytes()


def test_rest_exposure_in_header_and_bad_value_is_422(client, small_dng):
    files = {"file": ("s.dng", small_dng, "application/octet-stream")}
    r = client.post("/v1/white-balance", files=files, data={"format": "png"})
    assert r.status_code == 200, r.text
    head = json.loads(r.headers["X-Illuminant"])
    assert head["rendering"]["exposure"]["rule"] == "auto" and head["rendering"]["curve"] == "libraw"
    r = client.post("/v1/white-balance", files=files, data={"format": "png", "exposure": "1"})
    assert json.loads(r.headers["X-Illuminant"])["rendering"]["exposure"] == {"rule": "user", "ev": 1.0}
    r = client.post("/v1/white-balance", files=files, data={"exposure": "bright"})
    assert r.status_code == 422 and set(r.json()) >= {"error", "detail"} and "exposure" in r.json()["detail"]
