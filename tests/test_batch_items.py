"""Batch items by index and by name, store recovery and stale temporaries
(issue 17, items 5, 6, 7 and 12): the reproductions ``item_lookup.py``,
``item_index_name.py``, ``store_recovery_names.py`` and
``kill9_part_file.py`` through the ASGI app with its lifespan (the runner),
plus the job store and the temporary clean-up on their own."""

from __future__ import annotations

import io
import os
import time

import cv2
import numpy as np
from fastapi.testclient import TestClient

from service import jobs
from service.routers import batches
from service.app import app
from testing.dngwriter import scene_dng

from .test_batch_robustness import OPTS, _wait, batch_env  # noqa: F401 - batch_env is a fixture


def _dng(h=48, w=64, seed=1) -> bytes:
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D50", h, w, seed=seed)
    return buf.getvalue()


def _shape(content: bytes):
    img = cv2.imdecode(np.frombuffer(content, np.uint8), cv2.IMREAD_UNCHANGED)
    return None if img is None else img.shape[:2]


def test_odd_item_keys_are_404_not_500(batch_env):
    """item_lookup.py: items/² (str.isdigit() is true, int() refuses it) was a
    500 ValueError and items/99999999999999999999 (beyond SQLite's 64-bit
    integers) a 500 OverflowError. Both are 404, under every item URL."""
    batch_env()
    with TestClient(app, raise_server_exceptions=False) as c:
        r = c.post("/v1/batches", files=[("files", ("a.dng", _dng()))], data=OPTS)
        bid = r.json()["id"]
        assert _wait(c, bid)["counts"]["done"] == 1
        assert c.get(f"/v1/batches/{bid}/items/0").status_code == 200
        for key in ("%C2%B2", "99999999999999999999", "9" * 400, "-1", "%20" + "0", "0x0", "%D9%A0"):
            for path in ("items", "items/by-index", "items/by-name"):
                got = c.get(f"/v1/batches/{bid}/{path}/{key}")
                assert got.status_code == 404 and got.json()["error"] == "not_found", (path, key, got.text)
    store = jobs.JobStore(str(batch_env() / "data"))
    assert store.item(bid, "\u00b2") is None and store.item_by_index(bid, 10 ** 20) is None
    assert store.item_by_index(bid, "0")["name"] == "a.dng"


def test_a_file_named_like_an_index_never_takes_another_items_url(batch_env):
    """item_index_name.py: in a batch of holiday.dng (item 0) and a file
    named "0" (item 1), item 0's advertised url (items/0, looked up by name
    first) served item 1's image. The url is now items/by-index/N, which
    only ever means that index; items/by-name/NAME only that name; the older
    items/KEY still serves unambiguous keys and answers 409 ambiguous_item
    when KEY is one item's name and another's index."""
    batch_env()
    sizes = {"holiday.dng": (48, 64), "0": (40, 56)}
    files = [("files", (n, _dng(h, w, seed=i))) for i, (n, (h, w)) in enumerate(sizes.items())]
    with TestClient(app) as c:
        r = c.post("/v1/batches", files=files, data=OPTS)
        bid = r.json()["id"]
        doc = _wait(c, bid)
        assert [(it["index"], it["name"], it["status"]) for it in doc["items"]] == \
            [(0, "holiday.dng", "done"), (1, "0", "done")]
        for it in doc["items"]:
            assert it["url"] == f"/v1/batches/{bid}/items/by-index/{it['index']}"
            got = c.get(it["url"])
            assert got.status_code == 200 and _shape(got.content) == sizes[it["name"]], it
            by_name = c.get(f"/v1/batches/{bid}/items/by-name/{it['name']}")
            assert by_name.status_code == 200 and by_name.content == got.content
        base = f"/v1/batches/{bid}/items"
        amb = c.get(f"{base}/0")
        assert amb.status_code == 409 and amb.json()["error"] == "ambiguous_item", amb.text
        assert "by-index/0" in amb.json()["detail"] and "by-name/0" in amb.json()["detail"]
        assert _shape(c.get(f"{base}/holiday.dng").content) == sizes["holiday.dng"]
        assert _shape(c.get(f"{base}/1").content) == sizes["0"]
        assert c.get(f"{base}/by-name/1").status_code == 404
        assert c.get(f"{base}/by-index/2").status_code == 404


def _damage(data_dir) -> None:
    path = data_dir / "jobs.sqlite"
    path.write_bytes(b"this is not a database " * 200)
    for suffix in ("-wal", "-shm"):
        if (data_dir / ("jobs.sqlite" + suffix)).exists():
            (data_dir / ("jobs.sqlite" + suffix)).unlink()


