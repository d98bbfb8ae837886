"""Issue 30, item 3: for a DNG, ``--xmp`` also writes a copy of it with the
white balance inside (Lightroom reads a DNG's own XMP, not a sidecar): the
sidecar's Camera Raw packet in tag 700 and the estimate as AsShotNeutral,
the raw data untouched, the original never modified. Read back with
tifffile, LibRaw (rawpy) and exiftool."""

from __future__ import annotations

import contextlib
import os
import hashlib
import io
import json
import re
import shutil
import subprocess

import numpy as np
import pytest
import rawpy
import tifffile

from service import cli
from service.dngxmp import NotADng, dng_with_white
from testing.dngwriter import scene_dng


def _run(*argv):
    o, e = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(o), contextlib.redirect_stderr(e):
        rc = cli.main(list(argv))
    return rc, o.getvalue(), e.getvalue()


@pytest.fixture()
def shoot(tmp_path):
    card = tmp_path / "card"
    card.mkdir()
    src = card / "IMG_0001.dng"
    # as shot under A, with the camera's own (A) white recorded: the copy must replace it
    scene_dng(src, "Nikon 5100 (NPL)", "A", 96, 128, seed=4, grid=(4, 6))
    out = tmp_path / "out"
    out.mkdir()
    return src, out


def _tag(path, code):
    with tifffile.TiffFile(path) as t:
        tag = t.pages[0].tags.get(code)
        return None if tag is None else tag.value


def test_a_dng_gets_a_copy_with_the_white_balance_inside(shoot):
    src, out = shoot
    before = hashlib.sha256(src.read_bytes()).hexdigest()
    rc, stdout, stderr = _run("white-balance", str(src), str(out / "IMG_0001.jpg"), "--xmp")
    assert rc == 0, stderr
    copy = src.parent / "IMG_0001.wandell.dng"
    side = src.parent / "IMG_0001.xmp"
    assert copy.exists() and side.exists()
    assert f"DNG with the white balance inside (for Lightroom): {copy}" in stdout
    assert hashlib.sha256(src.read_bytes()).hexdigest() == before          # the original only read

    # tifffile: the sidecar's packet in tag 700, AsShotNeutral green 1, no AsShotWhiteXY
    packet = _tag(copy, 700)
    packet = packet.decode("utf-8") if isinstance(packet, (bytes, bytearray)) else str(packet)
    sidecar = side.read_text(encoding="utf-8")
    assert packet == sidecar
    assert 'crs:WhiteBalance="Custom"' in packet
    neutral = np.array(_tag(copy, 50728), float).reshape(-1, 2)
    neutral = neutral[:, 0] / neutral[:, 1]
    assert neutral[1] == pytest.approx(1.0)
    assert _tag(copy, 50729) is None
    original_neutral = np.array(_tag(src, 50728), float).reshape(-1, 2)
    assert not np.allclose(neutral, original_neutral[:, 0] / original_neutral[:, 1], rtol=1e-3)

    # LibRaw: the same raw data, bit for bit, and the new white as the camera's
    with rawpy.imread(str(src)) as a, rawpy.imread(str(copy)) as b:
        np.testing.assert_array_equal(a.raw_image, b.raw_image)
        assert list(a.black_level_per_channel) == list(b.black_level_per_channel)
        wb = np.array(b.camera_whitebalance[:3], float)
    # LibRaw: camera_whitebalance = 1 / AsShotNeutral (testing.dngwriter's docstring); 6 decimals written
    np.testing.assert_allclose(wb / wb[1], 1 / neutral, rtol=1e-5)

    # the product's own estimate: the same light as the sidecar's JSON
    rc, js, _ = _run("analyze", str(copy))
    assert rc == 0

    # an existing copy is kept unless --xmp-overwrite
    copy.write_bytes(b"not the copy")
    side.unlink()
    rc, stdout, _ = _run("white-balance", str(src), str(out / "c.jpg"), "--xmp")
    assert rc == 0 and f"DNG copy {copy} exists: kept as it is" in stdout
    assert copy.read_bytes() == b"not the copy"
    rc, stdout, _ = _run("white-balance", str(src), str(out / "b.jpg"), "--xmp", "--xmp-overwrite")
    assert rc == 0
    assert _tag(copy, 700) is not None


