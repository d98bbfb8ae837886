"""The REST service through its ASGI stack, on real DNG files decoded by
LibRaw (written by :mod:`testing.dngwriter` from spectral scenes with known
truth)."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import tifffile
from fastapi.testclient import TestClient

import models
from recovery import angular_error
from service.app import app
from testing.dngwriter import scene_dng

WL5 = models.wavelength_grid(400, 700, 5)


@pytest.fixture(scope="module")
def client():
    with TestClient(app) as c:
        yield c


def _in_model_surfaces():
    """24 reflectances inside the 2-term Fourier model (DC + one sine),
    all within [0.1, 0.9]."""
    f = models.fourier_basis(WL5, 2)
    f = f / f[:, 0].mean()
    amp = np.abs(f[:, 1]).max()
    return 0.5 + (np.linspace(-0.4, 0.4, 24) / amp)[:, None] * f[:, 1][None]


def _post(client, path, data: bytes, **fields):
    return client.post(path, files={"file": ("scene.dng", data, "application/octet-stream")}, data=fields)


@pytest.mark.parametrize("camera", models.camera_names())
@pytest.mark.parametrize("light", ["D4000", "D10000"])
def test_analyze_recovers_in_model_light_through_libraw(client, tmp_path, camera, light):
    """Surfaces in the 2-term Fourier model, a CIE daylight (in the 3-term
    daylight model), no noise: eq. 30/35 are exact in the continuum, so the
    remaining error is (a) the 10 nm analysis grid against the 5 nm grid the
    scene was made on (0.007-0.07 degrees, measured without the DNG) and (b)
    14-bit quantisation (a relative step of 1/15871 at full scale, < 0.04
    degrees at the darkest patch). 0.25 degrees bounds both with margin."""
    t = scene_dng(tmp_path / "m.dng", camera, light, 160, 240, seed=2, surfaces=_in_model_surfaces(),
                  grid=(4, 6), noise_multiplicative=0, noise_additive=0)
    r = _post(client, "/v1/analyze", (tmp_path / "m.dng").read_bytes(), method="maloney-wandell",
              surface_model="fourier")
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["method"] == "maloney-wandell"
    assert body["camera"] == {"name": camera, "source": "measured", "channels": 3, "approximate": False,
                              "notes": []}
    assert angular_error(body["illuminant"]["camera_rgb"], t.light_rgb) < 0.25
    assert body["diagnostics"]["subspace_fit_ratio"] < 1e-2
    assert not any("not confined" in w for w in body["warnings"])
    cct = body["illuminant"]["cct"]
    assert cct is not None and abs(cct - float(light[1:]) * 1.4388 / 1.4380) < 0.03 * float(light[1:])
    assert set(body["timings_ms"]) >= {"decode", "estimate", "total"}
    assert len(body["illuminant"]["spectrum"]) == len(body["illuminant"]["wavelengths"]) == 31


def test_analyze_real_scene_every_method_is_finite(client, tmp_path):
    t = scene_dng(tmp_path / "cc.dng", "Nikon 5100 (NPL)", "A", 120, 180, seed=1, grid=(4, 6))
    data = (tmp_path / "cc.dng").read_bytes()
    for method in ("auto", "maloney-wandell", "gray-world", "white-patch", "shades-of-gray", "gray-edge"):
        r = _post(client, "/v1/analyze", data, method=method)
        assert r.status_code == 200, r.text
        body = r.json()
        rgb = np.array(body["illuminant"]["camera_rgb"])
        assert np.all(np.isfinite(rgb)) and np.all(rgb > 0)
        wb = np.array(body["illuminant"]["wb_multipliers"])
        assert np.isclose(wb[1], 1.0) and np.allclose(wb * rgb, rgb[1])
    # white patch finds the ColorChecker's white: its departure from flat
    # reflectance plus 1 % noise on the brightest pixels keeps it within 2 deg
    r = _post(client, "/v1/analyze", data, method="white-patch").json()
    assert angular_error(r["illuminant"]["camera_rgb"], t.light_rgb) < 2.0
    assert r["as_shot"]["angle_to_estimate_deg"] < 2.0


def test_white_balance_returns_full_resolution_neutral_tiff(client, tmp_path):
    """With the in-model light recovered (< 0.1 degree, see above) and the
    synthesis in the same surface model (Fourier, C = 3 terms, which holds
    the flat frame exactly), the neutral frame (flat 5 % reflectance)
    renders neutral under D65 in sRGB: R = G = B within 0.5 % (0.1 degree is
    about 0.2 % between channels; 16-bit rounding is 1.5e-5)."""
    t = scene_dng(tmp_path / "wb.dng", "Canon EOS 5D Mark II", "D4000", 160, 240, seed=3,
              surfaces=_in_model_surfaces(), grid=(4, 6), noise_multiplicative=0, noise_additive=0,
              as_shot_neutral="D65")
    data = (tmp_path / "wb.dng").read_bytes()
    r = _post(client, "/v1/white-balance", data, method="maloney-wandell", surface_model="fourier")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/tiff"
    img = tifffile.imread(io.BytesIO(r.content))
    assert img.shape == (160, 240, 3) and img.dtype == np.uint16
    head = json.loads(r.headers["X-Illuminant"])
    assert head["method"] == "maloney-wandell" and len(head["correction_matrix"]) == 3
    from scipy import ndimage

    inner = ndimage.binary_erosion(t.labels == t.patch_index("frame"), iterations=2)
    frame = img[inner].astype(float).mean(0)
    assert frame.max() > 0 and np.ptp(frame) / frame.mean() < 0.005
    for fmt, mime, dtype in (("png", "image/png", np.uint8), ("png16", "image/png", np.uint16),
                             ("jpeg", "image/jpeg", np.uint8)):
        r = _post(client, "/v1/white-balance", data, format=fmt)
        assert r.status_code == 200 and r.headers["content-type"] == mime
        import cv2

        dec = cv2.imdecode(np.frombuffer(r.content, np.uint8), cv2.IMREAD_UNCHANGED)
        assert dec.shape == (160, 240, 3) and dec.dtype == dtype
    j = _post(client, "/v1/white-balance", data, response="json")
    assert j.status_code == 200 and "correction_matrix" in j.json()


def test_surfaces_points_rects_grid_and_csv(client, tmp_path):
    """In-model scene: with the light recovered (< 0.1 degree) and the
    surfaces in the Fourier model the recovered reflectance of each patch
    equals the truth up to the one free scale of eq. 27-28; 2 % normalised
    RMSE bounds the light error's effect and 14-bit rounding."""
    refl = _in_model_surfaces()
    t = scene_dng(tmp_path / "s.dng", "Sigma SDMerill (NPL)", "D10000", 160, 240, seed=4, surfaces=refl,
                  grid=(4, 6), noise_multiplicative=0, noise_additive=0)
    data = (tmp_path / "s.dng").read_bytes()
    centres = []
    for p in (0, 11, 23):
        ys, xs = np.nonzero(t.labels == p)
        centres.append((int(ys.mean()), int(xs.mean())))
    cy, cx = centres[1]
    r = _post(client, "/v1/surfaces", data, points=json.dumps([list(c) for c in centres]),
              rects=json.dumps([[cy - 2, cx - 2, cy + 2, cx + 2]]), grid="2x3", method="maloney-wandell",
              surface_model="fourier")
    assert r.status_code == 200, r.text
    body = r.json()
    kinds = [s["kind"] for s in body["surfaces"]]
    assert kinds == ["point"] * 3 + ["rect"] + ["grid"] * 6
    got = np.array([s["reflectance"] for s in body["surfaces"][:4]])
    truth = models.resample(WL5, refl[[0, 11, 23, 11]].T, models.DEFAULT_WAVELENGTHS).T
    scale = np.sum(got * truth) / np.sum(got * got)
    assert np.all(models.normalised_rmse(truth, got * scale) < 0.02)
    assert all(isinstance(s["warnings"], list) for s in body["surfaces"])
    csv = _post(client, "/v1/surfaces", data, grid="1x2", format="csv")
    assert csv.status_code == 200 and csv.headers["content-type"].startswith("text/csv")
    lines = csv.text.strip().splitlines()
    assert len(lines) == 3 and lines[0].startswith("kind,where,warnings,400")


