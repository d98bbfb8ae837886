"""Issue 13, item 4: "use this as white" (``neutral`` on /v1/analyze,
/v1/white-balance and /v1/preview) and the warning when the light used is
more than 5 degrees from the file's as-shot white."""

from __future__ import annotations

import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

import models
from recovery import angular_error
from service.app import app
from testing.dngwriter import scene_dng

WL = models.wavelength_grid(400, 700, 10)


@pytest.fixture(scope="module")
def client():
    with TestClient(app) as c:
        yield c


def _surfaces():
    """Patch 0 is a spectrally flat grey (its camera RGB is the light's);
    the others are coloured (smooth random spectra in 0.1..0.9)."""
    rng = np.random.default_rng(5)
    f = models.fourier_basis(WL, 5)
    refl = 0.5 + 0.25 * np.tanh(rng.normal(size=(12, 4)) @ (f[:, 1:5] / np.abs(f[:, 1:5]).max(0)).T)
    refl[0] = 0.7
    return refl


def _scene(tmp_path, name="s.dng", **kw):
    kw.setdefault("noise_multiplicative", 0.01)
    t = scene_dng(tmp_path / name, models.camera_names()[0], "D6500", 120, 180, seed=4, surfaces=_surfaces(),
                  wavelengths=WL, grid=(3, 4), **kw)
    return t, (tmp_path / name).read_bytes()


def _patch_rect(t, index, margin=0.3):
    """[r0, c0, r1, c1] well inside patch ``index`` (full-resolution pixels)."""
    rr, cc = np.nonzero(t.labels == index)
    r0, r1, c0, c1 = rr.min(), rr.max() + 1, cc.min(), cc.max() + 1
    dr, dc = int((r1 - r0) * margin), int((c1 - c0) * margin)
    return [int(r0 + dr), int(c0 + dc), int(r1 - dr), int(c1 - dc)]


def _post(client, path, data, **fields):
    return client.post(path, files={"file": ("s.dng", data, "application/octet-stream")}, data=fields)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    return _scene(tmp_path_factory.mktemp("neutral"))


def test_a_grey_rectangle_gives_the_light(client, scene):
    """The mean of a flat grey patch is the light's camera RGB up to noise
    (1 % multiplicative per site, averaged over hundreds of cells: well
    under 0.2 degrees) and 14-bit quantisation."""
    t, data = scene
    rect = _patch_rect(t, 0)
    r = _post(client, "/v1/analyze", data, neutral=json.dumps(rect))
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["method"] == "neutral-surface"
    assert body["neutral"]["where"] == rect and body["neutral"]["cells_used"] > 50
    assert angular_error(body["illuminant"]["camera_rgb"], t.light_rgb) < 0.2
    assert "angle_to_estimate_deg" in body["neutral"]
    assert not any("as-shot" in w for w in body["warnings"])      # agrees with the file's (true) as-shot white
    # a point inside the same patch gives the same light within the noise of one cell
    pt = [(rect[0] + rect[2]) // 2, (rect[1] + rect[3]) // 2]
    p = _post(client, "/v1/analyze", data, neutral=json.dumps(pt)).json()
    assert p["neutral"]["cells_used"] >= 1 and angular_error(p["illuminant"]["camera_rgb"], t.light_rgb) < 2.0


def test_a_coloured_surface_as_white_warns_against_the_as_shot_white(client, scene):
    t, data = scene
    angles = [angular_error(t.patch_rgb[i], t.light_rgb) for i in range(len(t.patch_rgb))]
    k = int(np.argmax(angles))
    assert angles[k] > 10                                          # a clearly coloured patch
    body = _post(client, "/v1/analyze", data, neutral=json.dumps(_patch_rect(t, k))).json()
    assert body["as_shot"]["angle_to_estimate_deg"] > 5
    assert any("as-shot" in w and "you chose" in w for w in body["warnings"]), body["warnings"]


def test_an_estimate_far_from_the_as_shot_white_warns(client, tmp_path):
    """A D65 scene whose file says it was shot under illuminant A."""
    t, data = _scene(tmp_path, as_shot_neutral="A")
    assert angular_error(t.as_shot_neutral, t.light_rgb) > 5
    body = _post(client, "/v1/analyze", data).json()
    assert body["as_shot"]["angle_to_estimate_deg"] > 5
    assert any("the estimate is" in w and "as-shot" in w for w in body["warnings"]), body["warnings"]


def test_white_balance_and_preview_take_the_neutral(client, scene):
    t, data = scene
    rect = json.dumps(_patch_rect(t, 0))
    r = _post(client, "/v1/white-balance", data, neutral=rect, format="png")
    assert r.status_code == 200, r.text
    head = json.loads(r.headers["X-Illuminant"])
    assert head["white"] == "neutral" and head["method"] == "neutral-surface"
    assert head["rendering"]["rendering"] == "spectral" and head["neutral"]["where"] == json.loads(rect)
    p = _post(client, "/v1/preview", data, wb="corrected", neutral=rect)
    assert p.status_code == 200 and json.loads(p.headers["X-Preview"])["method"] == "neutral-surface"
    # the grey patch renders grey in the corrected image (the same rendering as an estimate)
    import cv2

    img = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_COLOR)[..., ::-1].astype(int)
    r0, c0, r1, c1 = json.loads(rect)
    m = img[r0:r1, c0:c1].reshape(-1, 3).mean(0)
    assert m.max() - m.min() < 4, m


