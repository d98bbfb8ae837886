"""service.jobs: the SQLite job store, the exactly-once item function, the
shared-light pooling, the runner on a Dask LocalCluster (issue 6). Real
DNG files from testing.dngwriter with known truth."""

from __future__ import annotations

import json
import os

import cv2
import numpy as np
import pytest

import models
from recovery import angular_error
from service import jobs
from service.errors import ServiceError
from testing.dngwriter import scene_dng

WL5 = models.wavelength_grid(400, 700, 5)


def in_model_surfaces(shift: float = 0.0):
    """24 reflectances inside the 2-term Fourier model (DC + one sine),
    within [0.1, 0.9]; ``shift`` moves the set so images differ."""
    f = models.fourier_basis(WL5, 2)
    f = f / f[:, 0].mean()
    amp = np.abs(f[:, 1]).max()
    return 0.5 + shift + (np.linspace(-0.35, 0.35, 24) / amp)[:, None] * f[:, 1][None]


def task(src, out, options=None, **kw):
    return jobs.ItemTask(src=str(src), out=str(out), name=os.path.basename(str(src)),
                         options=options or jobs.batch_options(format="png"), max_pixels=10**8,
                         estimation_pixels=10**6, **kw)


@pytest.fixture(scope="module")
def dngs(tmp_path_factory):
    d = tmp_path_factory.mktemp("dng")
    truths = [scene_dng(d / f"im{i}.dng", "Nikon 5100 (NPL)", "D4000", 160, 240, seed=i, grid=(4, 6),
                        surfaces=in_model_surfaces(0.03 * (i - 1)), noise_multiplicative=0, noise_additive=0)
              for i in range(3)]
    (d / "corrupt.dng").write_bytes(b"II*\x00" + b"\x13" * 500)
    return d, truths


def test_batch_options_refuse_unknown_values_by_name():
    for kw, word in (({"format": "bmp"}, "format"), ({"lighting": "global"}, "lighting"),
                     ({"output": "XYZ"}, "output"), ({"method": "magic"}, "method"),
                     ({"target": "NOPE"}, "target"), ({"camera": "Leica M0"}, "camera")):
        with pytest.raises(ServiceError) as e:
            jobs.batch_options(**kw)
        assert word in e.value.detail and e.value.status == 422
    assert jobs.batch_options(format="jpeg").extension == "jpg"


def test_store_transitions_are_atomic_and_resume_requeues(tmp_path):
    store = jobs.JobStore(tmp_path / "data")
    bid = store.new_batch_id()
    opts = jobs.batch_options(format="png")
    store.create_batch(bid, opts, [("a.dng", "/x/a.dng"), ("a.dng", "/y/a.dng"), ("b.nef", "/x/b.nef")])
    rows = store.items(bid)
    assert [r["name"] for r in rows] == ["a.dng", "a (2).dng", "b.nef"]
    assert [os.path.basename(r["out"]) for r in rows] == ["a.png", "a (2).png", "b.png"]
    assert store.start_batch(bid) and not store.start_batch(bid)  # queued -> running once
    claimed = store.claim(bid, 2)
    assert [r["idx"] for r in claimed] == [0, 1]
    assert store.claim(bid, 5)[0]["idx"] == 2 and store.claim(bid, 5) == []  # nothing claimed twice
    assert store.finish_item(bid, 0, {"status": "done", "illuminant": {"cct": 4000}})
    assert not store.finish_item(bid, 0, {"status": "done"})  # only from running
    # a killed server: item 1 and 2 were running -> resume puts them back
    assert store.resume() == 2
    assert store.counts(bid)["pending"] == 2
    assert store.item(bid, "a (2).dng")["idx"] == 1 and store.item(bid, "2")["name"] == "b.nef"
    assert store.cancel(bid) and not store.cancel(bid)
    c = store.counts(bid)
    assert (c["done"], c["cancelled"], c["pending"]) == (1, 2, 0)
    doc = store.progress(bid)
    assert doc["status"] == "cancelled" and doc["counts"]["done"] == 1
    assert doc["items"][0]["illuminant"]["cct"] == 4000
    assert store.progress("nope") is None


