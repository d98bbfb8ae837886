"""Issue 30, item 3 (its last piece): batches offer the DNG with the white
balance inside. ``POST /v1/batches`` with ``format=dng`` makes each RAW's
result the file ``POST /v1/white-balance format=dng`` answers for the same
upload and options (a DNG's copy with the Camera Raw packet and the light
as AsShotNeutral, its raw data untouched); a linear TIFF/PNG item fails
alone (``not_a_raw``, naming what to ask for); the downloads are
``image/x-adobe-dng`` named ``.dng``, and the zip holds them. Through the
real ASGI app, with the real CinemaDNG of ``../shared/data/raw`` and DNGs of
:mod:`testing.dngwriter`; rawpy (LibRaw) reads every result back."""

from __future__ import annotations

import contextlib
import io
import json
import os
import zipfile

import numpy as np
import pytest
import rawpy
import tifffile
from fastapi.testclient import TestClient

from service import cli, jobs
from service.settings import get_settings
from testing.dngwriter import scene_dng

from .conftest import shared_file
from .test_batch_delete import _settle

#: AsShotNeutral is written as rationals of denominator 10^6 (service.dngxmp):
#: at most 5e-7 off on a neutral of green 1 whose channels are above 0.05,
#: i.e. 1e-5 relative; LibRaw's camera_whitebalance is float32 (6e-8).
WB_RTOL = 1e-5


def _linear_tiff() -> bytes:
    buf = io.BytesIO()
    img = (np.random.default_rng(0).random((64, 96, 3)) * 60000).astype(np.uint16)
    tifffile.imwrite(buf, img, photometric="rgb")
    return buf.getvalue()


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    base = tmp_path_factory.mktemp("batchdng")
    old = dict(os.environ)
    os.environ.update(WANDELL_DATA_DIR=str(base / "data"), WANDELL_BATCH_WORKERS="2")
    get_settings.cache_clear()
    yield base
    os.environ.clear()
    os.environ.update(old)
    get_settings.cache_clear()


@pytest.fixture(scope="module")
def client(env):
    from service.app import app

    with TestClient(app) as c:  # the lifespan starts (and stops) the batch runner
        yield c


def _wait(client, bid):
    return _settle(client, bid, timeout=300)


def _neutral_of(dng: bytes) -> np.ndarray:
    """AsShotNeutral (tag 50728) as numbers, green 1."""
    with tifffile.TiffFile(io.BytesIO(dng)) as t:
        v = np.array(t.pages[0].tags[50728].value, float).reshape(-1, 2)
    return v[:, 0] / v[:, 1]


def _check_dng(result: bytes, original: bytes, camera_rgb) -> None:
    """LibRaw reads ``result``: the original's raw data, and the camera white
    1/AsShotNeutral of the light ``camera_rgb`` (as tests/test_dng_xmp.py)."""
    rgb = np.asarray(camera_rgb, float)
    with rawpy.imread(io.BytesIO(original)) as a, rawpy.imread(io.BytesIO(result)) as b:
        np.testing.assert_array_equal(b.raw_image_visible, a.raw_image_visible)
        wb = np.array(b.camera_whitebalance[:3], float)
        np.testing.assert_allclose(wb / wb[1], rgb[1] / rgb, rtol=WB_RTOL)
    np.testing.assert_allclose(_neutral_of(result), rgb / rgb[1], rtol=WB_RTOL)
    with tifffile.TiffFile(io.BytesIO(result)) as t:
        packet = bytes(t.pages[0].tags[700].value).decode("utf-8")
    assert 'crs:WhiteBalance="Custom"' in packet and "crs:Temperature=" in packet


