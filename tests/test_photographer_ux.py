"""Issue 19, usability items for a photographer: one light described one
way (item 4), shared lighting over copies (6), error messages (9),
batch hygiene (11), the README's figures (13)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import app

from .conftest import shared_file


@pytest.fixture(scope="module")
def client():
    with TestClient(app) as c:
        yield c


def _cli(*args, **kw):
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
                          timeout=300, **kw)


def _embedded_cct_duv(data: bytes) -> set:
    """Every ``"cct":..,"duv":..`` pair of the JSON estimates a file carries."""
    pairs = re.findall(rb'"cct":\s*([-0-9.eE+]+),\s*"duv":\s*([-0-9.eE+]+)', data)
    return {(float(c), float(d)) for c, d in pairs}


# ---------------------------------------------------------------- item 4

def test_one_light_has_one_cct_duv_everywhere(client, blackmagic_dng, tmp_path):
    """The same DNG through /v1/analyze, the XMP download, the white-balance
    header and file, the CLI's analyze, and the CLI's output file and XMP
    sidecar: one CCT/Duv (the page showed 5056 K, the CLI's sidecar 5136 K).
    Temperature/Tint (Adobe's scale) describe the same chromaticity: within
    a few kelvin of the CCT, Tint about 3000 x Duv."""
    files = {"file": ("Blackmagic.dng", blackmagic_dng)}
    il = client.post("/v1/analyze", files=files).json()["illuminant"]
    cct, duv = il["cct"], il["duv"]
    assert cct is not None and duv is not None
    seen = {"analyze": (cct, duv)}

    x = client.post("/v1/white-balance", files=files, data={"format": "xmp"})
    assert x.status_code == 200, x.text
    t = float(re.search(r'crs:Temperature="([^"]+)"', x.text).group(1))
    tint = float(re.search(r'crs:Tint="([^"]+)"', x.text).group(1))
    (seen["xmp"],) = _embedded_cct_duv(x.content)
    hdr = json.loads(x.headers["X-Illuminant"])
    seen["xmp header"] = (hdr["cct"], hdr["duv"])
    assert t == round(il["temperature"]) and tint == round(il["tint"])

    w = client.post("/v1/white-balance", files=files, data={"format": "png"})
    assert w.status_code == 200
    h = json.loads(w.headers["X-Illuminant"])["illuminant"]
    seen["white-balance header"] = (h["cct"], h["duv"])
    (seen["white-balance file"],) = _embedded_cct_duv(w.content)

    src = tmp_path / "Blackmagic.dng"
    src.write_bytes(blackmagic_dng)
    r = _cli("analyze", str(src))
    assert r.returncode == 0, r.stderr
    ci = json.loads(r.stdout)["illuminant"]
    seen["cli analyze"] = (ci["cct"], ci["duv"])
    r = _cli("white-balance", str(src), str(tmp_path / "out.png"), "--xmp")
    assert r.returncode == 0, r.stderr
    (seen["cli file"],) = _embedded_cct_duv((tmp_path / "out.png").read_bytes())
    (seen["cli xmp"],) = _embedded_cct_duv((tmp_path / "Blackmagic.xmp").read_bytes())
    for where, (c, d) in seen.items():
        assert c == pytest.approx(cct, rel=1e-9) and d == pytest.approx(duv, abs=1e-12), where
    # Adobe's Temperature/Tint: the same xy (a matrix-derived camera), another method and scale
    assert il["chromaticity_basis"] == il["temperature_basis"] == "DNG tags"
    assert abs(il["temperature"] - cct) < 0.005 * cct
    assert abs(il["tint"] - 3000 * duv) < 3
    # the page says which is which
    page = client.get("/").text
    assert "Correlated colour temperature (CCT" in page and "Duv" in page
    assert "Camera Raw Temperature / Tint (Adobe's scale" in page and 'id="temp-tint"' in page


# ---------------------------------------------------------------- item 6

def test_shared_light_of_identical_copies_is_the_image_own_estimate(tmp_path):
    """``lighting=shared`` over N identical copies of one image: the shared
    light is that image's own (per-image) estimate to rounding, whatever N
    (pooling pixels into one image moved it 0.8 degrees, and with N), and
    the items carry the shared estimate's confidence."""
    from concurrent.futures import ThreadPoolExecutor

    from recovery import angular_error
    from service import cli, jobs
    from testing.dngwriter import scene_dng

    src = tmp_path / "src.dng"
    scene_dng(src, "Nikon 5100 (NPL)", "A", 160, 240, seed=3, grid=(4, 6))
    own_opts = jobs.batch_options(format="png")
    (tmp_path / "one").mkdir()
    shutil.copy(src, tmp_path / "one" / "a.dng")
    with ThreadPoolExecutor(2) as ex:
        (own,) = cli.run_batch(str(tmp_path / "one"), str(tmp_path / "own"), own_opts, executor=ex, quiet=True)
        assert own["status"] == "done"
        own_ill = own["illuminant"]
        assert isinstance(own_ill["confidence"], float)
        shared = jobs.batch_options(format="png", lighting="shared")
        for n in (1, 2, 5):
            d = tmp_path / f"copies{n}"
            d.mkdir()
            for i in range(n):
                shutil.copy(src, d / f"c{i}.dng")
            rows = cli.run_batch(str(d), str(tmp_path / f"out{n}"), shared, executor=ex, quiet=True)
            assert [r["status"] for r in rows] == ["done"] * n
            light = json.loads((tmp_path / f"out{n}" / ".wandell" / "shared-light.json").read_text())["light"]
            assert light["images"] == n
            for r in rows:
                ill = r["illuminant"]
                assert angular_error(ill["camera_rgb"], own_ill["camera_rgb"]) < 1e-6, n
                assert ill["cct"] == pytest.approx(own_ill["cct"], rel=1e-9)
                assert ill["confidence"] == pytest.approx(own_ill["confidence"], rel=1e-9), n
                assert ill["low_confidence"] == own_ill["low_confidence"]
            assert light["confidence"] == pytest.approx(own_ill["confidence"], rel=1e-9)
            assert max(light["image_angles_deg"]) < 1e-6


def test_shared_light_lowers_confidence_and_warns_when_images_disagree():
    """Two images whose own lights are 10 degrees apart: the shared light lies
    between them, its confidence is below theirs and a warning says so."""
    from recovery import angular_error
    from service import jobs

    class Cam:
        name, source = "cam", "measured"

    def sample(rgb, conf):
        rgb = np.asarray(rgb, float)
        return {"status": "ok", "camera": Cam, "profile": None, "warnings": [],
                "estimate": {"camera_rgb": rgb.tolist(), "spectrum": [1.0, 1.0, 1.0], "wavelengths": [400, 550, 700],
                             "confidence": conf, "method": "learned"}}

    a, b = np.array([0.5, 1.0, 0.6]), np.array([0.7, 1.0, 0.45])
    gap = angular_error(a, b)
    light = jobs.shared_light([sample(a, 0.8), sample(b, 0.8)], jobs.batch_options(lighting="shared"))
    assert angular_error(light["camera_rgb"], a) < gap and angular_error(light["camera_rgb"], b) < gap
    assert light["confidence"] < 0.8 * 0.5
    assert any("not all be under one light" in w for w in light["warnings"])


# ---------------------------------------------------------------- item 9

def test_a_text_file_named_dng_is_415_not_a_raw(client):
    """Detected by content: text has no TIFF/RAW signature, whatever its name
    (it was a 422 corrupt_file "LibRawIOError: Input/output error")."""
    for name in ("notes.dng", "IMG_1.NEF", None):
        r = client.post("/v1/analyze", files={"file": (name or "upload", b"hello, this is text\nnot a photo\n")})
        body = r.json()
        assert r.status_code == 415 and body["error"] == "unsupported_format", body
        assert "text file" in body["detail"] and "LibRaw" not in body["detail"].split("signature")[0]
        if name and name.endswith(("dng", "NEF")):
            assert "no TIFF or RAW signature" in body["detail"]
    # binary garbage with a RAW name is still a damaged RAW (test_rawio), a UTF-8 BOM'd CSV is text
    r = client.post("/v1/analyze", files={"file": ("a.dng", np.random.default_rng(1).bytes(5000))})
    assert r.status_code == 422 and r.json()["error"] == "corrupt_file"
    r = client.post("/v1/analyze", files={"file": ("a.dng", "\ufeffwavelength,r,g,b\n400,0.1,0.2,0.3\n".encode())})
    assert r.status_code == 415


def test_scanner_nef_names_its_make_once(client):
    data = shared_file("data/raw/Nikon_uncompressed.nef").read_bytes()
    r = client.post("/v1/analyze", files={"file": ("Nikon_uncompressed.nef", data)})
    body = r.json()
    assert r.status_code == 415 and body["error"] == "not_camera_raw"
    assert "(Nikon COOLSCAN" in body["detail"] and "Nikon Nikon" not in body["detail"], body["detail"]
    from service.rawio import camera_label

    assert camera_label("Nikon", "Nikon COOLSCAN IV ED") == "Nikon COOLSCAN IV ED"
    assert camera_label("Canon", "EOS 5D") == "Canon EOS 5D" and camera_label(None, "X") == "X"


def _node(script: str) -> dict:
    """Run the page's script in node (no DOM: only its pure functions are
    called) followed by ``script``, which prints JSON."""
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed")
    from pathlib import Path

    src = (Path(__file__).resolve().parents[1] / "service" / "static" / "app.js").read_text()
    prog = ("globalThis.document = {addEventListener() {}, getElementById() { return null; }};\n"
            "require('vm').runInThisContext(" + json.dumps(src + "\n" + script) + ");")
    r = subprocess.run([node, "-e", prog], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def test_page_shows_the_server_detail_and_page_words():
    out = _node("""
      const a = new ApiError(415, "not_camera_raw", "'x.nef' is not a camera RAW: a scanned 8-bit RGB image");
      const b = new ApiError(422, "some_new_code", "what went wrong");
      const w = diagnosticsInWords({method: "neutral-surface", diagnostics: {}, warnings: [
        "the white you chose is 7.0 degrees from the camera's own as-shot white (more than 5): check the " +
        "picture, or use a white surface ('neutral') or white=as-shot"]});
      console.log(JSON.stringify({a: a.message, b: b.message, summary: w.summary, warnings: w.warnings}));
    """)
    assert out["a"].startswith("No camera sensor data to analyse: 'x.nef' is not a camera RAW") and "415" in out["a"]
    assert out["b"].startswith("what went wrong") and "The request failed" not in out["b"]
    assert "surface you clicked" in out["summary"] and "neutral-surface" not in out["summary"]
    (w,) = out["warnings"]
    assert "click a white or grey surface" in w and "'neutral'" not in w and "white=as-shot" not in w


def test_inverted_neutral_rectangle_is_called_inverted_and_a_dark_patch_warns():
    from types import SimpleNamespace

    from service import pipeline
    from service.errors import ServiceError

    est = np.full((50, 60, 3), 0.5, np.float32)
    est[:10, :10] = 0.012                       # a dark tree: 1.2 % of the white level
    d = SimpleNamespace(full_shape=(100, 120), estimation=est, saturated=np.zeros((50, 60), bool))
    for where, words in (([40, 10, 20, 30], "r0 >= r1 (40 >= 20)"), ([10, 30, 20, 10], "c0 >= c1 (30 >= 10)"),
                         ([5, 5, 5, 9], "r0 >= r1 (5 >= 5)")):
        with pytest.raises(ServiceError) as e:
            pipeline.neutral_white(d, where)
        assert e.value.status == 422 and "inverted" in e.value.detail and words in e.value.detail
        assert "outside" not in e.value.detail
    with pytest.raises(ServiceError) as e:
        pipeline.neutral_white(d, [0, 0, 101, 10])
    assert "outside" in e.value.detail
    _, info = pipeline.neutral_white(d, [0, 0, 20, 20])
    assert "dark" in info["warning"] and "1.2 % of the white level" in info["warning"]
    _, info = pipeline.neutral_white(d, [40, 40, 60, 60])
    assert "warning" not in info


def test_cli_missing_file_is_a_clear_usage_error(tmp_path):
    for args in (("analyze", str(tmp_path / "nope.dng")),
                 ("white-balance", str(tmp_path / "nope.dng"), str(tmp_path / "o.tif"))):
        r = _cli(*args)
        assert r.returncode == 2, r
        assert "file_not_found" in r.stderr and "nope.dng" in r.stderr and "does not exist" in r.stderr
        assert "Traceback" not in r.stderr and "Errno" not in r.stderr + r.stdout
    r = _cli("analyze", str(tmp_path))
    assert r.returncode == 2 and "is a folder" in r.stderr and "wandell batch" in r.stderr


# ---------------------------------------------------------------- item 11

@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    """A shoot with a subfolder, a nested one, a JPEG, notes and a hidden file."""
    from testing.dngwriter import scene_dng

    d = tmp_path_factory.mktemp("tree")
    scene_dng(d / "a.dng", "Nikon 5100 (NPL)", "D4000", 64, 96, seed=1, grid=(4, 6))
    (d / "day2" / "deep").mkdir(parents=True)
    for p in (d / "day2" / "b.dng", d / "day2" / "deep" / "a.dng"):
        p.write_bytes((d / "a.dng").read_bytes())
    (d / "notes.txt").write_text("shoot notes")
    (d / "day2" / "preview.jpg").write_bytes(b"\xff\xd8\xff\xe0")
    (d / ".DS_Store").write_bytes(b"\0")
    return d


def test_batch_leaves_no_lock_files_and_locks_still_exclude(tree, tmp_path):
    import os
    import threading
    from concurrent.futures import ThreadPoolExecutor

    from service import cli, jobs

    out = tmp_path / "out"
    with ThreadPoolExecutor(2) as ex:
        rows = cli.run_batch(str(tree), str(out), jobs.batch_options(format="png"), executor=ex, quiet=True,
                             recursive=True)
    assert [r["status"] for r in rows] == ["done"] * 3
    left = [p for p in out.rglob("*") if p.suffix == ".lock"]
    assert left == [], left
    assert sorted(p.name for p in (out / ".wandell").iterdir()) == ["a.png.json"]
    # the lock is still exclusive while held, and removed after
    target = str(tmp_path / "x.png")
    inside, order = threading.Event(), []

    def second():
        with jobs._item_lock(target):
            order.append("second")

    with jobs._item_lock(target):
        assert os.path.exists(jobs.meta_path(target, ".lock"))
        t = threading.Thread(target=second)
        t.start()
        t.join(0.3)
        order.append("first")
        inside.set()
    t.join(10)
    assert order == ["first", "second"] and not os.path.exists(jobs.meta_path(target, ".lock"))


def test_batch_summary_names_what_it_skipped_and_recursive_mirrors_the_tree(tree, tmp_path):
    out = tmp_path / "flat"
    r = _cli("batch", str(tree), str(out), "--workers", "1", "--format", "png")
    assert r.returncode == 0, r.stderr
    assert "1 done" in r.stdout
    assert "not processed: 1 subfolder (--recursive processes them, mirroring the tree): day2/" in r.stdout
    assert "not processed: 1 file not RAW/TIFF/PNG (by name): notes.txt" in r.stdout
    assert ".DS_Store" not in r.stdout
    out = tmp_path / "tree"
    r = _cli("batch", str(tree), str(out), "--workers", "1", "--format", "png", "--recursive")
    assert r.returncode == 0, r.stderr
    assert "3 done" in r.stdout and "day2/deep/a.dng" in r.stdout
    for p in ("a.png", "day2/b.png", "day2/deep/a.png"):
        assert (out / p).is_file(), p
    assert "day2/preview.jpg" in r.stdout and "notes.txt" in r.stdout and "subfolder" not in r.stdout
    # the rerun skips all three (resumable in subfolders too)
    r = _cli("batch", str(tree), str(out), "--workers", "1", "--format", "png", "--recursive")
    assert r.returncode == 0 and "0 done, 3 skipped" in r.stdout


# ---------------------------------------------------------------- item 13

def _readme() -> str:
    from pathlib import Path

    return (Path(__file__).resolve().parents[1] / "README.md").read_text()


def _table_rows(text: str, header_start: str) -> list[list[str]]:
    lines = text.splitlines()
    i = next(k for k, ln in enumerate(lines) if ln.startswith(header_start))
    rows = []
    for ln in lines[i + 2:]:
        if not ln.startswith("|"):
            break
        rows.append([c.strip() for c in ln.strip().strip("|").split("|")])
    return rows


def test_readme_settings_table_lists_every_setting_with_its_default():
    from service.settings import Settings

    rows = _table_rows(_readme(), "| variable | default | what it does |")
    # the request-cost limits added by issue 28 are tabled in docs/limits.md (same columns) until the
    # README's rewrite takes them in
    from pathlib import Path

    limits = (Path(__file__).resolve().parents[1] / "docs" / "limits.md").read_text()
    rows += _table_rows(limits, "| variable | default | what it does |")
    got = {r[0].strip("`"): r for r in rows}
    fields = Settings.model_fields
    assert set(got) == {f"WANDELL_{k.upper()}" for k in fields}
    for k, f in fields.items():
        default = got[f"WANDELL_{k.upper()}"][1]
        if f.default == "":
            assert default.startswith("empty"), (k, default)
        else:
            first = default.split()[0].strip("`")
            assert type(f.default)(first) == f.default, (k, default, f.default)
        assert got[f"WANDELL_{k.upper()}"][2], k  # says what it does


def test_readme_analysis_pixels_are_those_of_the_real_file(client, blackmagic_dng):
    rows = _table_rows(_readme(), "| `quality` | at most | pixels analysed (Blackmagic.dng)")
    assert len(rows) == 4
    for quality, _, pixels, factor in rows:
        q = quality.strip("`")
        data = {} if q == "none" else {"quality": q}
        d = client.post("/v1/analyze", files={"file": ("Blackmagic.dng", blackmagic_dng)}, data=data).json()
        d = d["diagnostics"]
        assert d["pixels_total"] == int(pixels.split()[0].replace(",", "")), (q, d["pixels_total"])
        assert d["analysis_block_factor"] == int(factor), q


def test_readme_says_how_to_stop_the_server_and_what_wandell_serve_is():
    text = _readme()
    assert "Ctrl-C" in text and "`wandell-serve`" in text
    import tomllib
    from pathlib import Path

    meta = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())
    assert meta["project"]["scripts"]["wandell-serve"] == "service.__main__:main"
