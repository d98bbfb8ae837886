"""A bound on concurrent heavy work (decode, estimate, demosaic, encode).

Every upload endpoint does its numerical work in a worker thread. Without a
bound, all requests in flight run at once (up to the thread pool's 40
threads): on 2 cores that only slows each of them down, and the memory
peak is the per-request peak (about 2.3 x the decoded 16-bit image, measured
by ``python -m benchmarks.load``) times the number of requests. With at most
``Settings.max_concurrent_work`` (``WANDELL_MAX_CONCURRENT_WORK``; default
the number of CPUs) running and the rest queued first come first served,
the peak is that many images, and the early requests finish early. Light
requests (``/health``, ``/v1/models``) do not wait behind heavy ones: they do
not use this limiter.
"""

from __future__ import annotations

import asyncio
import functools
import os
import weakref

import anyio
import anyio.to_thread

from .settings import get_settings

__all__ = ["run_heavy", "default_concurrency"]

_LIMITERS: "weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, anyio.CapacityLimiter]" = \
    weakref.WeakKeyDictionary()


def default_concurrency() -> int:
    """Heavy jobs at once when the setting is 0: one per CPU this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def _limiter() -> anyio.CapacityLimiter:
    n = get_settings().max_concurrent_work or default_concurrency()
    loop = asyncio.get_running_loop()
    lim = _LIMITERS.get(loop)
    if lim is None:
        lim = _LIMITERS[loop] = anyio.CapacityLimiter(n)
    elif lim.total_tokens != n:
        lim.total_tokens = n
    return lim


async def run_heavy(func, *args, **kwargs):
    """``func(*args, **kwargs)`` in a worker thread, at most
    ``max_concurrent_work`` of them at once (FIFO)."""
    return await anyio.to_thread.run_sync(functools.partial(func, *args, **kwargs), limiter=_limiter())
