"""Issue 29, item 2: the public loader (``service.loader.load``) reads a RAW
or a linear TIFF/PNG into exactly what the service analyses, so the Python
API and the REST API give the same light for the same file. The real
CinemaDNG and NEF of ``../shared/data/raw``, the real app (TestClient)."""

from __future__ import annotations

import io
import subprocess
import sys

import numpy as np
import pytest
from fastapi.testclient import TestClient

from recovery import estimate_illuminant
from service.loader import ORIENTATIONS, Photo, load

from .conftest import shared_file

#: Same code, same arrays, same order of operations: the two roads agree to
#: the last bits of double rounding (a normalised 3-vector).
SAME = 1e-12


@pytest.fixture(scope="module")
def client():
    from service.app import app

    with TestClient(app) as c:
        yield c


@pytest.mark.parametrize("raw,options", [("Blackmagic.dng", {}), ("Blackmagic.dng", {"quality": "fast"}),
                                         ("Blackmagic.dng", {"method": "gray-world"}),
                                         ("Blackmagic.dng", {"camera": "generic"})])
def test_python_and_rest_give_the_same_light(client, raw, options):
    path = shared_file(f"data/raw/{raw}")
    photo = load(path, quality=options.get("quality"), camera=options.get("camera"))
    assert isinstance(photo, Photo) and photo.kind == "raw"
    est = estimate_illuminant(photo.linear, photo.camera, options.get("method", "auto"), mask=photo.mask,
                              quality=options.get("quality"))
    r = client.post("/v1/analyze", files={"file": (raw, path.read_bytes())}, data=options)
    assert r.status_code == 200, r.text
    rest = r.json()
    assert est.method == rest["method"]
    np.testing.assert_allclose(est.rgb, rest["illuminant"]["camera_rgb"], rtol=0, atol=SAME)
    assert photo.camera.name == rest["camera"]["name"] and photo.camera.source == rest["camera"]["source"]
    assert photo.linear.shape[0] * photo.linear.shape[1] == rest["diagnostics"]["pixels_total"]
    assert photo.block_factor == rest["diagnostics"]["analysis_block_factor"]
    assert list(photo.full_shape) == [rest["image"]["height"], rest["image"]["width"]]
    asn = photo.as_shot / np.linalg.norm(photo.as_shot)
    np.testing.assert_allclose(asn, rest["as_shot"]["camera_rgb"], rtol=0, atol=SAME)
    assert photo.orientation in ORIENTATIONS
    assert photo.mask.shape == photo.linear.shape[:2] and photo.mask.dtype == bool


def test_what_the_cinemadng_says_about_itself():
    photo = load(shared_file("data/raw/Blackmagic.dng"))
    assert "Blackmagic" in photo.model      # the DNG has no Make tag, its model names the camera
    assert photo.camera.source == "matrix-derived" and photo.camera_warnings
    assert photo.full_shape == (2176, 4128) and photo.orientation == 0
    assert photo.linear.dtype == np.float32 and np.isfinite(photo.linear).all()
    # 1.0 is saturation: the unsaturated pixels stay below it, the masked ones hold the clipped cells
    assert photo.linear[photo.mask].max() < 1.0 and 0 < photo.mask.mean() <= 1
    assert photo.as_shot[1] == pytest.approx(1.0)


def test_a_linear_tiff_from_bytes_and_camera_choice(client):
    import tifffile

    rng = np.random.default_rng(3)
    img = (rng.uniform(0.05, 0.8, (64, 96, 3)) * np.array([0.5, 1.0, 0.7]) * 65535).astype(np.uint16)
    buf = io.BytesIO()
    tifffile.imwrite(buf, img, photometric="rgb")
    data = buf.getvalue()
    photo = load(data, name="scene.tif", camera="Nikon 5100 (NPL)")
    assert photo.kind == "tiff" and photo.as_shot is None and photo.camera.source == "measured"
    np.testing.assert_allclose(photo.linear, img / 65535.0, rtol=0, atol=1e-6)
    est = estimate_illuminant(photo.linear, photo.camera, mask=photo.mask)
    r = client.post("/v1/analyze", files={"file": ("scene.tif", data)}, data={"camera": "Nikon 5100 (NPL)"})
    assert r.status_code == 200, r.text
    np.testing.assert_allclose(est.rgb, r.json()["illuminant"]["camera_rgb"], rtol=0, atol=SAME)


def test_bad_input_is_the_rest_apis_error(client, tmp_path):
    """The same refusal as over REST: a film scanner's NEF (the real one of
    ../shared) and a text file named .dng."""
    from service.errors import ServiceError

    p = tmp_path / "notes.dng"
    p.write_text("not an image")
    nef = shared_file("data/raw/Nikon_uncompressed.nef")
    for path in (p, nef):
        with pytest.raises(ServiceError) as e:
            load(path)
        r = client.post("/v1/analyze", files={"file": (path.name, path.read_bytes())})
        assert (e.value.status, e.value.code) == (r.status_code, r.json()["error"]), r.text


def test_the_loader_needs_no_web_stack():
    code = ("import sys; from service.loader import load; "
            "print(sorted(m for m in ('fastapi', 'starlette', 'uvicorn') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stderr