def test_a_mixed_batch_gives_each_raw_as_its_dng_and_fails_the_linear_image_alone(client, tmp_path):
    real = shared_file("data/raw/Blackmagic.dng").read_bytes()
    scene_dng(tmp_path / "scene.dng", "Nikon 5100 (NPL)", "A", 96, 128, seed=5, grid=(4, 6))
    inputs = {"Blackmagic.dng": real, "scene.dng": (tmp_path / "scene.dng").read_bytes(),
              "linear.tif": _linear_tiff()}
    opts = {"format": "dng", "method": "auto"}
    r = client.post("/v1/batches", files=[("files", (n, d, "application/octet-stream")) for n, d in inputs.items()],
                    data=opts)
    assert r.status_code == 202, r.text
    bid = r.json()["id"]
    doc = _wait(client, bid)
    assert doc["status"] == "done" and doc["options"]["format"] == "dng"
    assert (doc["counts"]["done"], doc["counts"]["failed"]) == (2, 1), doc
    by = {it["name"]: it for it in doc["items"]}

    # the linear image: its own 422-style error, naming what to ask for instead
    bad = by["linear.tif"]
    assert bad["status"] == "failed" and bad["error"].startswith("not_a_raw: "), bad
    assert "ask for tiff" in bad["error"] and "format=dng needs a camera RAW" in bad["error"]
    miss = client.get(f"/v1/batches/{bid}/items/by-index/{bad['index']}")
    assert miss.status_code == 409 and "not_a_raw" in miss.json()["detail"]

    downloads = {}
    for name in ("Blackmagic.dng", "scene.dng"):
        it = by[name]
        assert it["status"] == "done" and it["output"] == name, it
        got = client.get(it["url"])
        assert got.status_code == 200, got.text
        assert got.headers["content-type"] == "image/x-adobe-dng"
        assert f'filename="{name}"' in got.headers["content-disposition"]
        # the very bytes of the single-file endpoint for the same upload and options
        one = client.post("/v1/white-balance", files={"file": (name, inputs[name])}, data=opts)
        assert one.status_code == 200 and one.headers["content-type"] == "image/x-adobe-dng", one.text
        assert got.content == one.content
        assert json.loads(one.headers["X-Illuminant"])["camera_rgb"] == it["illuminant"]["camera_rgb"]
        _check_dng(got.content, inputs[name], it["illuminant"]["camera_rgb"])
        downloads[name] = got.content
    # the real file's own as-shot white (0.4533, 1, 0.5300) was replaced by the estimate
    assert not np.allclose(_neutral_of(downloads["Blackmagic.dng"]), [0.4533, 1, 0.53], atol=1e-3)

    z = client.get(f"/v1/batches/{bid}/zip")
    assert z.status_code == 200
    with zipfile.ZipFile(io.BytesIO(z.content)) as zf:
        assert sorted(zf.namelist()) == ["Blackmagic.dng", "FAILURES.txt", "batch.json", "manifest.json", "scene.dng"]
        for name, data in downloads.items():
            assert zf.read(name) == data
        assert "linear.tif\tfailed\tnot_a_raw" in zf.read("FAILURES.txt").decode()


def test_shared_lighting_puts_the_one_light_in_every_dng(client, tmp_path):
    files = []
    for i in range(2):
        p = tmp_path / f"s{i}.dng"
        scene_dng(p, "Nikon 5100 (NPL)", "D50", 96, 128, seed=10 + i, grid=(4, 6))
        files.append(("files", (p.name, p.read_bytes(), "application/octet-stream")))
    r = client.post("/v1/batches", files=files, data={"format": "dng", "lighting": "shared"})
    assert r.status_code == 202, r.text
    doc = _wait(client, r.json()["id"])
    assert doc["counts"]["done"] == 2, doc
    light = np.array(doc["shared_light"]["camera_rgb"], float)
    for it, (_, (name, data, _)) in zip(sorted(doc["items"], key=lambda i: i["index"]), files):
        got = client.get(it["url"])
        assert got.status_code == 200 and got.headers["content-type"] == "image/x-adobe-dng"
        _check_dng(got.content, data, light)


def test_the_openapi_document_offers_dng_for_batches(client):
    spec = client.get("/openapi.json").json()
    body = spec["paths"]["/v1/batches"]["post"]["requestBody"]["content"]
    ref = next(iter(body.values()))["schema"]["$ref"].split("/")[-1]
    fmt = spec["components"]["schemas"][ref]["properties"]["format"]
    enum = fmt.get("enum") or next(s["enum"] for s in fmt.get("anyOf", []) if s.get("enum"))
    assert set(enum) == {"tiff", "png", "png16", "jpeg", "jpg", "dng"}
    assert "dng: each RAW as a DNG with its white balance inside" in fmt["description"]
    assert "not_a_raw" in fmt["description"]
    for path in ("/v1/batches/{batch_id}/items/{item}", "/v1/batches/{batch_id}/items/by-index/{index}",
                 "/v1/batches/{batch_id}/items/by-name/{name}"):
        ok = spec["paths"][path]["get"]["responses"]["200"]
        assert "image/x-adobe-dng" in ok["content"] and "format=dng" in ok["description"], path


