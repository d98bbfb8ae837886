"""Issue 13, item 3: outputs other tools read (ICC profile, EXIF, the
estimate) and the Camera Raw XMP sidecar; the as-shot rendering download."""

from __future__ import annotations

import io
import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from service import outputs, pipeline

from .test_dng_render import real_file

PIL = pytest.importorskip("PIL")
from PIL import Image, ImageCms  # noqa: E402


@pytest.mark.parametrize("output", sorted(outputs.ICC_SPACES))
def test_shipped_icc_profiles_are_the_generated_ones(output):
    assert outputs.shipped_icc(output) == outputs.icc_profile(output)


def test_icc_profiles_map_colours_like_littlecms_srgb():
    lab = ImageCms.createProfile("LAB")
    rng = np.random.default_rng(0)
    im = Image.fromarray(rng.integers(0, 256, (16, 16, 3), dtype=np.uint8))

    def to_lab(profile):
        t = ImageCms.buildTransform(profile, lab, "RGB", "LAB", renderingIntent=1)
        return np.asarray(ImageCms.applyTransform(im, t)).astype(int)

    ours = ImageCms.ImageCmsProfile(io.BytesIO(outputs.shipped_icc("sRGB")))
    assert np.abs(to_lab(ours) - to_lab(ImageCms.createProfile("sRGB"))).max() <= 1

    def via(name, rgb):
        t = ImageCms.buildTransform(ImageCms.createProfile("sRGB"),
                                    ImageCms.ImageCmsProfile(io.BytesIO(outputs.shipped_icc(name))),
                                    "RGB", "RGB", renderingIntent=1)
        return ImageCms.applyTransform(Image.new("RGB", (1, 1), rgb), t).getpixel((0, 0))

    assert np.allclose(via("Display P3", (255, 0, 0)), (234, 51, 35), atol=1)    # sRGB red inside P3
    assert np.allclose(via("linear-sRGB", (128, 128, 128)), (55, 55, 55), atol=1)


FACTS = {"Make": "Nikon", "Model": "D800", "Orientation": 6, "ExposureTime": (1, 250), "FNumber": 5.6,
         "ISOSpeedRatings": 400, "DateTimeOriginal": "2024:05:01 10:00:00"}


@pytest.mark.parametrize("fmt,bits", [("png", 8), ("png", 16), ("jpeg", 8), ("tiff", 16)])
def test_outputs_carry_icc_exif_and_the_estimate(fmt, bits, tmp_path):
    img = np.full((8, 12, 3), 200 if bits == 8 else 50000, np.uint8 if bits == 8 else np.uint16)
    est = {"method": "bayes", "camera_rgb": [0.4, 0.8, 0.4], "xy": [0.3457, 0.3585], "cct": 5003.0,
           "duv": 0.0032, "confidence": 0.8}
    facts = outputs.output_facts(FACTS, est)
    meta = {"icc": outputs.shipped_icc("Display P3"), "facts": facts,
            "text": {"wandell:estimate": json.dumps(est), outputs.XMP_KEY: facts["XMP"]}}
    path = tmp_path / f"x.{fmt}"
    pipeline.encode_image(img, fmt, str(path), meta=meta)
    if fmt == "tiff":
        import tifffile

        with tifffile.TiffFile(path) as tf:
            tags = tf.pages[0].tags
            assert tags[34675].value == meta["icc"]
            assert tags[271].value == "Nikon" and tags[272].value == "D800"
            assert tags[274].value == 1                               # orientation applied once
            assert 270 not in tags                                    # no caption: the estimate is in the XMP
            _check_wandell_xmp(bytes(tags[700].value), est)
            assert np.array_equal(tf.asarray(), img)
        _exiftool_agrees(path, est)
        return
    with Image.open(path) as im:
        assert im.info["icc_profile"] == meta["icc"]
        exif = im.getexif()
        assert exif[271] == "Nikon" and exif[272] == "D800" and exif[274] == 1
        assert 270 not in exif                                        # no caption: the estimate is in the XMP
        sub = exif.get_ifd(0x8769)
        assert float(sub[33434]) == pytest.approx(1 / 250) and float(sub[33437]) == pytest.approx(5.6)
        assert sub[34855] == 400 and sub[36867] == "2024:05:01 10:00:00"
        packet = im.info.get(outputs.XMP_KEY) if fmt == "png" else im.info.get("xmp")
    _check_wandell_xmp(packet, est)
    _exiftool_agrees(path, est)
    if fmt == "png":
        import cv2

        back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)[..., ::-1]
        assert np.array_equal(back, img)                            # pixels untouched by the chunks


def _check_wandell_xmp(packet, est):
    """The XMP packet of an output carries the estimate as ``wandell:`` fields."""
    assert packet, "no XMP packet"
    got = outputs.read_wandell_xmp(packet)
    assert got["Method"] == "bayes" and got["CameraRGB"] == est["camera_rgb"] and got["LightXY"] == est["xy"]
    assert got["CCT"] == est["cct"] and got["Duv"] == est["duv"] and got["Confidence"] == est["confidence"]
    assert got["Estimate"] == est


