"""Round 9b of probing (docs/probe_round9b.md): the leftovers of round 8b
and the numerical core at its extremes, each the minimal reproduction of a
fault through the Python API, the command line as users run it
(``python -m service.cli``) or the real ASGI stack (FastAPI's TestClient),
and what holds once it is fixed."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from .conftest import isolated_app_client, strict_json


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")

_strict = strict_json


# --- 1a. AsShotWhiteXY without AsShotNeutral --------------------------------------------------

#: XYZ -> camera of the synthetic files: a D65 matrix and a different one for light A
CM_D65 = np.array([[0.9, -0.2, -0.1], [-0.3, 1.2, 0.1], [0.0, -0.1, 0.8]])
CM_A = np.array([[0.6, -0.1, -0.05], [-0.35, 1.25, 0.1], [0.05, -0.2, 1.3]])


def _xyz(xy):
    x, y = xy
    return np.array([x / y, 1.0, (1 - x - y) / y])


def _linear_dng(dtype, **tags) -> bytes:
    from testing.dngwriter import write_linear_dng

    rgb = np.random.default_rng(0).uniform(0.05, 0.9, (48, 64, 3))
    scale = 4e9 if dtype == np.uint32 else 65535
    buf = io.BytesIO()
    write_linear_dng(buf, (rgb * scale).astype(dtype), color_matrix1=CM_D65, **tags)
    return buf.getvalue()


def _as_shot(tmp_path, data: bytes, name: str):
    from service.loader import load

    p = tmp_path / name
    p.write_bytes(data)
    d = load(str(p)).decoded
    return d.as_shot_neutral, d.as_shot_problem


@pytest.mark.parametrize("dtype", [np.uint32, np.uint16], ids=["libraw-refuses", "libraw-opens"])
def test_as_shot_white_xy_gives_the_neutral_the_equivalent_as_shot_neutral_gives(tmp_path, dtype):
    """A LinearRaw DNG with AsShotWhiteXY and no AsShotNeutral was read
    without an as-shot white (LibRaw refuses 32-bit integers; for the files
    it opens it puts the xy in its daylight multipliers, not the as-shot
    ones, so those had none either). The neutral is now ``ColorMatrix *
    XYZ(xy)``, normalised (DNG specification 1.6, "Mapping Camera Color
    Space to CIE XYZ Space"): the one the same file written with that
    AsShotNeutral has."""
    xy = (0.4476, 0.4074)                          # light A's white
    want = CM_D65 @ _xyz(xy)
    want = want / want[1]
    n_xy, p_xy = _as_shot(tmp_path, _linear_dng(dtype, as_shot_neutral=None, as_shot_white_xy=xy), "xy.dng")
    n_asn, p_asn = _as_shot(tmp_path, _linear_dng(dtype, as_shot_neutral=want), "asn.dng")
    assert p_xy is None and p_asn is None
    assert n_xy is not None, "the as-shot white of AsShotWhiteXY was dropped"
    np.testing.assert_allclose(n_xy, want, rtol=1e-6)
    np.testing.assert_allclose(n_xy, n_asn, rtol=1e-6)
    if dtype == np.uint16:                         # LibRaw's own reading of the xy: its daylight multipliers
        import rawpy

        with rawpy.imread(io.BytesIO(_linear_dng(dtype, as_shot_neutral=None, as_shot_white_xy=xy))) as raw:
            pre = np.asarray(raw.daylight_whitebalance[:3], float)
        np.testing.assert_allclose(n_xy, pre[1] / pre, rtol=1e-4)


@pytest.mark.parametrize("kelvin,matrix", [(2000, "A"), (10000, "D65")])
def test_as_shot_white_xy_uses_the_matrix_interpolated_for_its_temperature(tmp_path, kelvin, matrix):
    """With ColorMatrix1 (D65) and ColorMatrix2 (light A) the matrix is the
    one interpolated in inverse temperature for the white: beyond A's 2850 K
    it is A's, beyond 6500 K D65's."""
    from recovery.dng_color import temperature_tint_to_xy

    xy = tuple(float(v) for v in temperature_tint_to_xy(kelvin, 0.0))
    cm = {"A": CM_A, "D65": CM_D65}[matrix]
    want = cm @ _xyz(xy)
    want = want / want[1]
    n, p = _as_shot(tmp_path, _linear_dng(np.uint32, as_shot_neutral=None, as_shot_white_xy=xy,
                                          color_matrix2=CM_A), "xy2.dng")
    assert p is None
    np.testing.assert_allclose(n, want, rtol=1e-5)


def test_as_shot_white_xy_is_what_white_as_shot_uses(client):
    """``white=as-shot`` on the file with AsShotWhiteXY answers what it
    answers on the file with the equivalent AsShotNeutral (it was the 422
    ``no_as_shot_white``); an xy that is not a chromaticity is that 422,
    naming the tag."""
    xy = (0.4476, 0.4074)
    want = CM_D65 @ _xyz(xy)
    want = want / want[1]
    answers = []
    for tags in ({"as_shot_neutral": None, "as_shot_white_xy": xy}, {"as_shot_neutral": want}):
        r = client.post("/v1/white-balance", files={"file": ("a.dng", _linear_dng(np.uint32, **tags))},
                        data={"white": "as-shot", "response": "json"})
        assert r.status_code == 200, r.text[:400]
        answers.append(_strict(r.text))
    a, b = answers
    assert a["illuminant"]["camera_rgb"] == pytest.approx(b["illuminant"]["camera_rgb"], rel=1e-5)
    bad = _linear_dng(np.uint32, as_shot_neutral=None, as_shot_white_xy=(0.7, 0.6))
    r = client.post("/v1/white-balance", files={"file": ("a.dng", bad)}, data={"white": "as-shot"})
    assert r.status_code == 422 and r.json()["error"] == "no_as_shot_white", r.text[:400]
    assert "AsShotWhiteXY 0.7, 0.6" in r.json()["detail"]


# --- 1b. the DNG copy of a RAW with a 255-byte name -------------------------------------------

def test_the_dng_copy_of_a_255_byte_raw_is_cut_like_the_outputs(tmp_path):
    """``wandell white-balance --xmp`` and ``wandell batch --xmp`` of a RAW
    named with 255 bytes (NAME_MAX) wrote the image and the sidecar but not
    the DNG copy: ``NAME.wandell.dng`` was 263 bytes ("no DNG copy: cannot
    write ...: File name too long"). Its stem is now cut as a batch's
    outputs' names are (188 bytes in all), the suffix kept, and a rerun of
    the batch over the folder does not take the cut copy for a photograph."""
    from .conftest import run_cli, scene_dng_bytes

    stem = "y" * 251
    src = tmp_path / "in"
    src.mkdir()
    (src / f"{stem}.dng").write_bytes(scene_dng_bytes(64, 96))
    cut = "y" * (188 - len(".wandell.dng")) + ".wandell.dng"
    r = run_cli("white-balance", "--xmp", str(src / f"{stem}.dng"), str(tmp_path / "o.tif"))
    assert r.returncode == 0, r.stderr[-600:]
    assert "no DNG copy" not in r.stderr + r.stdout, r.stderr[-600:]
    copy = src / cut
    assert copy.is_file() and copy.read_bytes()[:4] in (b"II*\x00", b"MM\x00*"), sorted(p.name[-30:] for p in src.iterdir())
    copy.unlink()
    (src / f"{stem}.xmp").unlink()                 # else the batch keeps the sidecar and makes no copy
    out = tmp_path / "out"
    args = ("batch", "--workers", "1", "--format", "jpeg", "--xmp", str(src), str(out))
    r = run_cli(*args)
    assert r.returncode == 0 and copy.is_file(), (r.returncode, r.stderr[-600:])
    assert "no DNG copy" not in r.stderr + r.stdout, r.stderr[-600:]
    again = run_cli(*args)
    assert again.returncode == 0, again.stderr[-600:]
    summary = json.loads((out / "batch.json").read_text())
    names = [it.get("name") for it in summary.get("items", summary.get("files", []))]
    assert cut not in names, names


# --- 1c. metamers= (an empty value) ---------------------------------------------------------------

def test_an_empty_metamers_is_not_given_and_the_docs_say_so(client):
    """``metamers=`` is taken as not given (false), the rule of every empty
    form field (kept: round 8b noticed it); the API's description and
    ``docs/surfaces.md`` now say so, and a blank value is still a 422."""
    from pathlib import Path

    from .conftest import scene_dng_bytes

    dng = scene_dng_bytes(64, 96)
    ask = {"points": "[[10, 10]]"}
    plain = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data=ask)
    empty = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data={**ask, "metamers": ""})
    assert plain.status_code == empty.status_code == 200, empty.text[:300]
    assert "metamer_lower" not in empty.json()["surfaces"][0]
    assert empty.json()["surfaces"] == plain.json()["surfaces"]
    blank = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data={**ask, "metamers": " "})
    assert blank.status_code == 422 and "metamers" in blank.json()["detail"], blank.text[:300]
    assert "an empty one (`metamers=`) is not" in client.get("/openapi.json").json()["info"]["description"]
    doc = (Path(__file__).resolve().parents[1] / "docs" / "surfaces.md").read_text()
    assert "An empty `metamers=` is not given (false)" in doc


# --- 2. a RAW exposed far below full scale ------------------------------------------------------

def _underexposed_dng(exposure: float) -> bytes:
    from testing.dngwriter import scene_dng

    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", 128, 192, seed=1, exposure=exposure)
    return buf.getvalue()


@pytest.mark.parametrize("exposure", [1e-4, 1e-6])
def test_a_raw_exposed_at_a_ten_thousandth_of_full_scale_is_flagged(client, exposure):
    """A RAW whose brightest surface is exposed at 1e-4 (or 1e-6) of the
    sensor's full scale is read noise only: ``/v1/analyze`` answered a light
    25 degrees from the truth with confidence 0.58 and ``low_confidence``
    false, no word of the exposure. The estimate now knows a RAW's full scale
    (its white level): confidence 0, flagged, and the warning says the
    brightest pixels' level and how many stops under it is."""
    r = client.post("/v1/analyze", files={"file": ("a.dng", _underexposed_dng(exposure))})
    assert r.status_code == 200, r.text[:300]
    j = _strict(r.text)
    d = j["diagnostics"]
    assert d["low_confidence"] is True and d["confidence"] == 0.0, (d["confidence"], d.get("confidence_rule"))
    assert d["signal_level"] < 2 ** -9
    assert any("underexposed" in w and "stops" in w and "noise" in w for w in j["warnings"]), j["warnings"]


def test_a_well_and_a_moderately_underexposed_raw_keep_their_confidence(client):
    """What holds: at 0.9 and 0.01 of full scale (7 stops under) the light
    is within a degree and its confidence is the estimator's own."""
    for exposure in (0.9, 0.01):
        j = _strict(client.post("/v1/analyze", files={"file": ("a.dng", _underexposed_dng(exposure))}).text)
        d = j["diagnostics"]
        assert d["low_confidence"] is False and d["confidence"] > 0.8, (exposure, d["confidence"])
        assert "underexposed" not in " ".join(j["warnings"])


def test_full_scale_in_the_python_api_flags_noise_and_is_checked():
    """The Python API: ``full_scale`` (default ``white_level``) says where the
    sensor's full scale lies; the same array is flagged only when its
    brightest pixels are more than 9 stops under it (the analysis is
    otherwise scale-free: the light is the same); a bad value is an
    ``InputError`` naming it."""
    from recovery import Camera, InputError, estimate_illuminant
    from testing.scenes import mondrian_scene

    cam = Camera.named("Nikon 5100 (NPL)")
    img = mondrian_scene(np.random.default_rng(3), 12, "Nikon 5100 (NPL)", "D65", 48).image.astype(float)
    plain = estimate_illuminant(img * 1e-4, cam, spatial=False)
    told = estimate_illuminant(img * 1e-4, cam, spatial=False, full_scale=1.0)
    np.testing.assert_array_equal(plain.rgb, told.rgb)
    assert "signal_level" not in plain.diagnostics and plain.diagnostics["low_confidence"] is False
    assert told.diagnostics["low_confidence"] is True and told.diagnostics["confidence"] == 0.0
    assert any("underexposed" in w for w in told.warnings)
    by_white = estimate_illuminant(img * 1e-4, cam, spatial=False, white_level=1.0)
    assert by_white.diagnostics["low_confidence"] is True
    bright = estimate_illuminant(img, cam, spatial=False, full_scale=1.0)
    assert bright.diagnostics["low_confidence"] is False
    for bad in (0, -1, float("nan"), "x"):
        with pytest.raises(InputError, match="full_scale"):
            estimate_illuminant(img, cam, spatial=False, full_scale=bad)