def test_a_finished_dng_item_is_adopted_and_a_lost_store_rebuilt_with_it(tmp_path):
    """Exactly once as for the other formats: a second run adopts the DNG
    (nothing written again), and a store rebuilt from the batch's manifest
    and journal knows the item done with its light."""
    d = tmp_path / "in"
    d.mkdir()
    for i in range(2):
        scene_dng(d / f"im{i}.dng", "Nikon 5100 (NPL)", "D65", 64, 96, seed=i)
    data = str(tmp_path / "data")
    store = jobs.JobStore(data)
    bid = store.new_batch_id()
    store.create_batch(bid, jobs.batch_options(format="dng"), [(f"im{i}.dng", str(d / f"im{i}.dng"))
                                                               for i in range(2)])
    rows = store.items(bid)
    assert [os.path.basename(r["out"]) for r in rows] == ["im0.dng", "im1.dng"]
    log = str(tmp_path / "writes.log")
    task = jobs.ItemTask(src=rows[0]["src"], out=rows[0]["out"], name=rows[0]["name"],
                         options=jobs.batch_options(format="dng"), max_pixels=10 ** 8, estimation_pixels=10 ** 6,
                         write_log=log, index=0)
    first = jobs.process_item(task)
    assert first["status"] == "done" and not first["adopted"], first
    written = open(rows[0]["out"], "rb").read()
    _check_dng(written, (d / "im0.dng").read_bytes(), first["illuminant"]["camera_rgb"])
    again = jobs.process_item(task)
    assert again["status"] == "done" and again["adopted"], again
    assert open(rows[0]["out"], "rb").read() == written
    assert len(open(log).read().splitlines()) == 1          # written once
    db = os.path.join(data, "jobs.sqlite")
    del store
    for suffix in ("", "-wal", "-shm"):
        with contextlib.suppress(FileNotFoundError):
            os.unlink(db + suffix)
    rebuilt = jobs.JobStore(data)
    by = {r["idx"]: r for r in rebuilt.items(bid)}
    assert by[0]["status"] == "done" and by[1]["status"] == "pending"
    assert json.loads(by[0]["illuminant"])["camera_rgb"] == first["illuminant"]["camera_rgb"]


def test_wandell_batch_format_dng_writes_dngs_and_fails_a_tiff_alone(tmp_path, capsys):
    """The command line takes the same option (its flag is checked by the
    same model): ``wandell batch IN OUT --format dng``."""
    src = tmp_path / "in"
    src.mkdir()
    scene_dng(src / "IMG_0001.dng", "Nikon 5100 (NPL)", "A", 96, 128, seed=7, grid=(4, 6))
    (src / "linear.tif").write_bytes(_linear_tiff())
    out = tmp_path / "out"
    rc = cli.main(["batch", str(src), str(out), "--format", "dng", "--workers", "1", "-q"])
    err = capsys.readouterr().err
    assert rc == 1 and "not_a_raw" in err, err                # one item failed, said on stderr
    made = (out / "IMG_0001.dng").read_bytes()
    side = json.loads((out / ".wandell" / "IMG_0001.dng.json").read_text())
    _check_dng(made, (src / "IMG_0001.dng").read_bytes(), side["illuminant"]["camera_rgb"])
    assert not (out / "linear.dng").exists()


@pytest.mark.parametrize("fmt,refused", [("dng", "IMG_0001.dng"), ("tiff", "linear.tif")])
def test_an_output_that_is_its_input_is_refused_and_the_original_kept(tmp_path, capsys, fmt, refused):
    """``wandell batch IN IN``: IMG_0001.dng's DNG (a TIFF's TIFF) would be
    named as the file itself; the item fails (``output_is_input``) and the
    original is left byte for byte, the other items go on."""
    import hashlib

    src = tmp_path / "in"
    src.mkdir()
    scene_dng(src / "IMG_0001.dng", "Nikon 5100 (NPL)", "A", 64, 96, seed=8)
    (src / "linear.tif").write_bytes(_linear_tiff())
    before = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in src.iterdir()}
    rc = cli.main(["batch", str(src), str(src), "--format", fmt, "--workers", "1", "-q"])
    err = capsys.readouterr().err
    assert rc == 1 and "output_is_input" in err and refused in err, err
    assert {n: hashlib.sha256((src / n).read_bytes()).hexdigest() for n in before} == before
    assert not (src / ".wandell" / f"{refused}.json").exists()
