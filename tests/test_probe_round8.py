"""Round 8 of probing (docs/probe_round8.md): each test is the minimal
reproduction of one fault found, through the Python API, the command line as
users run it (``python -m service.cli``) or the real ASGI stack (FastAPI's
TestClient), and holds once the fault is fixed."""

from __future__ import annotations

import json
import os

import numpy as np
import pytest

from recovery import Camera, InputError, analyze, estimate_illuminant

from .conftest import run_cli as _cli
from .conftest import scene_dng_bytes


@pytest.fixture(scope="module")
def dng() -> bytes:
    return scene_dng_bytes(64, 96)



# --- 1. cameras the shipped spectra cannot model ---------------------------------------------

def _nikon() -> Camera:
    return Camera.named("Nikon 5100 (NPL)")


@pytest.mark.parametrize("make", [
    lambda c: (c.wavelengths + 480, c.sensitivities),                      # 880-1180 nm, infrared
    lambda c: (c.wavelengths - 320, c.sensitivities),                      # 80-380 nm: one wavelength inside
    lambda c: (np.array([500.0, 600.0]), c.sensitivities[[10, 20]]),       # 2 wavelengths, 3 channels
    lambda c: (np.arange(380.0, 1001.0, 10.0),                             # a channel seeing only > 800 nm
               np.c_[np.ones(63), np.ones(63), (np.arange(380.0, 1001.0, 10.0) > 800).astype(float)]),
], ids=["880-1180nm", "80-380nm", "two-wavelengths", "infrared-channel"])
def test_a_camera_outside_the_measured_spectra_is_an_input_error_naming_it(make):
    """A camera on 880-1200 nm made ``auto``/``bayes``/``learned`` raise a
    bare ValueError ("candidate spectra and prior must be finite": the
    narrow-band candidate lights underflow there), one of two wavelengths a
    bare ValueError from the surface model's PCA ("dimension must be in
    1..2, not 3") on every method. The lights and surfaces are measured on
    380-780 nm: the camera is refused where it is made, naming the rule."""
    with pytest.raises(InputError, match=r"380-780 nm|at least 3 wavelengths"):
        Camera(*make(_nikon()))


def test_a_camera_reaching_past_the_measured_spectra_still_analyses():
    """What stays accepted: a camera whose grid reaches beyond 380-780 nm but
    sees at least C wavelengths inside it, on every method."""
    from .test_probe_pyapi import mondrian

    nik = _nikon()
    img = mondrian(nik)
    wl = np.arange(300.0, 1101.0, 10.0)
    sens = np.exp(-0.5 * ((wl[:, None] - np.array([450.0, 550.0, 650.0])) / 40.0) ** 2) + 1e-3
    for cam in (Camera(wl, sens), Camera(np.array([450.0, 550.0, 650.0]), np.eye(3) + 0.1)):
        for method in ("auto", "bayes", "gray-world"):
            est = estimate_illuminant(img, cam, method)
            assert np.all(np.isfinite(est.rgb)) and np.all(np.isfinite(est.spectrum)), (cam.wavelengths, method)
        res = analyze(img, cam, "gray-world")
        assert np.all(np.isfinite(res.reflectance([(1, 2)])))


# --- 3. wandell batch: files already in OUT_DIR ----------------------------------------------

