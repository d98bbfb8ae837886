"""Where items run, one interface (``submit``, ``shutdown``): a local process pool
(:class:`LocalExecutor`, stopped at once on Ctrl-C or cancel) or a Dask cluster
(:class:`DaskExecutor`); :func:`make_executor` picks one.
"""

from __future__ import annotations

import contextlib
import os
import threading
import time
from concurrent.futures import Future

from .items import _pool_worker_init, limit_threads


def default_data_dir() -> str:
    """``$XDG_CACHE_HOME/wandell`` (default ``~/.cache/wandell``)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "wandell")


def default_workers() -> int:
    """Workers sized to the machine: one per core available to us."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


#: Local pool workers per core at most (every worker is a process started at once).
WORKERS_PER_CORE = 4


def max_local_workers() -> int:
    """The most workers a local pool starts: :data:`WORKERS_PER_CORE` per
    core (``wandell batch --workers`` refuses more; the server's
    ``WANDELL_BATCH_WORKERS`` is clamped to it). 100,000 asked for were
    100,000 processes (probe round 7)."""
    return WORKERS_PER_CORE * default_workers()


class LocalExecutor:
    """A process pool (spawn: no fork of a threaded server), each worker
    capped at one numerical thread, at most :func:`max_local_workers`."""

    kind = "local"

    def __init__(self, workers: int):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.workers = max(1, min(int(workers), max_local_workers()))
        self._pool = ProcessPoolExecutor(self.workers, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_pool_worker_init)
        # start every worker now, with SIGINT ignored from their first
        # instruction on (an ignored signal stays ignored across exec, and
        # Python then installs no KeyboardInterrupt handler): a Ctrl-C while
        # a worker is still importing must not kill it with a traceback
        with _sigint_ignored():
            for _ in range(self.workers):
                self._pool.submit(int)

    def submit(self, fn, *args) -> Future:
        return self._pool.submit(fn, *args)

    @property
    def broken(self) -> str | None:
        """Why the pool can run nothing more (a worker died abruptly, e.g.
        killed by the OOM killer: ``concurrent.futures`` then fails every
        future of the pool and refuses every submit), or None. The runner
        replaces a broken pool (:meth:`BatchRunner._replace_broken_executor`)."""
        b = getattr(self._pool, "_broken", False)
        if b:
            return f"process pool broken: {b}"
        if getattr(self._pool, "_shutdown_thread", False):
            return "process pool shut down"
        return None

    def shutdown(self, wait: bool = True) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=True)

    def terminate(self, kill: bool = False, grace_s: float = 3.0) -> None:
        """Stop now: queued items are dropped, running ones are ended
        (SIGTERM: the worker removes its temporary file and exits; ``kill``
        or still alive after ``grace_s``: SIGKILL). Their outputs never got
        their final names, so nothing partial remains. Afterwards the pool's
        manager thread ends by itself (it sees its workers gone), so neither
        this call nor the interpreter's exit waits for running work."""
        procs = list((getattr(self._pool, "_processes", None) or {}).values())
        self._pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            with contextlib.suppress(Exception):
                p.kill() if kill else p.terminate()
        t_end = time.monotonic() + grace_s
        for p in procs:
            with contextlib.suppress(Exception):
                p.join(max(0.0, t_end - time.monotonic()))
                if p.is_alive():
                    p.kill()
                    p.join(1.0)
        manager = getattr(self._pool, "_executor_manager_thread", None)
        if manager is not None:
            manager.join(max(1.0, t_end - time.monotonic()))


@contextlib.contextmanager
def _sigint_ignored():
    """SIGINT ignored in this block (main thread only; elsewhere a no-op)."""
    import signal

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


def _dask_call(fn, *args):
    limit_threads()
    return fn(*args)