def test_cameras_models_and_matrix_derived_camera(client, tmp_path):
    cams = client.get("/v1/cameras").json()
    assert {c["name"] for c in cams["cameras"]} == set(models.camera_names())
    m = client.get("/v1/models").json()
    assert "D(E) <= D(S) + 1" in m["rules"]
    scene_dng(tmp_path / "u.dng", "Nikon 5100 (NPL)", "D65", 64, 96, seed=5, make="Foo", model="Bar 1")
    r = _post(client, "/v1/analyze", (tmp_path / "u.dng").read_bytes())
    assert r.status_code == 200, r.text
    body = r.json()
    assert body["camera"]["source"] == "matrix-derived" and body["camera"]["approximate"]
    assert any("approximate" in w for w in body["warnings"])


def test_uploaded_sensitivities_csv(client, tmp_path):
    t = scene_dng(tmp_path / "c.dng", "Canon EOS 5D Mark II", "D65", 64, 96, seed=6, make="Foo", model="Bar")
    sens = models.camera_sensitivities("Canon EOS 5D Mark II", WL5)
    csv = "wavelength,r,g,b\n" + "\n".join(f"{w},{a},{b},{c}" for w, (a, b, c) in zip(WL5, sens))
    r = client.post("/v1/analyze", files={"file": ("c.dng", (tmp_path / "c.dng").read_bytes()),
                                          "sensitivities": ("s.csv", csv.encode())},
                    data={"method": "white-patch"})
    assert r.status_code == 200, r.text
    assert r.json()["camera"]["source"] == "uploaded"
    assert angular_error(r.json()["illuminant"]["camera_rgb"], t.light_rgb) < 2.0
    bad = client.post("/v1/analyze", files={"file": ("c.dng", (tmp_path / "c.dng").read_bytes()),
                                            "sensitivities": ("s.csv", b"wavelength,r\n400,1\n")})
    assert bad.status_code == 422 and bad.json()["error"]


