"""Round 4 of probing the service as a hostile-but-realistic user would
(docs/probe_round4.md): each test is the minimal reproduction of one fault
found, through the real ASGI stack (FastAPI's TestClient), and holds once
the fault is fixed."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from service.schemas import responses as R

from .conftest import isolated_app_client, scene_dng_bytes


@pytest.fixture(scope="module")
def dng() -> bytes:
    return scene_dng_bytes(64, 96)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")


def _strict(text: str):
    def bad(name):
        raise ValueError(f"non-finite JSON constant {name}")
    return json.loads(text, parse_constant=bad)


@pytest.mark.parametrize("fmt", ["xmp", "dng"])
def test_response_json_answers_json_whatever_the_format(client, dng, fmt):
    """``response=json`` is "the estimate and correction matrix only"
    (README, the field's description), but with ``format=xmp`` or
    ``format=dng`` the answer was the sidecar (application/rdf+xml) or the
    DNG: a client asking for JSON got a file it cannot parse."""
    r = client.post("/v1/white-balance", files={"file": ("s.dng", dng)},
                    data={"format": fmt, "response": "json"})
    assert r.status_code == 200, r.text[:300]
    assert r.headers["content-type"].startswith("application/json"), r.headers["content-type"]
    R.WhiteBalanceResult.model_validate(_strict(r.text))


def test_a_repeated_form_field_is_refused_not_resolved_to_its_last_value(client, dng):
    """``method=auto&method=bayes`` ran bayes with a 200 (FastAPI keeps the
    last value), as a misspelled field was ignored before issue 29: the
    user cannot tell which of the two was used. Now a 422 naming the field;
    a list field (a batch's ``files``) still takes one value per part."""
    f = {"file": ("s.dng", dng)}
    r = client.post("/v1/analyze", files=f, data={"method": ["auto", "bayes"]})
    assert r.status_code == 422, r.text[:300]
    body = _strict(r.text)
    assert body["error"] == "repeated_field" and "'method'" in body["detail"]
    r = client.post("/v1/white-balance", files=[("file", ("a.dng", dng)), ("file", ("b.dng", dng))],
                    data={"format": "png"})
    assert r.status_code == 422 and "'file'" in r.json()["detail"], r.text[:300]
    r = client.delete("/v1/batches/0123456789abcdef?remove=true&remove=false")
    assert r.status_code == 422 and r.json()["error"] == "repeated_field", r.text[:300]
    r = client.post("/v1/batches", files=[("files", ("a.dng", dng)), ("files", ("b.dng", dng))],
                    data={"format": "jpeg"})
    assert r.status_code == 202, r.text[:300]


@pytest.mark.parametrize("dims", [{"light_dim": "auto"}, {"surface_dim": "auto", "spatial": "true"}])
def test_automatic_model_order_on_an_image_with_no_usable_pixel_is_a_422(client, dims):
    """``method=maloney-wandell`` with ``surface_dim`` or ``light_dim``
    ``auto`` (BIC) on an image whose every pixel is masked (all saturated
    here) was a 500: ``recovery.model_order.select_dimensions`` took the
    maximum of an empty array. The same request without ``auto`` was the
    422 ``insufficient_surface_variation`` it is now."""
    from testing.dngwriter import write_dng

    buf = io.BytesIO()
    write_dng(buf, np.full((48, 64), 16383, np.uint16), black_level=512, white_level=16383)
    r = client.post("/v1/analyze", files={"file": ("sat.dng", buf.getvalue())},
                    data={"method": "maloney-wandell", **dims})
    assert r.status_code == 422, r.text[:300]
    assert _strict(r.text)["error"] == "insufficient_surface_variation"


def settled(client, bid: str, timeout: float = 120.0) -> dict:
    """The batch's progress document once it is settled (polled)."""
    import time

    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        doc = client.get(f"/v1/batches/{bid}").json()
        if doc.get("settled"):
            return doc
        time.sleep(0.2)
    raise AssertionError(f"batch {bid} not settled in {timeout} s: {doc}")


def zip_while(bid: str, during) -> dict:
    """``GET /v1/batches/{bid}/zip`` through the app's ASGI stack by a client
    that stays connected, calling ``await during(other)`` once, when the
    zip's first bytes have gone out (``other``: a second client on the same
    app and event loop). Returns ``status``, ``body`` and ``during`` (what
    ``during`` returned)."""
    import anyio
    import httpx

    from service.app import app

    got: dict = {"body": b"", "during": None, "called": False}

    async def main():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as other:
            sent = []

            async def receive():      # the request, then a client that stays connected
                if not sent:
                    sent.append(True)
                    return {"type": "http.request", "body": b"", "more_body": False}
                await anyio.sleep_forever()

            async def send(message):
                if message["type"] == "http.response.start":
                    got["status"] = message["status"]
                elif message["type"] == "http.response.body":
                    if not got["called"]:
                        got["called"] = True
                        got["during"] = await during(other)
                    got["body"] += message.get("body", b"")

            path = f"/v1/batches/{bid}/zip"
            scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "GET",
                     "scheme": "http", "path": path, "raw_path": path.encode(),
                     "query_string": b"", "root_path": "", "headers": [(b"host", b"127.0.0.1")],
                     "client": ("127.0.0.1", 50000), "server": ("127.0.0.1", 80)}
            await app(scope, receive, send)

    anyio.run(main)
    return got


def test_deleting_a_batch_while_its_zip_is_downloaded_does_not_cut_the_zip(client, dng):
    """``DELETE /v1/batches/{id}?remove=true`` while ``GET .../zip`` was
    streaming removed the results under it: the next result's ``open``
    failed, the connection was dropped after a 200 and the client held a cut,
    unreadable zip (found against ``python -m service`` with 12 DNG results:
    6 MB of 40 read, ``BadZipFile``). Now the DELETE is a 409 ``downloading``
    while the zip is sent, the zip is whole, and a DELETE after it removes
    the batch. The two requests go through the ASGI stack on one event loop:
    the DELETE is sent when the zip's first bytes have gone out."""
    import zipfile

    r = client.post("/v1/batches", files=[("files", (f"{i}.dng", dng)) for i in range(3)], data={"format": "tiff"})
    assert r.status_code == 202, r.text
    bid = r.json()["id"]
    assert settled(client, bid)["counts"]["done"] == 3

    async def delete(other):
        return await other.delete(f"/v1/batches/{bid}?remove=true")

    got = zip_while(bid, delete)
    assert got["status"] == 200
    assert got["during"].status_code == 409, got["during"].text
    assert _strict(got["during"].text)["error"] == "downloading"
    names = zipfile.ZipFile(io.BytesIO(got["body"])).namelist()
    assert sorted(n for n in names if n.endswith(".tif")) == ["0.tif", "1.tif", "2.tif"], names
    r = client.delete(f"/v1/batches/{bid}?remove=true")
    assert r.status_code == 200 and r.json()["deleted"] is True, r.text