class DaskExecutor:
    """Items submitted to a Dask distributed cluster (``scheduler`` address,
    or a ``distributed.Client`` given). The workers need this project
    installed and the data directory (or batch root) at the same path.

    :attr:`workers` follows the cluster: the threads of the workers connected
    now (asked of the scheduler at most every ``refresh_s`` seconds), so
    workers that join later are used and a cluster with no worker left gives
    0 (the runner then hands out nothing and says it is waiting). A client
    that closed itself (the scheduler away longer than its reconnection
    timeout) is :attr:`broken`: the runner makes a new one."""

    kind = "dask"

    def __init__(self, scheduler=None, client=None, timeout: float = 20.0, refresh_s: float = 1.0):
        from distributed import Client

        self._own = client is None
        self.address = scheduler
        self.client = client if client is not None else Client(scheduler, timeout=f"{timeout}s")
        self.refresh_s = float(refresh_s)
        self.answer_s = max(1.0, float(timeout))
        self._workers, self._asked = 0, float("-inf")
        self._asking = Bounded("Dask scheduler info")
        self.workers_error: str | None = None

    @property
    def workers(self) -> int:
        """Threads of the workers connected now (0: none, or a scheduler that
        did not answer within ``answer_s``: then :attr:`workers_error`)."""
        now = time.monotonic()
        if now - self._asked >= self.refresh_s:
            self._asked = now
            try:
                # every worker, asked now (a synchronous client); a hung scheduler never answers, so
                # the question runs on a thread of its own and is waited for a bounded time
                info = self._asking.call(self.client.scheduler_info, self.answer_s)
                self._workers = sum(int(w.get("nthreads", 1) or 1) for w in info.get("workers", {}).values())
                self.workers_error = None
            except Exception as e:  # the scheduler does not answer: count nothing, say why
                self._workers, self.workers_error = 0, f"{type(e).__name__}: {e}"
        return self._workers

    @property
    def broken(self) -> str | None:
        status = str(getattr(self.client, "status", "running"))
        if status in ("closed", "closing", "failed"):
            return f"Dask client {status} (the scheduler was unreachable longer than its reconnection timeout)"
        return None

    def submit(self, fn, *args) -> Future:
        fut: Future = Future()
        dfut = self.client.submit(_dask_call, fn, *args, pure=False)

        def done(df):
            try:
                fut.set_result(df.result())
            except BaseException as e:  # a lost worker, a cancelled task, a closed client
                fut.set_exception(e)

        fut.set_running_or_notify_cancel()
        dfut.add_done_callback(done)
        return fut

    def shutdown(self, wait: bool = True) -> None:
        if self._own:
            with contextlib.suppress(Exception):
                self.client.close(timeout=5)


class Bounded:
    """A blocking call waited for at most a given time, on a daemon thread
    of its own; one at a time: while an earlier call is still hanging (a
    Dask scheduler that accepted the connection and never answers: the
    ``distributed`` handshake has no deadline), a new one is not started
    (no pile of stuck threads); its result is used once it comes."""

    def __init__(self, what: str):
        self.what = what
        self._pending: Future | None = None
        self._lock = threading.Lock()

    def call(self, fn, timeout: float):
        with self._lock:
            fut = self._pending
            if fut is None:
                fut = self._pending = Future()

                def run():
                    try:
                        fut.set_result(fn())
                    except BaseException as e:  # noqa: BLE001 - handed to the caller
                        fut.set_exception(e)

                threading.Thread(target=run, name=f"bounded: {self.what}", daemon=True).start()
        try:
            result = fut.result(timeout)
        except TimeoutError:
            raise TimeoutError(f"{self.what}: no answer within {timeout:g} s (the other side accepted the "
                               "connection but does not answer)") from None
        except BaseException:
            with self._lock:
                self._pending = None
            raise
        with self._lock:
            self._pending = None
        return result


_CONNECTING: dict = {}


def make_executor(workers: int | None = None, scheduler: str | None = None, timeout: float = 20.0):
    """Dask when a scheduler address is given, else the local pool. The
    connection to a scheduler is waited for at most ``timeout`` + 5 s even
    when the scheduler accepts it and never answers (:class:`Bounded`)."""
    if scheduler:
        b = _CONNECTING.setdefault(scheduler, Bounded(f"Dask scheduler {scheduler}"))
        return b.call(lambda: DaskExecutor(scheduler, timeout=timeout), timeout + 5.0)
    return LocalExecutor(workers or default_workers())


def run_alone(fn, task, attempts: int = 3):
    """``fn(task)`` alone in a pool of one worker of its own (a new one for
    each try), tried again while its worker dies abruptly (a crash of a
    native decoder, the OOM killer), at most ``attempts`` times: culprit
    isolation for an item that was in flight when a shared pool broke, so
    that an innocent item is not failed with the one that killed the pool
    (:class:`service.batch.runner.BatchRunner` does the same on the
    server). Returns ``(result, deaths)``: ``result`` None when the worker
    died every time. A Ctrl-C ends the worker (:meth:`LocalExecutor.terminate`)."""
    from concurrent.futures.process import BrokenProcessPool

    deaths = 0
    for _ in range(max(1, int(attempts))):
        pool = LocalExecutor(1)
        try:
            return pool.submit(fn, task).result(), deaths
        except BrokenProcessPool:
            deaths += 1
        except BaseException:
            pool.terminate()
            raise
        finally:
            pool.shutdown(wait=False)
    return None, deaths