def test_process_item_writes_once_and_adopts_a_finished_output(tmp_path, dngs):
    d, truths = dngs
    out = tmp_path / "im0.png"
    log = tmp_path / "writes.log"
    t = task(d / "im0.dng", out, jobs.batch_options(format="png", method="maloney-wandell",
                                                     surface_model="fourier"), write_log=str(log))
    r1 = jobs.process_item(t)
    assert r1["status"] == "done" and not r1["adopted"]
    # in-model surfaces and daylight without noise: eq. 30/35 exact up to the
    # 10 nm grid and 14-bit quantisation (< 0.1 degree, see test_api), so 0.25
    assert angular_error(r1["illuminant"]["camera_rgb"], truths[0].light_rgb) < 0.25
    img = cv2.imread(str(out), cv2.IMREAD_UNCHANGED)
    assert img.shape == (160, 240, 3) and img.dtype == np.uint8
    ino, mtime = os.stat(out).st_ino, os.stat(out).st_mtime_ns
    r2 = jobs.process_item(t)
    assert r2["status"] == "done" and r2["adopted"]
    assert r2["illuminant"]["camera_rgb"] == r1["illuminant"]["camera_rgb"]
    assert (os.stat(out).st_ino, os.stat(out).st_mtime_ns) == (ino, mtime)
    assert len(log.read_text().splitlines()) == 1
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".part")]


def test_partial_output_never_counts_as_finished(tmp_path, dngs):
    d, _ = dngs
    out = tmp_path / "im1.png"
    out.write_bytes(b"\x89PNG half")  # a crash mid-write by some other tool: no sidecar
    assert not jobs.is_finished(str(out))
    r = jobs.process_item(task(d / "im1.dng", out))
    assert r["status"] == "done" and not r["adopted"]
    assert cv2.imread(str(out)).shape == (160, 240, 3)


def test_corrupt_file_fails_with_a_clear_error(tmp_path, dngs):
    d, _ = dngs
    r = jobs.process_item(task(d / "corrupt.dng", tmp_path / "c.png"))
    assert r["status"] == "failed" and r["error"].startswith("corrupt_file:") and "corrupt.dng" in r["error"]
    assert not (tmp_path / "c.png").exists()
    s = jobs.estimation_sample(task(d / "corrupt.dng", tmp_path / "c.png"), 4096)
    assert s["status"] == "failed" and "corrupt_file" in s["error"]


def test_pool_images_pads_and_masks():
    a = np.ones((2, 3, 3), np.float32)
    b = 2 * np.ones((4, 5, 3), np.float32)
    img, mask = jobs.pool_images([a, b], [None, np.ones((4, 5), bool)])
    assert img.shape == (6, 5, 3) and mask.shape == (6, 5)
    assert mask.sum() == 2 * 3 + 4 * 5 and not mask[:2, 3:].any() and np.all(img[2:] == 2)


def test_shared_light_pools_all_images_and_is_the_true_light(tmp_path, dngs):
    """Three images under one daylight, surfaces in the 2-term model: every
    image's data lie in the same plane (eq. 26-29), so pooling them keeps
    eq. 30 exact; the same 0.25 degree bound as a single in-model image."""
    d, truths = dngs
    opts = jobs.batch_options(method="maloney-wandell", surface_model="fourier", lighting="shared", format="png")
    samples = [jobs.estimation_sample(task(d / f"im{i}.dng", tmp_path / f"{i}.png", opts), 20000)
               for i in range(3)]
    assert all(s["status"] == "ok" for s in samples)
    light = jobs.shared_light(samples, opts)
    assert light["images"] == 3
    assert angular_error(light["camera_rgb"], truths[0].light_rgb) < 0.25
    # the CCT of the recovered daylight: within 3 % of 4000 K (as test_api)
    assert abs(light["cct"] - 4000 * 1.4388 / 1.4380) < 0.03 * 4000
    r = jobs.process_item(task(d / "im2.dng", tmp_path / "2.png", opts, light=light))
    assert r["status"] == "done"
    assert np.allclose(r["illuminant"]["camera_rgb"], light["camera_rgb"], atol=1e-9)