def _exiftool_agrees(path, est, description=None):
    """exiftool (when installed) reads no ImageDescription but the source's,
    and the wandell: XMP fields (an unknown namespace: exiftool names them
    after the prefix)."""
    import shutil
    import subprocess

    if shutil.which("exiftool") is None:
        return
    out = json.loads(subprocess.run(["exiftool", "-j", "-G1", "-a", str(path)], capture_output=True, text=True,
                                    check=True).stdout)[0]
    descriptions = [v for k, v in out.items() if k.endswith(":ImageDescription") or k.endswith(":Description")]
    assert descriptions == ([description] * len(descriptions) if description else []), descriptions
    assert any(k.startswith("XMP-wandell:") for k in out), sorted(out)
    flat = {k.split(":", 1)[1].lower(): v for k, v in out.items() if k.startswith("XMP-wandell:")}
    assert flat.get("method") == "bayes" and float(flat["cct"]) == est["cct"], flat


def test_the_source_caption_is_kept_and_never_the_estimate(tmp_path):
    """A source ImageDescription stays the output's (ASCII in TIFF/EXIF, the
    whole text in dc:description); a blank one is dropped."""
    est = {"method": "bayes", "camera_rgb": [0.4, 0.8, 0.4], "xy": [0.31, 0.33], "cct": 6500.0, "duv": 0.0,
           "confidence": 0.5}
    assert "ImageDescription" not in outputs.output_facts({"ImageDescription": "   "}, est)
    facts = outputs.output_facts({"ImageDescription": "Lake Bled, José"}, est)
    assert facts["ImageDescription"] == "Lake Bled, José"
    assert "Lake Bled, José" in facts["XMP"] and "dc:description" in facts["XMP"]
    img = np.full((4, 6, 3), 120, np.uint8)
    for fmt in ("tiff", "jpeg", "png"):
        path = tmp_path / f"c.{fmt}"
        pipeline.encode_image(img if fmt != "tiff" else img.astype(np.uint16), fmt, str(path),
                              meta={"facts": facts, "text": {outputs.XMP_KEY: facts["XMP"]}})
        if fmt == "tiff":
            import tifffile

            with tifffile.TiffFile(path) as tf:
                assert tf.pages[0].tags[270].value == "Lake Bled, Jose"
        else:
            with Image.open(path) as im:
                assert im.getexif()[270] == "Lake Bled, Jose"
        _exiftool_agrees_caption(path)


def _exiftool_agrees_caption(path):
    import shutil
    import subprocess

    if shutil.which("exiftool") is None:
        return
    out = json.loads(subprocess.run(["exiftool", "-j", "-G1", "-a", str(path)], capture_output=True, text=True,
                                    check=True).stdout)[0]
    assert {v for k, v in out.items() if k.endswith("ImageDescription")} == {"Lake Bled, Jose"}, out
    assert out.get("XMP-dc:Description") == "Lake Bled, José"
    assert not any("wandell estimate" in str(v) for v in out.values())


def test_xmp_sidecar_is_camera_raw_settings():
    text = outputs.xmp_sidecar(5012.4, -7.6, {"method": "bayes"})
    root = ET.fromstring(text.split("?>", 1)[1].rsplit("<?xpacket", 1)[0])
    crs = "{http://ns.adobe.com/camera-raw-settings/1.0/}"
    d = root.find(".//{http://www.w3.org/1999/02/22-rdf-syntax-ns#}Description")
    assert d.get(crs + "WhiteBalance") == "Custom"
    assert d.get(crs + "Temperature") == "5012" and d.get(crs + "Tint") == "-8"
    assert outputs.read_wandell_xmp(text)["Method"] == "bayes"


@pytest.fixture(scope="module")
def client():
    from fastapi.testclient import TestClient

    from service.app import app

    with TestClient(app) as c:
        yield c


def test_xmp_of_the_as_shot_white_is_adobes_as_shot_temperature(client):
    """white=as-shot, format=xmp: the DNG's AsShotNeutral through its own
    matrices gives Adobe's as-shot Temperature/Tint (recomputed here by the
    module under test's inverse: the xy it reports maps back)."""
    from recovery.dng_color import temperature_tint_to_xy

    p = real_file("Blackmagic.dng")
    r = client.post("/v1/white-balance", files={"file": (p.name, p.read_bytes())},
                    data={"format": "xmp", "white": "as-shot"})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"].startswith("application/rdf+xml")
    h = json.loads(r.headers["x-illuminant"])
    assert h["basis"] == "DNG tags"
    assert 3900 < h["temperature"] < 4300 and 0 < h["tint"] < 15
    assert f'crs:Temperature="{round(h["temperature"])}"' in r.text
    xy = temperature_tint_to_xy(h["temperature"], h["tint"])
    assert np.all(np.isfinite(xy))


