"""A local service a web page cannot drive (issue 10, item 6): the Host and
Origin checks and the page's security headers through the ASGI app
(:mod:`service.security`), and connections that send nothing closed by a
real server (``python -m service``)."""

from __future__ import annotations

import asyncio
import json
import socket
import time

import httpx
import pytest
from fastapi.testclient import TestClient

from service.app import app

from .conftest import running_server


def _client(host: str = "127.0.0.1:8000") -> TestClient:
    return TestClient(app, base_url=f"http://{host}")


@pytest.mark.parametrize("host", ["127.0.0.1:8000", "localhost:8000", "localhost", "[::1]:8000",
                                  "LOCALHOST:1"])
def test_the_loopback_names_are_served(env_settings, host):
    env_settings(allowed_hosts="")
    r = _client(host).get("/health")
    assert r.status_code == 200, r.text


@pytest.mark.parametrize("host", ["attacker.example", "attacker.example:8000", "127.0.0.1.attacker.example",
                                  "localhost.attacker.example:8000", "0.0.0.0:8000", ""])
def test_any_other_host_is_a_400_json(env_settings, host):
    """A DNS-rebinding page reaches 127.0.0.1 with its own name in Host."""
    env_settings(allowed_hosts="")
    with _client() as c:
        for method, path in (("GET", "/health"), ("GET", "/"), ("POST", "/v1/analyze")):
            r = c.request(method, path, headers={"host": host})
            assert r.status_code == 400, (method, path, r.text)
            assert r.json()["error"] == "host_not_allowed" and isinstance(r.json()["detail"], str)


def test_allowed_hosts_setting_adds_names_and_the_bound_host_is_served(env_settings):
    env_settings(allowed_hosts="photos.lan, other.lan:9000", host="192.168.1.5")
    for host in ("photos.lan", "photos.lan:8000", "other.lan", "192.168.1.5:8000", "localhost"):
        assert _client(host).get("/health").status_code == 200, host
    assert _client("evil.lan").get("/health").status_code == 400


def test_cross_origin_state_changing_requests_are_403(env_settings):
    """A page on another origin can send a multipart POST without a preflight;
    the Origin header gives it away. Same-origin POSTs (the service's page)
    and clients that send no Origin (curl, scripts) are served."""
    env_settings(allowed_hosts="", allowed_origins="http://tools.lan:3000", batch_root="")
    with _client() as c:
        for origin in ("http://attacker.example", "null", "http://localhost:8000", "http://127.0.0.1:8001",
                       "https://127.0.0.1:8000"):
            for path in ("/v1/batches", "/v1/analyze", "/v1/render"):
                r = c.post(path, data={"folder": "x"}, headers={"origin": origin})
                assert r.status_code == 403, (origin, path, r.text)
                assert r.json()["error"] == "cross_origin"
            r = c.delete("/v1/batches/0123456789abcdef", headers={"origin": origin})
            assert r.status_code == 403
            # reading is not refused by Origin (the browser's CORS rule keeps the answer from the page)
            assert c.get("/health", headers={"origin": origin}).status_code == 200
        # the page's own origin, a listed origin and no Origin at all reach the endpoint (its own 4xx)
        for headers in ({"origin": "http://127.0.0.1:8000"}, {"origin": "http://tools.lan:3000"}, {}):
            r = c.post("/v1/batches", data={"folder": "x"}, headers=headers)
            assert r.status_code == 403 and r.json()["error"] == "folder_mode_disabled", (headers, r.text)


def test_the_page_has_a_csp_nosniff_and_frame_protection(env_settings):
    env_settings(allowed_hosts="")
    with _client() as c:
        page = c.get("/")
        assert page.status_code == 200
        csp = page.headers["content-security-policy"]
        directives = dict(d.strip().split(" ", 1) for d in csp.split(";"))
        assert directives["script-src"] == "'self'" and directives["style-src"] == "'self'"
        assert directives["frame-ancestors"] == "'none'" and directives["object-src"] == "'none'"
        assert page.headers["x-frame-options"] == "DENY"
        assert page.headers["x-content-type-options"] == "nosniff"
        # the CSP allows no inline script, style or handler: the page must have none
        html = page.text
        for bad in ("<script>", "<style", " style=", " onsubmit=", " onclick=", " onload=", "javascript:"):
            assert bad not in html, bad
        for path in ("/static/app.js", "/static/style.css", "/health", "/nope"):
            r = c.get(path)
            assert r.headers["x-content-type-options"] == "nosniff", path
            assert r.headers["x-frame-options"] == "DENY", path


