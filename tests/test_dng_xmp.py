"""Issue 30, item 3: for a DNG, ``--xmp`` also writes a copy of it with the
white balance inside (Lightroom reads a DNG's own XMP, not a sidecar): the
sidecar's Camera Raw packet in tag 700 and the estimate as AsShotNeutral,
the raw data untouched, the original never modified. Read back with
tifffile, LibRaw (rawpy) and exiftool."""

from __future__ import annotations

import contextlib
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
