"""The FastAPI app through its ASGI stack (httpx + TestClient)."""

from __future__ import annotations

from fastapi.testclient import TestClient

from service.app import app


def test_health_and_openapi():
    with TestClient(app) as client:
        r = client.get("/health")
        assert r.status_code == 200
        body = r.json()
        assert body["status"] == "ok" and body["max_upload_bytes"] == 200 * 1024 * 1024
        assert client.get("/openapi.json").json()["paths"]["/health"]
        assert client.get("/docs").status_code == 200