def _items(doc) -> list:
    return [{k: it.get(k) for k in ("index", "name", "status", "output", "error", "url", "illuminant")}
            for it in doc["items"]]


def test_store_recovery_gives_back_the_same_items_indices_and_states(batch_env):
    """store_recovery_names.py: after a damaged jobs.sqlite was recovered, a
    done item named .hidden.dng came back failed (outputs starting with '.'
    were skipped), A.dng (stored as "A (2).dng") came back twice (done, and
    failed under its original name) and indices were renumbered. Each batch
    now keeps a manifest of its items and a journal of their states: the
    same items at the same indices in the same states (errors included),
    the same bytes at the same urls, and a batch that had not finished is
    queued again and finishes."""
    base = batch_env()
    names = ["a.dng", "A.dng", ".hidden.dng", "broken.dng", "b.dng"]
    data = {n: _dng(seed=i) for i, n in enumerate(names)}
    data["broken.dng"] = b"II*\x00" + b"\x13" * 500
    with TestClient(app) as c:
        bid = c.post("/v1/batches", files=[("files", (n, data[n])) for n in names], data=OPTS).json()["id"]
        before = _wait(c, bid)
        assert [it["status"] for it in before["items"]] == ["done", "done", "done", "failed", "done"]
        assert [it["name"] for it in before["items"]] == ["a.dng", "A (2).dng", ".hidden.dng", "broken.dng",
                                                          "b.dng"]
        images = {it["url"]: c.get(it["url"]).content for it in before["items"] if it.get("url")}
    batches.stop_runner()
    _damage(base / "data")
    store = jobs.JobStore(str(base / "data"))  # a batch that was waiting when the store broke
    waiting = store.new_batch_id()
    src = base / "waiting.dng"
    src.write_bytes(data["a.dng"])
    store.create_batch(waiting, jobs.batch_options(**OPTS), [("w.dng", str(src)), ("x.dng", str(src))])
    store.fail_item(waiting, 1, "some_error: given up")
    del store
    _damage(base / "data")
    with TestClient(app) as c:
        health = c.get("/health").json()["job_store"]
        assert health["status"] == "recovered", health
        after = c.get(f"/v1/batches/{bid}").json()
        assert after["status"] == "done" and _items(after) == _items(before)
        assert health["batches_recovered"] == 2, health
        for url, content in images.items():
            assert c.get(url).content == content, url
        doc = _wait(c, waiting)
        assert [(it["name"], it["status"], it.get("error")) for it in doc["items"]] == \
            [("w.dng", "done", None), ("x.dng", "failed", "some_error: given up")]


def _plant(out_dir, name: str) -> list:
    """Stale temporaries of output ``name`` as atomic_write names them (the
    image's beside it, the sidecar's in .wandell), as a kill -9 leaves them."""
    (out_dir / ".wandell").mkdir(parents=True, exist_ok=True)
    paths = [out_dir / f".{name}.k9abc_12.part", out_dir / ".wandell" / f".{name}.json.zz9x0q1w.part"]
    for p in paths:
        p.write_bytes(b"half written")
    return paths


def test_stale_temporaries_go_only_when_nobody_writes_them(tmp_path):
    """kill9_part_file.py, the rule: only atomic_write's own pattern
    (.NAME.XXXXXXXX.part), only while the output's item lock is free (a
    writer at work holds it), never another file."""
    import fcntl

    out = tmp_path / "out"
    stale = _plant(out, "a.png")
    busy = _plant(out, "b.png")
    keep = [out / n for n in (".mine.part", "notes.part", ".a.png.ABCDEFGH.part", ".a.png.abc.part", "a.png",
                              ".a.png.abcd1234.part.txt")] + [out / ".wandell" / ".notes.txt.abcd1234.part"]
    for p in keep:
        p.write_bytes(b"user")
    fd = os.open(jobs.meta_path(str(out / "b.png"), ".lock"), os.O_CREAT | os.O_RDWR)
    fcntl.flock(fd, fcntl.LOCK_EX)  # b.png is being written
    try:
        assert sorted(jobs.remove_stale_temporaries(str(out), {"c.png"})) == []
        assert sorted(jobs.remove_stale_temporaries(str(out))) == sorted(map(str, stale))
        assert all(p.exists() for p in busy + keep)
    finally:
        os.close(fd)
    assert sorted(jobs.remove_stale_temporaries(str(out))) == sorted(map(str, busy))
    assert all(p.exists() for p in keep)


