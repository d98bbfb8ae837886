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

A request whose client has gone away while it waited for a slot is dropped
when its turn comes (:func:`run_heavy` with ``request``): its work would be
answered to nobody and would delay everyone queued behind it. (Work already
running in a thread cannot be interrupted; it runs to its end.)

After each job the C heap is trimmed (glibc ``malloc_trim``): a 24 MP
request allocates a few GB in many mid-sized blocks across the worker
threads' malloc arenas, and without a trim the freed memory stays with the
process instead of going back to the system.

The server also caps glibc's malloc arenas at :data:`MALLOC_ARENAS` (2) when
it starts (:func:`limit_malloc_arenas`, ``mallopt(M_ARENA_MAX)``, before the
first pool thread). By default glibc gives each new thread an arena of its
own, up to 8 per CPU; the pool's threads (the jobs, the uploads spooled to
disk, the batch runner) each kept one, and a trim does not give back what
stays scattered among them: with the decoders' uploads no longer kept by
reference cycles (``service.decode.tiffbytes``), 16 requests of a 10 MP TIFF
sent at once still left the process some 80 MiB (165-200) above what one
request leaves with glibc's default, about 5 with the cap (two work slots,
``python -m benchmarks.request_costs --arenas``; ``docs/limits.md``). A
``MALLOC_ARENA_MAX`` (or ``GLIBC_TUNABLES`` naming ``glibc.malloc.arena_max``)
set in the environment is left as glibc applied it; without glibc's
``mallopt`` (musl, macOS, Windows) nothing is done.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import functools
import logging
import os
import weakref

import anyio
import anyio.to_thread

from .errors import ServiceError
from .settings import get_settings

__all__ = ["run_heavy", "default_concurrency", "work_slots", "trim_memory", "limit_malloc_arenas",
           "MALLOC_ARENAS"]

log = logging.getLogger("service")

_LIMITERS: "weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, anyio.CapacityLimiter]" = \
    weakref.WeakKeyDictionary()


def default_concurrency() -> int:
    """Heavy jobs at once when the setting is 0: one per CPU this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def work_slots() -> int:
    """Heavy jobs allowed at once: ``max_concurrent_work``, or one per CPU when it is 0."""
    return get_settings().max_concurrent_work or default_concurrency()


def _limiter() -> anyio.CapacityLimiter:
    n = work_slots()
    loop = asyncio.get_running_loop()
    lim = _LIMITERS.get(loop)
    if lim is None:
        lim = _LIMITERS[loop] = anyio.CapacityLimiter(n)
    elif lim.total_tokens != n:
        lim.total_tokens = n
    return lim


def _libc():
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:  # no C library ctypes can open (Windows): nothing to tune
        return None


_LIBC = _libc()
_MALLOC_TRIM = getattr(_LIBC, "malloc_trim", None)   # not glibc: nothing to trim

#: malloc arenas the server allows (the event loop's and one the worker threads share; more
#: arenas only spread the same freed memory over more places)
MALLOC_ARENAS = 2
_M_ARENA_MAX = -8     # glibc's malloc.h


def _arena_max_from_environment(environ) -> bool:
    return bool(environ.get("MALLOC_ARENA_MAX")) or "glibc.malloc.arena_max" in environ.get("GLIBC_TUNABLES", "")


def limit_malloc_arenas(n: int = MALLOC_ARENAS, *, libc=None, environ=None) -> str:
    """Cap glibc's malloc arenas at ``n`` for this process (``mallopt(M_ARENA_MAX, n)``), to be
    called before the worker threads start: a thread that already has an arena keeps it. Returns
    what was done: ``"applied"``; ``"environment"`` when ``MALLOC_ARENA_MAX`` or
    ``GLIBC_TUNABLES`` sets it (glibc applied that at start; left alone); ``"unavailable"`` when the
    C library has no ``mallopt`` (not glibc); ``"refused"`` when ``mallopt`` said no (musl's
    does nothing). Never raises."""
    environ = os.environ if environ is None else environ
    if _arena_max_from_environment(environ):
        return "environment"
    mallopt = getattr(_LIBC if libc is None else libc, "mallopt", None)
    if mallopt is None:
        return "unavailable"
    try:
        ok = mallopt(ctypes.c_int(_M_ARENA_MAX), ctypes.c_int(int(n)))
    except (OSError, TypeError, ValueError, ctypes.ArgumentError):
        return "unavailable"
    return "applied" if ok == 1 else "refused"


def trim_memory() -> None:
    """Give freed C-heap memory back to the system (glibc ``malloc_trim``; a
    no-op elsewhere)."""
    if _MALLOC_TRIM is not None:
        _MALLOC_TRIM(0)


def _then_trim(call):
    try:
        return call()
    finally:
        trim_memory()


def _reading_uploads(func, args, kwargs):
    """``func(*args, **kwargs)`` with each :class:`service.deps.Upload`
    among them replaced by its bytes, read here, in the worker thread with
    the slot held: a queued request holds no copy of its file."""
    from .deps import Upload

    args = [a.read() if isinstance(a, Upload) else a for a in args]
    kwargs = {k: v.read() if isinstance(v, Upload) else v for k, v in kwargs.items()}
    return func(*args, **kwargs)


async def _client_gone(request) -> None:
    """Return when the client disconnects. Only after the body has been read
    (FastAPI reads the form before the endpoint runs), so every message left
    is ``http.disconnect``. Receiving is what makes the server look: uvicorn
    stops reading a connection once its request is complete, so a reset is
    only noticed while someone waits in ``receive()``."""
    while (await request.receive())["type"] != "http.disconnect":
        pass


async def run_heavy(func, *args, request=None, **kwargs):
    """``func(*args, **kwargs)`` in a worker thread, at most
    ``max_concurrent_work`` of them at once (FIFO); an argument that is a
    :class:`service.deps.Upload` is read there, once the slot is held. With ``request`` (a
    Starlette request), a client that disconnects while its job waits for a
    slot leaves the queue at once and gets no work done: 499
    ``client_closed_request`` (nobody reads it)."""
    call = functools.partial(_reading_uploads, func, args, kwargs)
    limiter = _limiter()
    if request is None:
        async with limiter:
            return await anyio.to_thread.run_sync(_then_trim, call)
    acquired = gone = False
    async with anyio.create_task_group() as tg:
        async def watch():
            nonlocal gone
            await _client_gone(request)
            gone = True
            tg.cancel_scope.cancel()

        tg.start_soon(watch)
        await limiter.acquire()
        acquired = True
        tg.cancel_scope.cancel()
    try:
        if gone:
            log.warning("dropped queued work for %s %s: the client disconnected", request.method,
                        request.url.path)
            raise ServiceError(499, "client_closed_request", "the client closed the connection before the work started")
        # the slot is held by this task; the thread comes from anyio's default pool
        return await anyio.to_thread.run_sync(_then_trim, call)
    finally:
        if acquired:
            limiter.release()