@pytest.mark.parametrize("value,code", [
    ("[1, 2, 3]", "invalid_parameter"), ("[1.5, 2]", "invalid_parameter"), ("not json", "invalid_parameter"),
    ("[0, 0, 500, 10]", "invalid_parameter"), ("[-1, 4]", "invalid_parameter"), ("[5, 5, 5, 9]", "invalid_parameter"),
])
def test_bad_neutral_is_a_422(client, scene, value, code):
    _, data = scene
    r = _post(client, "/v1/analyze", data, neutral=value)
    assert r.status_code == 422 and r.json()["error"] == code and "neutral" in r.json()["detail"], r.text


def test_a_clipped_neutral_is_refused_and_clipped_cells_are_left_out():
    import types

    from service import pipeline
    from service.errors import ServiceError

    est = np.full((10, 20, 3), 0.2, np.float32)
    est[:, :10] = [0.3, 0.6, 0.4]                      # the light's colour, left half
    sat = np.zeros((10, 20), bool)
    sat[:, 10:] = True                                  # right half clipped
    est[:, 10:] = 1.0
    d = types.SimpleNamespace(full_shape=(40, 80), estimation=est, saturated=sat)
    with pytest.raises(ServiceError) as e:
        pipeline.neutral_white(d, [0, 40, 40, 80])      # all clipped
    assert e.value.status == 422 and e.value.code == "unusable_neutral"
    rgb, info = pipeline.neutral_white(d, [0, 20, 40, 60])   # half clipped: only the unclipped half counts
    assert np.allclose(rgb, [0.3, 0.6, 0.4]) and info["cells_used"] == 50 and info["cells_clipped_or_black"] == 50
    rgb, info = pipeline.neutral_white(d, [13, 7])           # a point: its cell (full -> estimation scale 1/4)
    assert np.allclose(rgb, [0.3, 0.6, 0.4]) and info["cells_used"] == 1


def test_neutral_with_as_shot_white_conflicts(client, scene):
    t, data = scene
    r = _post(client, "/v1/white-balance", data, neutral=json.dumps(_patch_rect(t, 0)), white="as-shot")
    assert r.status_code == 422 and "neutral" in r.json()["detail"]


def test_several_picks_are_the_mean_of_their_whites(client, scene):
    """Issue 29, item 3 ("several picks averaged"), in the API so the REST
    API and the page agree: ``neutral`` takes a list of points and
    rectangles; the white is the mean of each pick's white scaled to unit
    length (each pick weighs the same), which is what the single picks
    answer, up to floating point (bound 1e-6 degrees). Two halves of the
    grey patch give the light (as one rectangle does, 0.2 degrees), and
    /v1/white-balance and /v1/preview take the same list."""
    t, data = scene
    grey, k = _patch_rect(t, 0), 5
    other = _patch_rect(t, k)
    picks = [grey, [(other[0] + other[2]) // 2, (other[1] + other[3]) // 2], other]
    singles = [np.array(_post(client, "/v1/analyze", data, neutral=json.dumps(p)).json()["illuminant"]["camera_rgb"])
               for p in picks]
    r = _post(client, "/v1/analyze", data, neutral=json.dumps(picks))
    assert r.status_code == 200, r.text
    body = r.json()
    mean = np.mean([s / np.linalg.norm(s) for s in singles], axis=0)
    assert body["method"] == "neutral-surface"
    assert angular_error(body["illuminant"]["camera_rgb"], mean) < 1e-6
    assert body["neutral"]["where"] == picks and len(body["neutral"]["picks"]) == 3
    assert body["neutral"]["spread_deg"] == pytest.approx(max(angular_error(s, mean) for s in singles), abs=1e-6)
    halves = [[grey[0], grey[1], grey[2], (grey[1] + grey[3]) // 2], [grey[0], (grey[1] + grey[3]) // 2, grey[2], grey[3]]]
    both = _post(client, "/v1/analyze", data, neutral=json.dumps(halves)).json()
    assert angular_error(both["illuminant"]["camera_rgb"], t.light_rgb) < 0.2
    wb = _post(client, "/v1/white-balance", data, neutral=json.dumps(picks), response="json")
    assert wb.status_code == 200 and angular_error(wb.json()["illuminant"]["camera_rgb"], mean) < 1e-6, wb.text
    p = _post(client, "/v1/preview", data, wb="corrected", neutral=json.dumps(picks))
    assert p.status_code == 200 and json.loads(p.headers["X-Preview"])["method"] == "neutral-surface"


@pytest.mark.parametrize("value,words", [
    ("[[10, 10], [1, 2, 3]]", "neutral pick 2 of 2 is [1, 2, 3]"),
    ("[[10, 10], [10.5, 3]]", "neutral pick 2 of 2"),
    ("[[10, 10], [0, 0, 500, 10]]", "pick 2 of 2: neutral [0, 0, 500, 10] is outside"),
    ("[[20, 20, 10, 10]]", "pick 1 of 1: neutral [20, 20, 10, 10] is an inverted"),
    ("[]", "neutral is an empty list"),
    (json.dumps([[1, 2]] * 17), "neutral has 17 picks, at most 16"),
    ("[[1, 2], 3]", "neutral must be"),
])
def test_bad_picks_are_a_422_naming_the_pick(client, scene, value, words):
    _, data = scene
    r = _post(client, "/v1/analyze", data, neutral=value)
    assert r.status_code == 422 and r.json()["error"] == "invalid_parameter", r.text
    assert words in r.json()["detail"], r.json()["detail"]