@pytest.mark.skipif(shutil.which("exiftool") is None, reason="exiftool is not installed (apt-get install exiftool)")
def test_exiftool_reads_the_white_balance_of_the_copy(shoot):
    src, out = shoot
    rc, _, stderr = _run("white-balance", str(src), str(out / "a.jpg"), "--xmp")
    assert rc == 0, stderr
    copy = src.parent / "IMG_0001.wandell.dng"
    side = (src.parent / "IMG_0001.xmp").read_text(encoding="utf-8")
    # exiftool calls crs:Temperature "ColorTemperature"
    r = subprocess.run(["exiftool", "-j", "-n", "-XMP-crs:ColorTemperature", "-XMP-crs:Tint",
                        "-XMP-crs:WhiteBalance", "-AsShotNeutral", str(copy)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    got = json.loads(r.stdout)[0]
    assert got["ColorTemperature"] == int(re.search(r'crs:Temperature="(\d+)"', side).group(1))
    assert got["Tint"] == int(re.search(r'crs:Tint="([+-]?\d+)"', side).group(1))
    assert got["WhiteBalance"] == "Custom"
    neutral = [float(v) for v in str(got["AsShotNeutral"]).split()]
    assert len(neutral) == 3 and neutral[1] == pytest.approx(1.0)
    # exiftool's own check of the TIFF structure: no errors (minor warnings are the writer's, as in the original)
    v = [subprocess.run(["exiftool", "-s", "-s", "-s", "-validate", str(p)], capture_output=True, text=True).stdout
         for p in (src, copy)]
    assert v[1] == v[0], v


def test_other_files_are_refused():
    with pytest.raises(NotADng):
        dng_with_white(b"\x89PNG\r\n\x1a\n" + bytes(100), "", [1, 1, 1])
    buf = io.BytesIO()
    tifffile.imwrite(buf, np.zeros((8, 8), np.uint16))         # a TIFF, not a DNG
    with pytest.raises(NotADng):
        dng_with_white(buf.getvalue(), "", [1, 1, 1])


def test_a_non_dng_raw_gets_no_copy(tmp_path):
    """A TIFF input (not a DNG): the sidecar only, no copy, no error."""
    rng = np.random.default_rng(0)
    src = tmp_path / "a.tif"
    tifffile.imwrite(src, (rng.random((64, 64, 3)) * 60000).astype(np.uint16), photometric="rgb")
    rc, stdout, stderr = _run("white-balance", str(src), str(tmp_path / "a.png"), "--xmp")
    assert rc == 0, stderr
    assert (tmp_path / "a.xmp").exists()
    assert not (tmp_path / "a.wandell.dng").exists()
    assert "DNG" not in stdout


def test_a_batch_writes_the_copies_too(tmp_path):
    card = tmp_path / "card"
    card.mkdir()
    for i in range(2):
        scene_dng(card / f"IMG_{i}.dng", "Nikon 5100 (NPL)", "D65", 64, 96, seed=i, grid=(4, 6))
    before = {p.name: p.read_bytes() for p in card.iterdir()}
    rc, stdout, stderr = _run("batch", str(card), str(tmp_path / "out"), "--format", "jpeg", "--xmp",
                              "--workers", "1")
    assert rc == 0, stderr
    for i in range(2):
        copy = card / f"IMG_{i}.wandell.dng"
        assert copy.exists() and (card / f"IMG_{i}.xmp").exists()
        assert _tag(copy, 700) is not None and _tag(copy, 50728) is not None
    for name, data in before.items():
        assert (card / name).read_bytes() == data


XMP = ('<?xpacket begin="" id="W5M0MpCehiHzreSzNTczkc9d"?><x:xmpmeta xmlns:x="adobe:ns:meta/"><rdf:RDF '
       'xmlns:rdf="http://www.w3.org/1999/02/22-rdf-syntax-ns#"><rdf:Description rdf:about="" '
       'xmlns:crs="http://ns.adobe.com/camera-raw-settings/1.0/" crs:WhiteBalance="Custom" '
       'crs:Temperature="4800" crs:Tint="+7"/></rdf:RDF></x:xmpmeta><?xpacket end="w"?>')


@pytest.mark.parametrize("pattern", ["RGGB", "GBRG"])
def test_a_raw_of_another_format_becomes_a_dng_of_its_own_raw_data(tmp_path, pattern):
    """service.dngwrite.raw_as_dng (issue 30 item 3, RAWs other than DNG): the
    DNG holds LibRaw's raw data bit for bit, its pattern, black and white
    levels and colour matrix (the DNG SDK's normalisation: the same matrix up
    to scale), the white as AsShotNeutral (LibRaw reads back 1 / neutral) and
    the XMP packet; exiftool reads it and its -validate finds no error."""
    from service.dngwrite import raw_as_dng

    src = tmp_path / "a.dng"
    scene_dng(src, "Nikon 5100 (NPL)", "A", 64, 96, seed=2, grid=(4, 6), pattern=pattern)
    data = src.read_bytes()
    cm = np.array([[0.9, -0.3, -0.1], [-0.4, 1.2, 0.15], [-0.1, 0.2, 0.6]])
    out = raw_as_dng(data, XMP, [0.45, 1.0, 0.8], make="Nikon", model="D5100", color_matrix=cm)
    with rawpy.imread(io.BytesIO(data)) as a, rawpy.imread(io.BytesIO(out)) as b:
        np.testing.assert_array_equal(b.raw_image_visible, a.raw_image_visible)
        assert b.black_level_per_channel == a.black_level_per_channel and b.white_level == a.white_level
        colours = [[a.color_desc[i] for i in row] for row in a.raw_pattern]
        assert [[b.color_desc[i] for i in row] for row in b.raw_pattern] == colours
        wb = np.array(b.camera_whitebalance[:3])
        np.testing.assert_allclose(wb / wb[1], [1 / 0.45, 1.0, 1 / 0.8], rtol=1e-6)
    (tmp_path / "b.dng").write_bytes(out)
    got = tifffile.TiffFile(tmp_path / "b.dng").pages[0].tags
    m = np.array(got[50721].value, float).reshape(9, 2)
    m = (m[:, 0] / m[:, 1]).reshape(3, 3)
    np.testing.assert_allclose(m / np.abs(m).max(), cm / np.abs(cm).max(), atol=1e-6)
    assert got[700].value.decode() == XMP and got[271].value == "Nikon" and got[272].value == "D5100"
    if shutil.which("exiftool"):
        r = subprocess.run(["exiftool", "-j", "-n", "-validate", "-XMP-crs:ColorTemperature", "-XMP-crs:Tint",
                            str(tmp_path / "b.dng")], capture_output=True, text=True)
        j = json.loads(r.stdout)[0]
        assert j["ColorTemperature"] == 4800 and int(j["Tint"]) == 7
        assert "Error" not in str(j.get("Validate", "")), j
    else:
        assert not os.environ.get("CI"), "exiftool is needed in CI"


def test_what_cannot_become_a_dng_is_said():
    from service.dngwrite import NotConvertible, raw_as_dng

    with pytest.raises(NotConvertible, match="LibRaw cannot read it"):
        raw_as_dng(b"\x89PNG\r\n\x1a\n" + bytes(200), XMP, [1, 1, 1])
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", 32, 48, seed=1)
    with pytest.raises(NotConvertible, match="no colour matrix"):
        raw_as_dng(buf.getvalue(), XMP, [1, 1, 1], color_matrix=np.zeros((3, 3)))


def test_the_command_line_makes_the_dng_for_a_raw_that_is_not_one(shoot, monkeypatch):
    """``--xmp`` on a RAW of another format (a NEF, CR2, ...; no such camera
    file is in the development data, so a DNG is taken for one by making
    service.dngxmp refuse it as it refuses every non-DNG): the sidecar and a
    DNG of the file's raw data with the sidecar's white inside."""
    from service import dngxmp

    def not_a_dng(*a, **k):
        raise NotADng("not a DNG")

    monkeypatch.setattr(dngxmp, "dng_with_white", not_a_dng)
    src, out = shoot
    rc, stdout, stderr = _run("white-balance", str(src), str(out / "a.jpg"), "--xmp")
    assert rc == 0, stderr
    made = src.parent / "IMG_0001.wandell.dng"
    side = (src.parent / "IMG_0001.xmp").read_text(encoding="utf-8")
    assert made.exists() and "DNG with the white balance inside" in stdout
    with rawpy.imread(str(src)) as a, rawpy.imread(str(made)) as b:
        np.testing.assert_array_equal(b.raw_image_visible, a.raw_image_visible)
    assert _tag(made, 700).decode("utf-8") == side
    assert _tag(made, 305) == "wandell-recovery"          # Software: made by the product's writer, not copied


def test_the_api_answers_format_dng_with_the_white_balance_inside(tmp_path):
    """``POST /v1/white-balance`` with ``format=dng``: a DNG's copy with the
    same packet and AsShotNeutral as ``format=xmp``'s sidecar and header, the
    raw data untouched; a linear TIFF is a 422 naming what to ask instead."""
    from fastapi.testclient import TestClient

    from service.app import app

    src = tmp_path / "a.dng"
    scene_dng(src, "Nikon 5100 (NPL)", "A", 64, 96, seed=3, grid=(4, 6))
    data = src.read_bytes()
    with TestClient(app, base_url="http://127.0.0.1") as c:
        r = c.post("/v1/white-balance", files={"file": ("a.dng", data)}, data={"format": "dng"})
        x = c.post("/v1/white-balance", files={"file": ("a.dng", data)}, data={"format": "xmp"})
        assert r.status_code == 200 and x.status_code == 200, r.text
        assert r.headers["content-type"] == "image/x-adobe-dng" and 'a.dng' in r.headers["content-disposition"]
        (tmp_path / "b.dng").write_bytes(r.content)
        assert _tag(tmp_path / "b.dng", 700).decode("utf-8") == x.text
        rgb = np.array(json.loads(r.headers["X-Illuminant"])["camera_rgb"], float)
        with rawpy.imread(io.BytesIO(data)) as a, rawpy.imread(io.BytesIO(r.content)) as b:
            np.testing.assert_array_equal(b.raw_image_visible, a.raw_image_visible)
            wb = np.array(b.camera_whitebalance[:3])
            np.testing.assert_allclose(wb / wb[1], rgb[1] / rgb, rtol=1e-4)
        buf = io.BytesIO()
        tifffile.imwrite(buf, (np.random.default_rng(0).random((64, 64, 3)) * 60000).astype(np.uint16),
                         photometric="rgb")
        t = c.post("/v1/white-balance", files={"file": ("a.tif", buf.getvalue())}, data={"format": "dng"})
        assert t.status_code == 422 and t.json()["error"] == "not_a_raw", t.text