def test_folder_sources_refuse_paths_outside_the_root(tmp_path, dngs):
    d, _ = dngs
    root = tmp_path / "root"
    (root / "shoot").mkdir(parents=True)
    for n in ("im0.dng", "im1.dng"):
        (root / "shoot" / n).write_bytes((d / n).read_bytes())
    (root / "shoot" / "notes.txt").write_text("not an image")
    os.symlink(d / "im2.dng", root / "shoot" / "escape.dng")    # a symlink leading out: skipped
    os.symlink(d, root / "out-link")                              # a folder symlink leading out: refused
    got = jobs.folder_sources(str(root), "shoot")
    assert [n for n, _ in got] == ["im0.dng", "im1.dng"]
    for bad in ("../", "shoot/../..", "/etc", str(d), "out-link"):
        with pytest.raises(ServiceError) as e:
            jobs.folder_sources(str(root), bad)
        assert e.value.code == "path_outside_root" and e.value.status == 403
    with pytest.raises(ServiceError) as e:
        jobs.folder_sources("", "shoot")
    assert e.value.code == "folder_mode_disabled" and "WANDELL_BATCH_ROOT" in e.value.detail
    with pytest.raises(ServiceError) as e:
        jobs.folder_sources(str(root), "missing")
    assert e.value.status == 404


def test_runner_on_a_dask_local_cluster(tmp_path, dngs):
    """The same batch on a Dask LocalCluster (in-process workers): every
    readable item done with its estimate, the corrupt one failed, in both
    lighting modes."""
    distributed = pytest.importorskip("distributed")
    d, truths = dngs
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        ex = jobs.DaskExecutor(client=client)
        assert ex.workers == 2
        runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), poll_s=0.05), executor=ex)
        runner.start()
        try:
            srcs = [(n, str(d / n)) for n in ("im0.dng", "im1.dng", "im2.dng", "corrupt.dng")]
            ids = {}
            for mode in ("per-image", "shared"):
                bid = runner.store.new_batch_id()
                runner.store.create_batch(bid, jobs.batch_options(format="png", lighting=mode,
                                                                  method="maloney-wandell",
                                                                  surface_model="fourier"), srcs)
                ids[mode] = bid
            runner.wake()
            for mode, bid in ids.items():
                doc = runner.wait(bid, 120)
                assert doc["status"] == "done"
                assert (doc["counts"]["done"], doc["counts"]["failed"]) == (3, 1)
                by = {it["name"]: it for it in doc["items"]}
                assert "corrupt_file" in by["corrupt.dng"]["error"]
                for i in range(3):
                    rgb = by[f"im{i}.dng"]["illuminant"]["camera_rgb"]
                    assert angular_error(rgb, truths[i].light_rgb) < 0.25  # in-model, as above
                    out = os.path.join(runner.store.batch_dir(bid), "out", f"im{i}.png")
                    assert cv2.imread(out).shape == (160, 240, 3)
            shared = runner.store.progress(ids["shared"])
            assert shared["shared_light"]["images"] == 3
            rgbs = {tuple(it["illuminant"]["camera_rgb"]) for it in shared["items"] if it["status"] == "done"}
            assert len(rgbs) == 1
        finally:
            runner.stop()


def test_unreachable_dask_scheduler_is_reported_not_hidden(tmp_path, dngs):
    """No scheduler listening: the items stay pending and the runner says why."""
    pytest.importorskip("distributed")
    import socket

    with socket.socket() as s:  # a loopback port with nothing listening
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    runner = jobs.BatchRunner(jobs.RunnerConfig(str(tmp_path / "data"), dask_scheduler=f"tcp://127.0.0.1:{port}",
                                                 dask_timeout=2))
    bid = runner.store.new_batch_id()
    d, _ = dngs
    runner.store.create_batch(bid, jobs.batch_options(format="png"), [("im0.dng", str(d / "im0.dng"))])
    runner._tick()
    assert runner.executor_error.startswith("executor_unavailable")
    assert runner.store.counts(bid)["pending"] == 1
