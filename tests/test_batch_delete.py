"""Issue 29, item 6: disk the user controls. ``DELETE /v1/batches/{id}``
removes a batch that is over with its inputs and results (a running one is
cancelled first, as before, and removed by a second DELETE once settled),
``POST .../cancel`` only cancels, ``GET /v1/batches`` lists what is kept
and its size, and ``WANDELL_BATCH_RESULT_RETENTION`` removes finished
batches by themselves. Through the real app (TestClient) on a data
directory of the test's own."""

from __future__ import annotations

import io
import os
import time

from testing.dngwriter import scene_dng


def _dng(seed=1) -> bytes:
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", 96, 128, seed=seed)
    return buf.getvalue()


def _settle(client, bid, timeout=120):
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        doc = client.get(f"/v1/batches/{bid}").json()
        if doc.get("settled"):
            return doc
        time.sleep(0.1)
    raise AssertionError(f"batch {bid} not settled: {doc}")


def _batch(client, n=2):
    r = client.post("/v1/batches", files=[("files", (f"im{i}.dng", _dng(i))) for i in range(n)],
                    data={"format": "tiff"})
    assert r.status_code == 202, r.text
    return r.json()["id"]


def test_delete_removes_a_finished_batch_and_its_files(app_with):
    client, data = app_with()
    bid = _batch(client)
    doc = _settle(client, bid)
    assert doc["counts"]["done"] == 2
    listed = client.get("/v1/batches").json()
    mine = next(b for b in listed["batches"] if b["id"] == bid)
    assert mine["bytes"] > 2 * 96 * 128 * 6 and mine["counts"]["done"] == 2 and mine["url"] == f"/v1/batches/{bid}"
    assert listed["bytes"] >= mine["bytes"] and listed["result_retention_s"] == 7 * 24 * 3600
    folder = data / "batches" / bid
    assert folder.is_dir()
    # a plain DELETE (a cancel) of a batch that is over deletes nothing
    r = client.delete(f"/v1/batches/{bid}")
    assert r.status_code == 200 and r.json()["deleted"] is False and "remove=true" in r.json()["note"], r.text
    assert folder.is_dir() and client.get(f"/v1/batches/{bid}/items/by-index/0").status_code == 200
    r = client.delete(f"/v1/batches/{bid}?remove=true")
    assert r.status_code == 200, r.text
    assert r.json() == {"id": bid, "deleted": True, "freed_bytes": mine["bytes"]}
    assert not folder.exists() and not any(p.name.endswith(bid) for p in data.iterdir())
    for url in (f"/v1/batches/{bid}", f"/v1/batches/{bid}/items/by-index/0", f"/v1/batches/{bid}/zip"):
        assert client.get(url).status_code == 404, url
    assert client.delete(f"/v1/batches/{bid}?remove=true").status_code == 404
    assert bid not in [b["id"] for b in client.get("/v1/batches").json()["batches"]]


def test_delete_of_a_running_batch_cancels_it_first(app_with):
    client, data = app_with()
    bid = _batch(client, n=6)
    r = client.delete(f"/v1/batches/{bid}")
    assert r.status_code == 200 and r.json()["deleted"] is False and r.json()["status"] == "cancelled", r.text
    assert (data / "batches" / bid).is_dir()          # cancelled, nothing removed yet
    t_end, answers = time.monotonic() + 120, set()
    while time.monotonic() < t_end:
        r = client.delete(f"/v1/batches/{bid}?remove=true")
        answers.add(r.status_code)
        if r.status_code == 200:
            break
        assert r.status_code == 409 and r.json()["error"] == "not_settled", r.text
        time.sleep(0.05)
    assert r.json()["deleted"] is True and not (data / "batches" / bid).exists(), answers


def test_cancel_only_cancels(app_with):
    client, data = app_with()
    bid = _batch(client, n=4)
    r = client.post(f"/v1/batches/{bid}/cancel")
    assert r.status_code == 200 and r.json()["status"] in ("cancelled", "done"), r.text
    doc = _settle(client, bid)
    assert doc["status"] in ("cancelled", "done") and (data / "batches" / bid).is_dir()
    assert client.post("/v1/batches/0123456789abcdef/cancel").status_code == 404


def test_result_retention_removes_finished_batches(app_with):
    client, data = app_with(batch_result_retention=0.5)
    bid = _batch(client, n=1)
    _settle(client, bid)
    t_end = time.monotonic() + 60
    while client.get(f"/v1/batches/{bid}").status_code != 404 and time.monotonic() < t_end:
        time.sleep(0.2)
    assert client.get(f"/v1/batches/{bid}").status_code == 404
    assert not (data / "batches" / bid).exists()


def test_negative_result_retention_keeps_them(app_with):
    client, data = app_with(batch_result_retention=-1, batch_input_retention=-1)
    bid = _batch(client, n=1)
    _settle(client, bid)
    from service.routers.batches import get_runner

    assert get_runner().remove_expired_batches() == []
    assert client.get(f"/v1/batches/{bid}").status_code == 200 and os.listdir(data / "batches" / bid / "out")


def test_the_suite_never_writes_into_the_users_store():
    """tests/conftest.py points WANDELL_DATA_DIR at a folder of the session
    (the servers the tests start inherit it; the web-page tests give theirs
    their own): never the default ~/.cache/wandell."""
    import tempfile

    from service.jobs import default_data_dir

    here = os.path.realpath(os.environ["WANDELL_DATA_DIR"])
    assert here.startswith(os.path.realpath(tempfile.gettempdir()) + os.sep)
    assert here != os.path.realpath(default_data_dir())


def test_wandell_batches_lists_and_removes(app_with, capsys):
    from service import cli

    client, data = app_with()
    first, second = _batch(client, n=1), _batch(client, n=1)
    _settle(client, first)
    _settle(client, second)
    assert cli.main(["batches"]) == 0
    out = capsys.readouterr().out
    assert f"2 batches under {data}" in out and first in out and second in out and "1/1 done" in out
    assert cli.main(["batches", "--remove", first, "nosuchbatch"]) == 1
    captured = capsys.readouterr()
    assert f"removed {first}" in captured.out and "not_found" in captured.err
    assert client.get(f"/v1/batches/{first}").status_code == 404 and not (data / "batches" / first).exists()
    assert cli.main(["batches", "--older-than", "1"]) == 0     # finished seconds ago: kept
    assert client.get(f"/v1/batches/{second}").status_code == 200
    assert cli.main(["batches", "--older-than", "0"]) == 0
    assert f"removed {second}" in capsys.readouterr().out
    assert client.get(f"/v1/batches/{second}").status_code == 404