# ---------------------------------------------------------------------------
# Slow and silent clients
# ---------------------------------------------------------------------------

def test_a_body_that_stops_arriving_is_cut_off_with_a_408(env_settings):
    """The client sends the headers and part of the body, then nothing: after
    WANDELL_BODY_TIMEOUT (0.5 s here) the app answers 408 body_timeout with
    Connection: close, instead of holding the connection for ever."""
    env_settings(body_timeout=0.5)
    head = (b'--zz\r\nContent-Disposition: form-data; name="file"; filename="a.dng"\r\n'
            b"Content-Type: application/octet-stream\r\n\r\n")
    chunks = [head, b"\0" * 1000]
    sent = []

    async def receive():
        if chunks:
            return {"type": "http.request", "body": chunks.pop(0), "more_body": True}
        await asyncio.sleep(3600)  # the client went silent

    async def send(message):
        sent.append(message)

    scope = {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": "POST",
             "scheme": "http", "path": "/v1/analyze", "raw_path": b"/v1/analyze", "query_string": b"",
             "root_path": "", "headers": [(b"host", b"127.0.0.1:8000"),
                                          (b"content-type", b"multipart/form-data; boundary=zz"),
                                          (b"transfer-encoding", b"chunked")],
             "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 8000)}
    t0 = time.monotonic()
    asyncio.run(asyncio.wait_for(app(scope, receive, send), 20))
    took = time.monotonic() - t0
    start = [m for m in sent if m["type"] == "http.response.start"]
    body = b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body")
    assert len(start) == 1 and start[0]["status"] == 408, sent
    assert json.loads(body)["error"] == "body_timeout"
    assert (b"connection", b"close") in start[0]["headers"]
    assert 0.5 <= took < 10


def _closed_within(sock: socket.socket, seconds: float) -> bool:
    """True if the server closes ``sock`` (EOF or reset) within ``seconds``."""
    sock.settimeout(seconds)
    try:
        while sock.recv(4096):
            pass
        return True
    except ConnectionResetError:
        return True
    except socket.timeout:
        return False


def test_a_real_server_closes_silent_and_slow_connections():
    """``python -m service`` with WANDELL_KEEP_ALIVE_TIMEOUT=1 and
    WANDELL_BODY_TIMEOUT=1: a connection that sends nothing, one that sends
    half a request line, one that stops mid-body, and an idle keep-alive
    connection after a response are all closed within a few seconds (1 s
    plus scheduling on a loaded 2-core machine: 8 s), while a normal request
    is answered."""
    with running_server({"keep_alive_timeout": 1, "body_timeout": 1}) as (base, _, _):
        port = int(base.rsplit(":", 1)[1])
        silent = socket.create_connection(("127.0.0.1", port))
        partial = socket.create_connection(("127.0.0.1", port))
        partial.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # headers never finished
        body = socket.create_connection(("127.0.0.1", port))
        body.sendall(b"POST /v1/analyze HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 100000\r\n"
                     b"Content-Type: multipart/form-data; boundary=zz\r\n\r\n--zz\r\n")
        idle = socket.create_connection(("127.0.0.1", port))
        idle.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        t0 = time.monotonic()
        for name, s in (("silent", silent), ("partial headers", partial), ("stalled body", body),
                        ("idle keep-alive", idle)):
            assert _closed_within(s, max(0.1, 8 - (time.monotonic() - t0))), f"{name} connection still open"
            s.close()
        assert httpx.get(base + "/health", timeout=10).status_code == 200
