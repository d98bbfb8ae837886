"""Configurable limits (issue 6): upload size and pixel count from the
environment (``WANDELL_*``, :mod:`service.settings`), honoured for declared
and for streamed request bodies (:mod:`service.limits`)."""

from __future__ import annotations


import httpx
import pytest
from fastapi.testclient import TestClient

from benchmarks import fuzz
from service.app import app
from service.limits import FRAMING

from .conftest import asgi_post_stream


@pytest.fixture(scope="module")
def seeds():
    return fuzz.seed_dngs()


# ---------------------------------------------------------------------------
# Limits from the environment (WANDELL_*; service.settings)
# ---------------------------------------------------------------------------

def test_upload_limit_is_read_from_the_environment(env_settings, seeds):
    data = seeds[0]
    env_settings(max_upload_bytes=len(data) - 1)
    with TestClient(app) as c:
        r = c.post("/v1/analyze", files={"file": ("a.dng", data, "image/x-adobe-dng")})
        assert r.status_code == 413 and r.json()["error"] == "file_too_large", r.text
        assert c.get("/health").json()["max_upload_bytes"] == len(data) - 1
    env_settings(max_upload_bytes=len(data))
    with TestClient(app) as c:
        assert c.post("/v1/analyze", files={"file": ("a.dng", data, "image/x-adobe-dng")}).status_code == 200


def test_declared_body_over_the_limit_is_refused_before_reading(env_settings):
    """The middleware refuses a Content-Length above the limit plus 1 MiB of
    multipart framing, without reading the body."""
    env_settings(max_upload_bytes=1000)
    with TestClient(app) as c:
        r = c.post("/v1/analyze", content=b"x" * (1000 + 1024 * 1024 + 1),
                   headers={"content-type": "multipart/form-data; boundary=zz"})
    assert r.status_code == 413 and r.json()["error"] == "file_too_large", r.text


def test_pixel_limit_is_read_from_the_environment(env_settings, seeds):
    _, _, _, h, w = fuzz.SEEDS[0]
    env_settings(max_pixels=h * w - 1)
    with TestClient(app) as c:
        r = c.post("/v1/analyze", files={"file": ("a.dng", seeds[0], "image/x-adobe-dng")})
        assert r.status_code == 413 and r.json()["error"] == "too_many_pixels", r.text
        assert c.get("/health").json()["max_pixels"] == h * w - 1
    env_settings(max_pixels=h * w)
    with TestClient(app) as c:
        assert c.post("/v1/analyze", files={"file": ("a.dng", seeds[0], "image/x-adobe-dng")}).status_code == 200


def test_streamed_body_over_the_limit_is_cut_off_while_reading(env_settings):
    """A chunked body (no Content-Length) of 64 chunks of 64 kB against a
    limit of 1000 bytes + FRAMING (1 MiB): the app stops reading at the first
    chunk past the allowance and answers 413 file_too_large, so at most
    allowance + one chunk is ever received (not the 4 MiB sent)."""
    env_settings(max_upload_bytes=1000)
    chunk = 64 * 1024
    head = (b'--zz\r\nContent-Disposition: form-data; name="file"; filename="a.dng"\r\n'
            b"Content-Type: application/octet-stream\r\n\r\n")
    chunks = [head] + [b"\0" * chunk] * 64 + [b"\r\n--zz--\r\n"]
    start, body, consumed = asgi_post_stream("/v1/analyze", chunks, [
        (b"content-type", b"multipart/form-data; boundary=zz"), (b"transfer-encoding", b"chunked")])
    assert len(start) == 1 and start[0]["status"] == 413
    assert body["error"] == "file_too_large"
    assert consumed <= 1000 + FRAMING + chunk
    assert chunks, "the whole body was read"


def test_streamed_body_under_the_limit_is_read_whole(env_settings, seeds):
    """The same path without Content-Length for a body within the limit: the
    upload is analysed (200), nothing cut off."""
    env_settings(max_upload_bytes=len(seeds[0]))
    with TestClient(app) as c:
        # a generator body is sent chunked, without Content-Length
        files = {"file": ("a.dng", seeds[0], "image/x-adobe-dng")}
        req = httpx.Request("POST", "http://test/v1/analyze", files=files)
        payload = req.read()
        r = c.post("/v1/analyze", content=iter([payload[:1000], payload[1000:]]),
                   headers={"content-type": req.headers["content-type"]})
    assert r.status_code == 200, r.text


def test_content_length_that_is_not_a_number_is_a_400(env_settings):
    env_settings(max_upload_bytes=1000)
    with TestClient(app) as c:
        r = c.post("/v1/analyze", content=b"x", headers={"content-length": "lots", "content-type": "text/plain"})
    assert r.status_code == 400 and r.json()["error"] == "bad_content_length"


def test_body_pieces_are_joined_up_to_a_mebibyte():
    # the server hands the body on 64 KiB at a time; the app gets it in
    # pieces of about 1 MiB (issue 19: one spooled-file write on a worker
    # thread per piece), the same bytes in order, and a disconnect that
    # comes in the middle after the body so far
    import asyncio

    from service.limits import COALESCE_BYTES, UploadLimitMiddleware

    pieces = [bytes([i % 251]) * 65536 for i in range(40)]
    seen = []

    async def app(scope, receive, send):
        while True:
            m = await receive()
            seen.append(m)
            if m["type"] != "http.request" or not m.get("more_body"):
                break

    def run(messages):
        seen.clear()
        queue = list(messages)

        async def receive():
            return queue.pop(0)

        async def send(message):
            pass

        scope = {"type": "http", "path": "/v1/analyze", "method": "POST", "headers": []}
        asyncio.run(UploadLimitMiddleware(app)(scope, receive, send))
        return list(seen)

    msgs = [{"type": "http.request", "body": p, "more_body": i < len(pieces) - 1} for i, p in enumerate(pieces)]
    got = run(msgs)
    assert b"".join(m["body"] for m in got) == b"".join(pieces)
    assert all(len(m["body"]) <= COALESCE_BYTES for m in got) and len(got) == 3
    assert [m["more_body"] for m in got] == [True, True, False]
    got = run(msgs[:5] + [{"type": "http.disconnect"}])
    assert [m["type"] for m in got] == ["http.request", "http.disconnect"]
    assert got[0]["body"] == b"".join(pieces[:5]) and got[0]["more_body"]