def test_as_shot_download_beside_the_corrected_one(client):
    p = real_file("Blackmagic.dng")
    data = p.read_bytes()
    shots = {}
    for white in ("estimate", "as-shot"):
        r = client.post("/v1/white-balance", files={"file": (p.name, data)},
                        data={"format": "jpeg", "white": white})
        assert r.status_code == 200, r.text
        h = json.loads(r.headers["x-illuminant"])
        assert h["white"] == white and h["rendering"]["rendering"] == "dng-matrix"
        assert ("as-shot" in r.headers["content-disposition"]) == (white == "as-shot")
        im = Image.open(io.BytesIO(r.content))
        assert im.size == (4096, 2160)                              # the DNG's DefaultCrop
        assert len(im.info["icc_profile"]) > 0
        shots[white] = np.asarray(im, float)
    # the estimate is within a degree of the as-shot white: the two pictures agree closely
    diff = np.abs(shots["estimate"].mean((0, 1)) - shots["as-shot"].mean((0, 1)))
    assert diff.max() < 12, diff


def _icc_tags(prof: bytes) -> dict:
    import struct

    n = struct.unpack(">I", prof[128:132])[0]
    out = {}
    for i in range(n):
        sig, off, size = struct.unpack(">4sII", prof[132 + 12 * i:144 + 12 * i])
        out[sig.decode()] = prof[off:off + size]
    return out


def _s15_xyz(tag: bytes) -> np.ndarray:
    import struct

    assert tag[:4] == b"XYZ "
    return np.array(struct.unpack(">3i", tag[8:20])) / 65536.0


@pytest.mark.parametrize("name", ["Typical CRT Brainard 1997", "Apple Studio Display"])
def test_spectral_display_profiles_are_their_guns_through_cie_1931(name):
    """The display's ICC profile: colorants = its guns' CIE 1931 XYZ
    (computed here from colour-science's spectra and observer on the 400..700
    nm / 10 nm grid, white Y = 1), adapted from the display white to D50 by
    Bradford, within s15Fixed16 rounding; the TRC the identity (the output
    holds linear gun intensities: no encoding); LittleCMS reads it."""
    colour = pytest.importorskip("colour")

    wl = np.arange(400.0, 701.0, 10.0)
    shape = colour.SpectralShape(400, 700, 10)
    guns = colour.MSDS_DISPLAY_PRIMARIES[name].copy().align(shape)
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    assert np.allclose(guns.wavelengths, wl) and np.allclose(cmfs.wavelengths, wl)
    G = np.clip(guns.values, 0, None).T @ cmfs.values * 10.0      # (3 guns, XYZ)
    G = G.T / G.sum(axis=0)[1]                                     # columns, white Y = 1
    w = G.sum(axis=1)
    cat = colour.adaptation.matrix_chromatic_adaptation_VonKries(w, colour.xy_to_XYZ([0.3457, 0.3585]),
                                                                  transform="Bradford")
    want = cat @ G
    prof = outputs.shipped_icc(name)
    assert prof == outputs.icc_profile(name)
    tags = _icc_tags(prof)
    got = np.stack([_s15_xyz(tags[t]) for t in ("rXYZ", "gXYZ", "bXYZ")], axis=1)
    assert np.abs(got - want).max() <= 2 / 65536, np.abs(got - want).max()
    # white -> D50 (xy 0.3457, 0.3585, as the shipped sRGB/P3 profiles; the PCS header's 4-digit XYZ within 3e-4)
    assert np.allclose(got.sum(axis=1), outputs.D50_XYZ, atol=3e-4)
    assert tags["rTRC"] == tags["gTRC"] == tags["bTRC"] == b"curv" + b"\0" * 8     # count 0: gamma 1.0
    # LittleCMS: full red of the display -> its D50-adapted XYZ column
    p = ImageCms.ImageCmsProfile(io.BytesIO(prof))
    assert name.split(",")[0] in ImageCms.getProfileDescription(p)
    lab = ImageCms.createProfile("LAB")
    t = ImageCms.buildTransform(p, lab, "RGB", "LAB", renderingIntent=1)
    white = ImageCms.applyTransform(Image.new("RGB", (1, 1), (255, 255, 255)), t).getpixel((0, 0))
    assert white[0] >= 254 and abs(white[1] - 128) <= 1 and abs(white[2] - 128) <= 1     # media-relative white


def test_display_outputs_carry_their_profile(client):
    """A white-balanced image for the Typical CRT carries that display's
    profile (its values are linear gun intensities: the pipeline encodes
    nothing for a spectral display)."""
    from recovery.synthesis import output_space

    name = "Typical CRT Brainard 1997"
    assert output_space(name, np.arange(400.0, 701.0, 10.0)).encoding is None
    p = real_file("Blackmagic.dng")
    r = client.post("/v1/white-balance", files={"file": (p.name, p.read_bytes())},
                    data={"format": "png", "output": name})
    assert r.status_code == 200, r.text
    with Image.open(io.BytesIO(r.content)) as im:
        assert im.info["icc_profile"] == outputs.shipped_icc(name)
        assert 270 not in im.getexif()