def test_batch_keeps_a_read_only_output_even_with_force_and_says_so(tmp_path, dng):
    """``wandell batch IN OUT --force`` replaced an output the user had made
    read-only (``chmod a-w``; the new file even came back writable), exit 0
    and "2 done" (round 7 made ``white-balance`` keep one). It is kept, its
    item fails ``output_read_only`` saying what to do (exit 1); without
    ``--force`` a finished read-only output is simply skipped."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    for name in ("a.dng", "b.dng"):
        (src / name).write_bytes(dng)
    args = ("batch", "--workers", "1", "--format", "png", str(src), str(out))
    assert _cli(*args).returncode == 0
    kept = out / "a.png"
    before = kept.read_bytes()
    kept.chmod(0o444)
    r = _cli(*args[:-2], "--force", *args[-2:])
    assert r.returncode == 1, (r.returncode, r.stdout, r.stderr)
    assert "output_read_only" in r.stdout and "1 done" in r.stdout and "1 failed" in r.stdout, r.stdout
    assert kept.read_bytes() == before and not os.stat(kept).st_mode & 0o222, "the read-only output was replaced"
    r = _cli(*args)
    assert r.returncode == 0 and "2 skipped" in r.stdout, (r.stdout, r.stderr)


def test_batch_keeps_a_file_of_the_users_own_that_has_an_outputs_name(tmp_path, dng):
    """A picture of the user's own in OUT_DIR named like an output
    (``a.png`` for ``a.dng``; no record of a batch in ``.wandell``) was
    replaced without ``--force`` and without a word, exit 0: lost. It is
    kept and its item fails ``output_exists`` naming ``--force``; with
    ``--force`` it is replaced, as that flag now says."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    out.mkdir()
    (src / "a.dng").write_bytes(dng)
    (out / "a.png").write_bytes(b"the user's own picture")
    args = ("batch", "--workers", "1", "--format", "png", str(src), str(out))
    r = _cli(*args)
    assert r.returncode == 1 and "output_exists" in r.stdout and "--force" in r.stdout, (r.stdout, r.stderr)
    assert (out / "a.png").read_bytes() == b"the user's own picture"
    r = _cli(*args[:-2], "--force", *args[-2:])
    assert r.returncode == 0 and (out / "a.png").read_bytes()[:4] == b"\x89PNG", (r.stdout, r.stderr)


# --- 4. /v1/surfaces and quality -------------------------------------------------------------

@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from .conftest import isolated_app_client

    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")


@pytest.mark.parametrize("quality", ["fast", "balanced", "accurate"])
def test_surfaces_take_quality_and_answer_the_light_analyze_answers(client, dng, quality):
    """``/v1/analyze`` takes ``quality`` (the analysis resolution of the
    light), ``/v1/surfaces`` refused it (422 ``unknown_field``), so the page
    dropped it there: with "fast" chosen the picture was corrected under one
    light and "read a surface" estimated the surface under another, while
    saying "under Auto's light". Now the same fields give the same light."""
    f = {"quality": quality}
    a = client.post("/v1/analyze", files={"file": ("a.dng", dng)}, data=f)
    s = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data={"points": "[[10, 10]]", **f})
    assert a.status_code == 200 and s.status_code == 200, (a.text[:300], s.text[:300])
    assert s.json()["illuminant"]["camera_rgb"] == a.json()["illuminant"]["camera_rgb"]
    bad = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data={"points": "[[1, 1]]", "quality": "x"})
    assert bad.status_code == 422 and "quality" in bad.json()["detail"], bad.text


# --- 5. the flag in the X-Illuminant header and the XMP ---------------------------------------

@pytest.mark.parametrize("method", ["auto", "maloney-wandell"])
def test_the_x_illuminant_header_and_the_xmp_carry_the_low_confidence_flag(client, dng, method):
    """The JSON answer's ``diagnostics`` carry ``confidence`` and
    ``low_confidence``; the corrected image's ``X-Illuminant`` header carried
    neither, the XMP sidecar (``format=xmp``) and the XMP inside the image
    the confidence but not the flag: a photographer batch-processing with
    headers or sidecars could not pick out the doubtful ones. Both now carry
    the flag the JSON gives (``maloney-wandell`` is always flagged: it has no
    calibration on real photographs)."""
    from service.outputs import read_wandell_xmp

    f = {"method": method}
    js = client.post("/v1/white-balance", files={"file": ("a.dng", dng)}, data={**f, "response": "json"}).json()
    want = {k: js["diagnostics"][k] for k in ("confidence", "low_confidence")}
    assert want["low_confidence"] is (method == "maloney-wandell")
    img = client.post("/v1/white-balance", files={"file": ("a.dng", dng)}, data={**f, "format": "png"})
    head = json.loads(img.headers["X-Illuminant"])
    assert {k: head.get(k) for k in want} == want, head
    xmp = client.post("/v1/white-balance", files={"file": ("a.dng", dng)}, data={**f, "format": "xmp"})
    assert {k: json.loads(xmp.headers["X-Illuminant"]).get(k) for k in want} == want
    props = read_wandell_xmp(xmp.text)
    assert props["LowConfidence"] is want["low_confidence"] and props["Confidence"] == want["confidence"], props