@pytest.fixture(scope="module")
def good_dng(tmp_path_factory):
    p = tmp_path_factory.mktemp("dng") / "g.dng"
    scene_dng(p, "Nikon 5100 (NPL)", "D65", 64, 96, seed=7)
    return p.read_bytes()


def _bad_cases(good: bytes):
    import cv2

    jpeg = cv2.imencode(".jpg", np.zeros((32, 32, 3), np.uint8))[1].tobytes()
    png8 = cv2.imencode(".png", np.zeros((32, 32, 3), np.uint8))[1].tobytes()
    flipped = bytearray(good)
    flipped[8:64] = bytes(b ^ 0xFF for b in flipped[8:64])
    return {
        "empty": (b"", (422,)),
        "random": (np.random.default_rng(0).bytes(5000), (415, 422)),
        "text": (b"hello, this is not an image\n" * 50, (415, 422)),
        "jpeg": (jpeg, (415,)),
        "png8": (png8, (415,)),
        "truncated_half": (good[: len(good) // 2], (422,)),
        "truncated_header": (good[:100], (415, 422)),
        "bitflipped_header": (bytes(flipped), (415, 422)),
    }


@pytest.mark.parametrize("case", ["empty", "random", "text", "jpeg", "png8", "truncated_half",
                                  "truncated_header", "bitflipped_header"])
@pytest.mark.parametrize("path", ["/v1/analyze", "/v1/white-balance", "/v1/surfaces"])
def test_bad_uploads_are_4xx_json_and_service_keeps_serving(client, good_dng, case, path):
    data, statuses = _bad_cases(good_dng)[case]
    extra = {"grid": "2x2"} if path == "/v1/surfaces" else {}
    r = _post(client, path, data, **extra)
    assert r.status_code in statuses, (case, r.status_code, r.text)
    body = r.json()
    assert set(body) == {"error", "detail"} and body["detail"]
    assert client.get("/health").status_code == 200
    assert _post(client, "/v1/analyze", good_dng).status_code == 200


def test_bad_parameters_list_what_is_accepted(client, good_dng):
    cases = [({"method": "magic"}, "gray-world"), ({"camera": "Leica M"}, "Nikon 5100"),
             ({"surface_dim": "3", "light_dim": "3", "method": "maloney-wandell"}, "D(S) < C"),
             ({"surface_dim": "1", "light_dim": "3", "method": "maloney-wandell"}, "D(E) <= D(S) + 1"),
             ({"surface_dim": "abc"}, "surface_dim"), ({"surface_model": "wavelets"}, "fourier")]
    for fields, needle in cases:
        r = _post(client, "/v1/analyze", good_dng, **fields)
        assert r.status_code == 422, (fields, r.text)
        assert needle in r.json()["detail"], (fields, r.json())
    r = _post(client, "/v1/white-balance", good_dng, format="bmp")
    assert r.status_code == 422 and "tiff" in r.json()["detail"]
    r = _post(client, "/v1/white-balance", good_dng, target="D65x")
    assert r.status_code == 422 and "D65x" in r.json()["detail"]
    r = _post(client, "/v1/surfaces", good_dng, points="[[1,2,3]]")
    assert r.status_code == 422 and "points" in r.json()["detail"]
    r = _post(client, "/v1/surfaces", good_dng, points="[[100000, 5]]")
    assert r.status_code == 422 and "outside" in r.json()["detail"]
    r = client.post("/v1/analyze")
    assert r.status_code == 422 and r.json()["error"]


def test_size_and_pixel_limits_are_413(good_dng, monkeypatch):
    from service.settings import Settings, get_settings

    app.dependency_overrides[get_settings] = lambda: Settings(max_upload_bytes=10_000, max_pixels=50_000_000)
    try:
        with TestClient(app) as c:
            r = _post(c, "/v1/analyze", good_dng)
            assert r.status_code == 413 and r.json()["error"] == "file_too_large"
    finally:
        app.dependency_overrides.clear()
    app.dependency_overrides[get_settings] = lambda: Settings(max_pixels=1000)
    try:
        with TestClient(app) as c:
            r = _post(c, "/v1/analyze", good_dng)
            assert r.status_code == 413 and r.json()["error"] == "too_many_pixels"
            assert c.get("/health").status_code == 200
    finally:
        app.dependency_overrides.clear()


def test_linear_16bit_tiff_and_png_uploads(client):
    """A linear 16-bit image (no RAW metadata) goes through the same path;
    the camera must then be named (or a generic one is used, with a warning)."""
    import cv2

    from testing.dngwriter import spectral_scene

    s = spectral_scene("Canon EOS 5D Mark II", "D65", 60, 90, seed=8)
    img16 = np.rint(np.clip(s.image, 0, 1) * 65535).astype(np.uint16)
    buf = io.BytesIO()
    tifffile.imwrite(buf, img16, photometric="rgb")
    r = client.post("/v1/analyze", files={"file": ("x.tif", buf.getvalue())},
                    data={"camera": "Canon EOS 5D Mark II", "method": "white-patch"})
    assert r.status_code == 200, r.text
    assert r.json()["camera"]["source"] == "measured"
    assert angular_error(r.json()["illuminant"]["camera_rgb"], s.light_rgb) < 2.0
    png = cv2.imencode(".png", np.ascontiguousarray(img16[..., ::-1]))[1].tobytes()
    r = client.post("/v1/analyze", files={"file": ("x.png", png)})
    assert r.status_code == 200, r.text
    assert r.json()["camera"]["source"] == "generic" and any("generic" in w for w in r.json()["warnings"])
    wb = client.post("/v1/white-balance", files={"file": ("x.png", png)}, data={"format": "png"})
    assert wb.status_code == 200 and wb.headers["content-type"] == "image/png"


def test_quality_and_model_order_options(client, good_dng):
    for q in ("fast", "balanced", "accurate"):
        r = _post(client, "/v1/analyze", good_dng, quality=q)
        assert r.status_code == 200, r.text
        assert r.json()["diagnostics"]["quality"] == q
    r = _post(client, "/v1/analyze", good_dng, quality="best")
    assert r.status_code == 422 and "balanced" in r.json()["detail"]
    r = _post(client, "/v1/analyze", good_dng, method="maloney-wandell", surface_dim="auto", light_dim="auto")
    assert r.status_code == 200, r.text
    d = r.json()["diagnostics"]
    assert isinstance(d["model_order"], dict) and d["D(S)"] in (1, 2)
