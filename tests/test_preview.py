"""``POST /v1/preview``: the original with the file's camera white balance and
the corrected image, downsized for the web page."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import app
from testing.dngwriter import scene_dng


@pytest.fixture(scope="module")
def client():
    return TestClient(app)


def _decode(body: bytes) -> np.ndarray:
    import cv2

    img = cv2.imdecode(np.frombuffer(body, np.uint8), cv2.IMREAD_UNCHANGED)
    assert img is not None, "the preview is not a decodable image"
    return img[..., ::-1].astype(float)


def _dng(illuminant: str, camera="Nikon 5100 (NPL)", seed=1, **kw):
    buf = io.BytesIO()
    truth = scene_dng(buf, camera, illuminant, 120, 180, seed=seed, **kw)
    return buf.getvalue(), truth


def _patch_means(img: np.ndarray, labels: np.ndarray, names, margin: int = 1) -> dict:
    """Mean colour of each patch's interior in ``img`` (any size: the label
    map's boxes are scaled to it and shrunk by ``margin`` pixels so no edge
    pixel, mixed by demosaicking or resampling, is included)."""
    H, W = labels.shape
    h, w = img.shape[:2]
    out = {}
    for k, name in enumerate(names):
        rr, cc = np.nonzero(labels == k)
        if not len(rr) or name.startswith("frame"):   # the frame is a thin border: no interior
            continue
        r0, r1 = int(np.ceil(rr.min() * h / H)) + margin, int((rr.max() + 1) * h / H) - margin
        c0, c1 = int(np.ceil(cc.min() * w / W)) + margin, int((cc.max() + 1) * w / W) - margin
        assert r1 - r0 >= 3 and c1 - c0 >= 3, name
        out[name] = img[r0:r1, c0:c1].reshape(-1, 3).mean(axis=0)
    return out


def test_camera_preview_uses_the_files_as_shot_white_balance(client):
    # An illuminant-A scene whose as-shot neutral is the truth: LibRaw's
    # rendering balances it, so the ColorChecker's neutral patches come out
    # grey. Those patches are not perfectly flat spectrally (chroma of about
    # 1 CIELAB unit), i.e. 1-2 sRGB codes at mid grey, and 8-bit rounding
    # adds 0.5: 4 codes of spread allowed.
    data, truth = _dng("A", as_shot_neutral="truth")
    r = client.post("/v1/preview", files={"file": ("a.dng", data)}, data={"wb": "camera", "format": "png"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "image/png"
    info = json.loads(r.headers["X-Preview"])
    assert info["wb"] == "camera" and info["warnings"] == []
    # LibRaw's camera multipliers are 1 / AsShotNeutral (stored as float32)
    expected = (1 / truth.as_shot_neutral) / (1 / truth.as_shot_neutral[1])
    np.testing.assert_allclose(info["camera_multipliers"], expected, rtol=1e-5)
    img = _decode(r.content)
    # LibRaw's half-size rendering: one pixel per 2x2 CFA cell
    assert img.shape == (60, 90, 3) and (info["width"], info["height"]) == (90, 60)
    assert (info["full_width"], info["full_height"]) == (180, 120)
    means = _patch_means(img, truth.labels, truth.patch_names)
    greys = [n for n in means if "neutral" in n]
    assert len(greys) == 4
    for n in greys:
        assert np.ptp(means[n]) <= 4.0, (n, means[n])

    # the same scene with a D65 as-shot balance: the A light shows through,
    # strongly warm (the camera's R/B ratio under A is over twice that under
    # D65 for this sensor, so R/B of a grey is far above 1.5)
    data, truth = _dng("A", as_shot_neutral="D65")
    r = client.post("/v1/preview", files={"file": ("a.dng", data)}, data={"wb": "camera", "format": "png"})
    means = _patch_means(_decode(r.content), truth.labels, truth.patch_names)
    for n in ("colorchecker neutral 5 (.70 D)", "colorchecker neutral 3.5 (1.05 D)"):
        assert means[n][0] / means[n][2] > 1.5, (n, means[n])


def test_corrected_preview_matches_white_balance_output(client):
    # The preview applies /v1/white-balance's 3x3 matrix to the binned
    # half-size image instead of the demosaicked full-size one. On a patch's
    # interior both see the same surface: the means differ only by noise
    # (1 % per pixel, averaged over >= 80 pixels: < 0.2 %, i.e. < 0.5 code)
    # and 8-bit rounding of each pixel (averages out): 1 code allowed.
    # quality=fast on both: the full image's demosaic is then the linear
    # bilinear one, whose patch interiors are the binned means' (the default
    # RCD is nonlinear: in the yellow patch's blue, a few per cent of a dark
    # channel under 1 % noise, it moves the 8-bit mean by 2 codes)
    data, truth = _dng("D4000", camera="Canon EOS 5D Mark II", seed=3)
    opts = {"method": "gray-world", "target": "D65", "quality": "fast"}
    r = client.post("/v1/preview", files={"file": ("c.dng", data)}, data=dict(opts, wb="corrected", format="png"))
    assert r.status_code == 200, r.text
    info = json.loads(r.headers["X-Preview"])
    assert info["wb"] == "corrected" and info["method"] == "gray-world" and info["target"] == "D65"
    full = client.post("/v1/white-balance", files={"file": ("c.dng", data)}, data=dict(opts, format="png"))
    assert full.status_code == 200, full.text
    np.testing.assert_allclose(info["correction_matrix"],
                               json.loads(full.headers["X-Illuminant"])["correction_matrix"], rtol=1e-12)
    small, big = _decode(r.content), _decode(full.content)
    assert small.shape == (60, 90, 3) and big.shape == (120, 180, 3)
    ms = _patch_means(small, truth.labels, truth.patch_names)
    mb = _patch_means(big, truth.labels, truth.patch_names, margin=2)
    assert len(ms) == 24
    for n in ms:
        np.testing.assert_allclose(ms[n], mb[n], atol=1.0, err_msg=n)


def test_preview_is_downsized_to_max_side_keeping_the_aspect(client):
    data, _ = _dng("D65")
    for wb in ("camera", "corrected"):
        r = client.post("/v1/preview", files={"file": ("a.dng", data)},
                        data={"wb": wb, "max_side": "40", "method": "gray-world"})
        assert r.status_code == 200, r.text
        assert r.headers["content-type"] == "image/jpeg"
        img = _decode(r.content)
        # 3:2 image, longest side 40: 40 x 27 (rounded)
        assert img.shape[:2] == (27, 40), (wb, img.shape)
        info = json.loads(r.headers["X-Preview"])
        assert (info["width"], info["height"]) == (40, 27)
        assert np.all(np.isfinite(img))


def test_linear_tiff_preview_says_it_has_no_camera_white_balance(client):
    import tifffile

    rng = np.random.default_rng(0)
    img = (rng.uniform(0.1, 0.8, (40, 60, 3)) * 65535).astype(np.uint16)
    buf = io.BytesIO()
    tifffile.imwrite(buf, img, photometric="rgb")
    r = client.post("/v1/preview", files={"file": ("lin.tif", buf.getvalue())}, data={"format": "png"})
    assert r.status_code == 200, r.text
    info = json.loads(r.headers["X-Preview"])
    assert any("no camera white balance" in w for w in info["warnings"])
    out = _decode(r.content)
    assert out.shape == (40, 60, 3)
    # unbalanced: the sRGB encoding of the linear values (8-bit rounding,
    # plus the 16-bit linear step of the shared LUT: 1 code)
    import colour

    expected = np.asarray(colour.RGB_COLOURSPACES["sRGB"].cctf_encoding(img / 65535.0)) * 255
    np.testing.assert_allclose(out, expected, atol=1.0)


@pytest.mark.parametrize("fields, status, code, word", [
    ({"wb": "auto"}, 422, "invalid_parameter", "wb"),
    ({"max_side": "8"}, 422, "invalid_parameter", "max_side"),
    ({"max_side": "99999"}, 422, "invalid_parameter", "max_side"),
    ({"max_side": "big"}, 422, "invalid_parameter", "max_side"),
    ({"format": "gif"}, 422, "invalid_parameter", "format"),
    ({"output": "CMYK"}, 422, "invalid_parameter", "output"),
    ({"wb": "corrected", "method": "magic"}, 422, "invalid_parameter", "method"),
])
def test_bad_options_are_named(client, fields, status, code, word):
    data, _ = _dng("D65")
    r = client.post("/v1/preview", files={"file": ("a.dng", data)}, data=fields)
    assert r.status_code == status, r.text
    body = r.json()
    assert body["error"] == code and word in body["detail"]


@pytest.mark.parametrize("wb", ["camera", "corrected"])
def test_bad_upload_is_a_4xx_with_words(client, wb):
    r = client.post("/v1/preview", files={"file": ("notes.txt", b"just some text\n")}, data={"wb": wb})
    assert r.status_code == 415
    body = r.json()
    assert body["error"] == "unsupported_format" and "notes.txt" in body["detail"]
    data, _ = _dng("D65")
    r = client.post("/v1/preview", files={"file": ("cut.dng", data[: len(data) // 3])}, data={"wb": wb})
    assert 400 <= r.status_code < 500 and r.json()["error"] == "corrupt_file", r.text


def test_preview_is_in_the_openapi_schema(client):
    spec = client.get("/openapi.json").json()
    op = spec["paths"]["/v1/preview"]["post"]
    assert set(op["responses"]["200"]["content"]) >= {"image/jpeg", "image/png"}
    form = next(iter(op["requestBody"]["content"].values()))["schema"]
    ref = form["$ref"].rsplit("/", 1)[-1]
    props = spec["components"]["schemas"][ref]["properties"]
    assert {"file", "wb", "max_side", "format", "target"} <= set(props)
    assert "as-shot white balance" in props["wb"]["description"]