def test_a_white_the_user_set_carries_no_confidence_in_the_header(client, dng):
    """A white the user set (as-shot, a temperature/tint, a picked neutral)
    has no confidence in the JSON answer, so none in the header either."""
    for f in ({"white": "as-shot"}, {"white": "5000/+10"}, {"neutral": "[10, 10]"}):
        img = client.post("/v1/white-balance", files={"file": ("a.dng", dng)}, data={**f, "format": "png"})
        head = json.loads(img.headers["X-Illuminant"])
        assert img.status_code == 200 and "confidence" not in head and "low_confidence" not in head, (f, head)


# --- long upload names: the download keeps its extension --------------------------------------

@pytest.mark.parametrize("stem", ["w" * 300, "日" * 200], ids=["ascii", "utf8"])
def test_a_long_names_download_keeps_its_extension(client, dng, stem):
    """``Content-Disposition`` names are cut to 200 characters; the cut took
    the extension: the XMP sidecar of a RAW with a long name downloaded as
    ``www...w`` (no ``.xmp``; the page's "Download XMP sidecar" saves it
    so), in both ``filename`` and ``filename*``."""
    from urllib.parse import unquote

    r = client.post("/v1/white-balance", files={"file": (stem + ".dng", dng)}, data={"format": "xmp"})
    assert r.status_code == 200, r.text[:300]
    cd = r.headers["content-disposition"]
    plain = cd.split('filename="', 1)[1].split('"', 1)[0]
    assert plain.endswith(".xmp") and len(plain) <= 200, cd
    if "filename*=" in cd:
        full = unquote(cd.split("filename*=UTF-8''", 1)[1])
        assert full.endswith(".xmp") and full.startswith(stem[:50]) and len(full) <= 200, full


# --- a file name at the file system's limit (255 bytes) ---------------------------------------

