"""The bound on concurrent heavy work (service.workers): requests beyond
WANDELL_MAX_CONCURRENT_WORK queue, light endpoints do not wait."""

from __future__ import annotations

import asyncio
import threading
import time

import httpx
import pytest

from service import workers
from service.errors import ServiceError
from service.app import app
from service.routers import analysis
from service.settings import get_settings


class _Probe:
    """Stands in for the decode+estimate step: records how many run at once."""

    def __init__(self, hold: float = 0.05, gate: threading.Event | None = None):
        self.lock = threading.Lock()
        self.now = self.peak = self.calls = 0
        self.hold, self.gate = hold, gate

    def __call__(self, *args, **kwargs):
        with self.lock:
            self.now += 1
            self.calls += 1
            self.peak = max(self.peak, self.now)
        if self.gate is not None:
            self.gate.wait(10)
        else:
            time.sleep(self.hold)
        with self.lock:
            self.now -= 1
        raise ServiceError(422, "probe", "stopped by the test")


async def _fire(n: int, path="/v1/analyze"):
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
        return await asyncio.gather(*(c.post(path, files={"file": ("a.dng", b"II*\0" + bytes(64))})
                                      for _ in range(n)))


@pytest.mark.parametrize("limit", [1, 2, 3])
def test_at_most_the_configured_number_run_at_once(env_settings, monkeypatch, limit):
    """8 simultaneous uploads, each holding its worker 50 ms: the peak number
    running together is exactly the limit (8 > limit, and 50 ms is far longer
    than it takes the event loop to hand out the next token), and every
    request still gets its answer."""
    env_settings(max_concurrent_work=limit)
    probe = _Probe()
    monkeypatch.setattr(analysis, "analyze_upload", probe)
    rs = asyncio.run(_fire(8))
    assert [r.status_code for r in rs] == [422] * 8 and probe.calls == 8
    assert probe.peak == limit


def test_default_is_one_job_per_cpu(env_settings):
    env_settings(max_concurrent_work=0)
    assert workers.default_concurrency() >= 1
    assert get_settings().max_concurrent_work == 0


def test_health_answers_while_heavy_work_fills_every_slot(env_settings, monkeypatch):
    """With the only slot held by a blocked job and more queued, /health
    still answers: light endpoints do not use the heavy-work limiter."""
    env_settings(max_concurrent_work=1)
    gate = threading.Event()
    probe = _Probe(gate=gate)
    monkeypatch.setattr(analysis, "analyze_upload", probe)

    async def scenario():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            heavy = [asyncio.create_task(c.post("/v1/analyze", files={"file": ("a.dng", b"II*\0" + bytes(64))}))
                     for _ in range(3)]
            while probe.calls < 1:
                await asyncio.sleep(0.01)
            h = await asyncio.wait_for(c.get("/health"), 10)
            busy = probe.now
            gate.set()
            done = await asyncio.gather(*heavy)
            return h, busy, done

    h, busy, done = asyncio.run(scenario())
    assert h.status_code == 200 and busy == 1
    assert [r.status_code for r in done] == [422] * 3 and probe.peak == 1