def test_a_killed_writers_temporaries_are_removed_on_restart_and_rerun(batch_env, tmp_path):
    """kill9_part_file.py: kill -9 mid-write left .NAME.XXXXXXXX.part in the
    batch's out/ for ever. The runner now removes stale temporaries of every
    batch at start-up and of a batch when it finishes, and an item being
    (re)run removes its own output's under its lock; the CLI removes those
    of its batch's outputs and (unlike before) no other file of OUT_DIR."""
    from concurrent.futures import ThreadPoolExecutor

    from service import cli

    base = batch_env()
    with TestClient(app) as c:
        bid = c.post("/v1/batches", files=[("files", ("a.dng", _dng()))], data=OPTS).json()["id"]
        assert _wait(c, bid)["counts"]["done"] == 1
    batches.stop_runner()
    out = base / "data" / "batches" / bid / "out"
    stale = _plant(out, "a.png") + _plant(out, "gone.png")
    with TestClient(app) as c:
        t_end = time.monotonic() + 20
        while any(p.exists() for p in stale) and time.monotonic() < t_end:
            time.sleep(0.1)
        assert not [p for p in stale if p.exists()]
        assert c.get(f"/v1/batches/{bid}/items/by-index/0").status_code == 200
    src = tmp_path / "in" / "x.dng"
    src.parent.mkdir()
    src.write_bytes(_dng())
    item_out = tmp_path / "item" / "x.png"
    stale = _plant(item_out.parent, "x.png")
    t = jobs.ItemTask(src=str(src), out=str(item_out), name="x.dng", options=jobs.batch_options(**OPTS),
                      max_pixels=10 ** 8, estimation_pixels=10 ** 6)
    assert jobs.process_item(t)["status"] == "done" and not [p for p in stale if p.exists()]
    cli_out = tmp_path / "cli"
    stale = _plant(cli_out, "x.png")
    mine = [cli_out / ".holiday.part", cli_out / ".other.png.abcd1234.part"]
    for p in mine:
        p.write_bytes(b"the user's")
    with ThreadPoolExecutor(1) as ex:
        rows = cli.run_batch(str(src.parent), str(cli_out), jobs.batch_options(**OPTS), executor=ex, quiet=True)
    assert [r["status"] for r in rows] == ["done"]
    assert not [p for p in stale if p.exists()] and all(p.read_bytes() == b"the user's" for p in mine)


def test_a_batch_from_before_manifests_is_rebuilt_from_its_input_names(tmp_path):
    """Batches written before the manifest (no batch.json / states.jsonl):
    the inputs' stored names (NNNNN-name) are named again as create_batch
    named them, so "A (2).dng" matches its output and ".hidden.dng" its
    .hidden.png (skipped before): same indices, done where finished, the
    others failed."""
    data = tmp_path / "data"
    store = jobs.JobStore(str(data))
    bid = store.new_batch_id()
    bdir = data / "batches" / bid
    names = ["a.dng", "A.dng", ".hidden.dng", "lost.dng"]
    srcs = []
    for i, n in enumerate(names):
        srcs.append(bdir / "in" / f"{i:05d}-{n}")
        srcs[-1].write_bytes(b"raw")
    opts = jobs.batch_options(**OPTS)
    store.create_batch(bid, opts, [(n, str(p)) for n, p in zip(names, srcs)])
    rows = store.items(bid)
    assert [r["name"] for r in rows] == ["a.dng", "A (2).dng", ".hidden.dng", "lost.dng"]
    for r in rows[:3]:  # finished as process_item leaves them (before the sidecar had an index)
        (bdir / "out" / os.path.basename(r["out"])).write_bytes(b"png")
        os.makedirs(bdir / "out" / ".wandell", exist_ok=True)
        (bdir / "out" / ".wandell" / (os.path.basename(r["out"]) + ".json")).write_text(
            '{"name": "%s", "illuminant": {"cct": 5000}, "options": %s}' % (r["name"], opts.to_json()))
    (bdir / jobs.MANIFEST).unlink()
    del store
    _damage(data)
    store = jobs.JobStore(str(data))
    assert store.recovered["batches_recovered"] == 1
    got = [(r["idx"], r["name"], r["status"], os.path.basename(r["out"])) for r in store.items(bid)]
    assert got == [(0, "a.dng", "done", "a.png"), (1, "A (2).dng", "done", "A (2).png"),
                   (2, ".hidden.dng", "done", ".hidden.png"), (3, "lost.dng", "failed", "lost.png")]