def test_a_raw_with_a_255_byte_name_is_corrected_by_batch_and_white_balance(tmp_path, dng):
    """A RAW named with 255 bytes (NAME_MAX) is a valid file, but ``wandell
    batch`` failed it with ``OSError: [Errno 36] File name too long:
    '.wandell/NAME.jpg.lock'`` (its records add to the output's name), and
    ``wandell white-balance RAW OUT`` with a 255-byte OUT with ``[Errno 36]``
    on its temporary ``.OUT.XXXXXXXX.part``. The batch's output name is now
    cut as the server's batches cut theirs (extension kept, so its records
    fit), and a temporary's name is cut when it would not fit."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    stem = "y" * 251
    (src / f"{stem}.dng").write_bytes(dng)
    args = ("batch", "--workers", "1", "--format", "jpeg", str(src), str(out))
    r = _cli(*args)
    assert r.returncode == 0 and "1 done" in r.stdout, (r.stdout[-600:], r.stderr[-600:])
    made = [p.name for p in out.iterdir() if p.suffix == ".jpg"]
    assert len(made) == 1 and made[0].startswith(stem[:100]) and len(made[0].encode()) <= 200, made
    r = _cli(*args)
    assert r.returncode == 0 and "1 skipped" in r.stdout, r.stdout[-600:]
    one = tmp_path / f"{stem}.tif"          # 255 bytes
    r = _cli("white-balance", str(src / f"{stem}.dng"), str(one))
    assert r.returncode == 0 and one.read_bytes()[:2] in (b"II", b"MM"), (r.stdout[-600:], r.stderr[-600:])
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]


# --- the camera's own preview of a DNG LibRaw cannot render ------------------------------------

@pytest.mark.parametrize("kind", ["uint32", "deflate-predictor"])
def test_the_camera_preview_of_a_dng_the_service_reads_is_not_called_damaged(client, kind):
    """A LinearRaw DNG of 32-bit integers, or deflate with a predictor, is
    read by every endpoint (the service decodes it itself), but the page's
    first picture, ``/v1/preview`` with ``wb=camera`` (LibRaw's own
    rendering), was a 422 ``corrupt_file`` "LibRaw could not render the file
    ...; it is damaged". It is now the file's as-shot white through the
    service's own rendering (what ``/v1/white-balance white=as-shot``
    writes), with a warning saying so."""
    import io as _io

    from testing.dngwriter import write_linear_dng

    rgb = np.random.default_rng(0).uniform(0.05, 0.9, (48, 64, 3))
    buf = _io.BytesIO()
    if kind == "uint32":
        write_linear_dng(buf, (rgb * 4e9).astype(np.uint32))
    else:
        write_linear_dng(buf, (rgb * 65535).astype(np.uint16), compression="deflate", predictor=True)
    data = buf.getvalue()
    assert client.post("/v1/analyze", files={"file": ("a.dng", data)}).status_code == 200
    r = client.post("/v1/preview", files={"file": ("a.dng", data)})
    assert r.status_code == 200 and r.headers["content-type"] == "image/jpeg", r.text[:300]
    info = json.loads(r.headers["X-Preview"])
    assert info["wb"] == "camera" and (info["width"], info["height"]) == (64, 48), info
    assert any("LibRaw cannot render" in w and "as-shot" in w for w in info["warnings"]), info


# --------------------------------------------------------------------------- item 2: points in the Python API
@pytest.fixture(scope="module")
def mondrian_result():
    from .test_probe_pyapi import mondrian

    cam = Camera.named("Nikon 5100 (NPL)")
    return analyze(mondrian(cam), cam, "gray-world")


@pytest.mark.parametrize("points", [[(True, False)], np.array([[True, True]])])
def test_boolean_points_are_an_input_error(mondrian_result, points):
    """A boolean (a mask passed by mistake) was read as pixel (1, 0)."""
    for fn in (mondrian_result.reflectance, mondrian_result.surface_estimates, mondrian_result.surface_weights):
        with pytest.raises(InputError, match="booleans"):
            fn(points)


def test_many_points_in_one_call_are_taken_in_chunks_with_each_points_own_answer():
    """200,000 points in one call took 1.4 GB (probe round 8 found no bound on them); they are now estimated
    SURFACE_CHUNK at a time. Each point's posterior is its own (the exposure is the scene's), so points on
    both sides of a chunk's edge must answer exactly what they answer asked alone."""
    from recovery import Camera, analyze
    from recovery.api import SURFACE_CHUNK

    from .test_probe_pyapi import mondrian

    cam = Camera.named("Nikon 5100 (NPL)")
    res = analyze(mondrian(cam, size=128), cam, "gray-world")
    pts = np.argwhere(np.ones((128, 128), bool))[: SURFACE_CHUNK + 10]
    many = res.surface_estimates(pts)
    assert many.mean.shape == (SURFACE_CHUNK + 10, 31) and many.std.shape == many.mean.shape
    edge = pts[SURFACE_CHUNK - 3: SURFACE_CHUNK + 3]
    alone = res.surface_estimates(edge)
    np.testing.assert_allclose(many.mean[SURFACE_CHUNK - 3: SURFACE_CHUNK + 3], alone.mean, rtol=0, atol=1e-12)
    np.testing.assert_allclose(many.std[SURFACE_CHUNK - 3: SURFACE_CHUNK + 3], alone.std, rtol=0, atol=1e-12)
    assert many.typicality is None or many.typicality.shape == (SURFACE_CHUNK + 10,)
