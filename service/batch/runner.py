"""The batch runner (:class:`BatchRunner`): claims queued items of the active batches, runs them
on an executor, the shared light first in ``shared`` mode, cancels, resumes after a restart,
removes stale temporaries and expired inputs; :func:`scan_folder` for a folder batch.

Every item ends exactly once whatever happens to the process that runs it
(issue 28; the state machine is in ``docs/reliability.md``):

- a graceful stop (SIGTERM, Ctrl-C: :meth:`BatchRunner.stop`) puts the items
  in flight back to ``pending`` (journalled), run again after the restart;
- a worker lost (a pool worker killed, a Dask worker or client lost) puts
  its item back to ``pending``; a broken pool or a closed Dask client is
  replaced at the next step. On the local pool, the items that were in flight
  when it broke are not charged: they run again one at a time, alone in the
  pool, before anything else (culprit isolation), and only an item whose
  worker dies while it runs alone is charged, ``failed`` as ``worker_killed``
  after :data:`~service.batch.store.MAX_ATTEMPTS` such runs. On Dask, any
  item whose worker is lost is charged, at most ``MAX_ATTEMPTS`` runs;
- a result that cannot be recorded (the store's disk full, the store
  locked) is kept and recorded at a later step, so no item stays
  ``running``; an item whose output could not be written for want of space
  is ``pending`` again and the runner pauses;
- no Dask worker, or no scheduler, is said in :attr:`BatchRunner.executor_error`
  (the progress document's ``runner_error``, ``/health``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sqlite3
import threading
import time
from dataclasses import dataclass, field

from ..errors import ServiceError
from ..schemas.options import BatchOptions
from .downloads import Downloads
from .executors import make_executor
from .items import (ItemTask, RAW_SUFFIXES, _error_text, estimation_sample, process_item, remove_stale_lock,
                    remove_stale_temporaries, shared_light)
from .store import MAX_ATTEMPTS, UNREGISTERED, JobStore

log = logging.getLogger("service.jobs")


@dataclass
class RunnerConfig:
    data_dir: str
    workers: int = 0                 # 0: one per core
    max_concurrent_batches: int = 2
    max_pixels: int = 120_000_000
    estimation_pixels: int = 1_000_000
    dask_scheduler: str | None = None
    dask_timeout: float = 20.0
    poll_s: float = 0.2
    #: seconds a finished or cancelled batch's uploaded inputs are kept (< 0: kept forever)
    input_retention_s: float = 24 * 3600.0
    #: folder batches' root (their items are opened under it, no symlink followed); "" = none
    batch_root: str = ""
    #: the largest input an item reads (the upload limit; checked on the open file); None = no limit
    max_input_bytes: int | None = None
    #: runs of an item whose worker was lost before it is failed for good
    max_attempts: int = MAX_ATTEMPTS
    #: seconds the runner hands out no item after an output could not be written for want of space
    disk_full_pause_s: float = 10.0
    #: seconds between two attempts to connect to an unreachable Dask scheduler
    reconnect_s: float = 5.0
    #: seconds a finished or cancelled batch (results and all) is kept; negative: for ever
    result_retention_s: float = -1.0
    #: seconds after its last change a batch folder the store does not know (a POST cut by a crash before
    #: its batch was accepted) is removed
    orphan_age_s: float = 600.0
    extra: dict = field(default_factory=dict)


class BatchRunner:
    """Runs batches from the store on an executor, in a background thread.

    At most ``max_concurrent_batches`` run at once; within them items are
    dispatched so that about two per worker are in flight (the pool never
    idles, a cancel takes effect quickly). :meth:`start` re-queues what a
    killed server left running and carries on.
    """

    def __init__(self, config: RunnerConfig, store: JobStore | None = None, executor=None):
        self.config = config
        self.store = store or JobStore(config.data_dir)
        self._executor = executor
        self._inflight: dict = {}          # (batch, idx) -> Future
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._light_jobs: dict = {}        # batch -> (estimation futures, light future)
        #: shared batches whose estimation lost a worker: {"samples": idx -> (row, estimate), "losses": idx -> n}
        self._light_retry: dict = {}
        #: why items are not running (e.g. no Dask scheduler, no worker), shown in progress and /health
        self.executor_error: str | None = None
        #: since when (epoch seconds) the cause in :attr:`executor_error` holds
        self.error_since: float | None = None
        #: executors replaced because they broke (a killed pool worker, a closed Dask client)
        self.executor_rebuilds = 0
        #: store transitions that failed (disk full, store locked), retried at each step
        self._unrecorded: list = []
        #: state changes the store could not take at once (kept, recorded later), since start
        self.records_deferred = 0
        #: outputs that could not be written for want of space (their items re-queued), since start
        self.disk_full_retries = 0
        #: batches whose creation found the store busy, registered from their manifest (:meth:`defer`)
        self._deferred: set = set()
        self._paused_until = 0.0
        self._next_connect = 0.0
        self._next_idle_check = 0.0
        self._next_cleanup = 0.0
        self._last_log: dict = {}
        #: what a pool worker runs for an item. Tests put here a function that ends its worker for
        #: some items (``testing.faults``); settable from Python only (no request, option or variable)
        self.item_fn = process_item
        self.sample_fn = estimation_sample     # the shared light's per-image estimation (the same rule)
        #: culprit isolation: items in flight when the local pool broke, (batch, idx) -> how often
        #: their worker was lost while they ran alone; they run one at a time before anything else
        self._suspects: dict = {}
        self._solo = None                  # the suspect running alone now
        #: items failed as ``worker_killed`` (their worker died each time they ran alone), since start
        self.worker_kills = 0
        #: why the store cannot be written (a read-only data directory): batches are then only read
        self.read_only: str | None = None
        #: zip downloads being sent (the router counts them): the retention sweep postpones those batches
        self.downloads = Downloads()

    @property
    def executor(self):
        if self._executor is None:
            self._executor = make_executor(self.config.workers or None, self.config.dask_scheduler,
                                           self.config.dask_timeout)
        return self._executor

    def defer(self, batch_id: str) -> None:
        """A batch made while the store was busy (its manifest on disk):
        registered at the runner's next step that finds the store free."""
        self.store.defer(batch_id)
        self._deferred.add(batch_id)
        self._wake.set()

    def start(self) -> int:
        """Resume what a killed server left and start the runner's thread. A
        store that opens but cannot be written (the data directory's files
        read-only, a read-only mount) starts nothing: the batches are served
        read-only (:attr:`read_only`, ``/health`` degraded) until a restart
        finds it writable."""
        self._deferred.update(self.store.unregistered())
        try:
            n = self.store.resume()
        except sqlite3.OperationalError as e:
            if "readonly" not in str(e).lower():
                raise
            self.read_only = (f"read_only_store: the job store under {self.store.data_dir} cannot be written "
                              f"({e}); finished results can be read, no batch can be made, run or cancelled "
                              "until the data directory is writable and the server restarted")
            self._set_error(self.read_only)
            log.error("%s", self.read_only)
            return 0
        self._thread = threading.Thread(target=self._loop, name="batch-runner", daemon=True)
        self._thread.start()
        return n

    def stop(self, wait: bool = True) -> None:
        """Stop the runner. ``wait``: let the items in flight finish (and be
        recorded). Otherwise (the server is going away: SIGTERM, Ctrl-C) the
        pool is ended at once and every item in flight goes back to
        ``pending`` (journalled): the restart runs it again; nothing it had
        half-written keeps a final name, and its lock file is removed."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
        with self._lock:
            keys = list(self._inflight)
        if self._executor is not None:
            if not wait and hasattr(self._executor, "terminate"):
                self._executor.terminate()   # the futures' callbacks requeue their items (_done)
            else:
                self._executor.shutdown(wait=wait)
        with self._lock:
            left = list(self._inflight)
            self._inflight.clear()
        for bid, idx in left:   # a Dask task left on the cluster, or a callback not yet run: requeue now
            self._record(self.store.requeue_item, bid, idx, "stopped: the server stopped while it ran")
        self._flush_unrecorded()
        self._remove_stale_locks(keys)

    def wake(self) -> None:
        self._wake.set()

    def cancel_file(self, batch_id: str) -> str:
        """The marker that tells the batch's running items to stop."""
        return os.path.join(self.store.batch_dir(batch_id), "cancelled")

    def cancel(self, batch_id: str) -> bool:
        """Cancel a batch: pending items are dropped, items handed to the
        executor but not started are dropped (cancelled future) or stop at
        their first step, running ones stop at their next step without
        writing (the marker file :meth:`cancel_file`, which workers on any
        executor see) and become ``cancelled``; results finished before are
        kept. In shared mode the light's estimation jobs are dropped or
        stopped the same way. The progress document says ``settled`` once
        all have answered."""
        ok = self.store.cancel(batch_id)
        if ok:
            with contextlib.suppress(OSError):
                with open(self.cancel_file(batch_id), "w") as f:
                    f.write(f"{time.time()}\n")
        with self._lock:
            futs = [fut for (b, _), fut in self._inflight.items() if b == batch_id]
            light = self._light_jobs.pop(batch_id, None)
            self._light_retry.pop(batch_id, None)
        if light is not None:
            est, light_fut = light
            futs += [f for _, f in est] + ([light_fut] if light_fut is not None else [])
        for fut in futs:  # outside the lock: cancel() runs the done callback at once
            fut.cancel()  # not yet started: dropped; started: stops at its next step
        self._wake.set()
        return ok

    def wait(self, batch_id: str, timeout: float = 120.0) -> dict:
        """Block until the batch is over and settled (tests, CLI)."""
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            doc = self.store.progress(batch_id)
            if doc and doc["status"] not in ("queued", "running") and doc.get("settled", True):
                return doc
            time.sleep(0.1)
        raise TimeoutError(f"batch {batch_id} still running after {timeout} s")

    def health(self) -> dict:
        """The runner's state for ``/health``: ``ok``, or ``degraded`` with
        why items are not running (``runner_error``) and since when."""
        doc = {"status": "degraded" if self.executor_error else "ok",
               "executor": getattr(self._executor, "kind", None) or ("dask" if self.config.dask_scheduler
                                                                      else "local"),
               "executor_rebuilds": self.executor_rebuilds, "unrecorded_results": len(self._unrecorded),
               "records_deferred": self.records_deferred, "disk_full_retries": self.disk_full_retries,
               "isolating": len(self._suspects), "worker_kills": self.worker_kills}
        if self.executor_error:
            doc["runner_error"] = self.executor_error
            doc["since"] = self.error_since
        return doc

    # -- internals -----------------------------------------------------------
    def _task(self, row, options: BatchOptions, light: dict | None) -> ItemTask:
        bdir = self.store.batch_dir(row["batch_id"])
        src = row["src"]
        # uploads are read under their batch's folder, folder batches under the batch root, anything
        # else (stored as a resolved path) from "/": in every case no symbolic link on the way is followed
        broot = os.path.realpath(self.config.batch_root) if self.config.batch_root else None
        if src.startswith(os.path.abspath(bdir) + os.sep):
            root = bdir
        elif broot and src.startswith(broot + os.sep):
            root = broot
        else:
            root = os.sep
        return ItemTask(src=src, out=row["out"], name=row["name"], options=options, index=row["idx"],
                        max_pixels=self.config.max_pixels, estimation_pixels=self.config.estimation_pixels,
                        light=light, write_log=os.path.join(bdir, "writes.log"),
                        cancel_file=self.cancel_file(row["batch_id"]), root=root,
                        max_bytes=self.config.max_input_bytes)

    def remove_stale_temporaries(self, batch_id: str | None = None) -> list[str]:
        """The temporaries a killed writer left in one batch's ``out/``, or
        in every batch's (at start-up); see :func:`remove_stale_temporaries`."""
        root = os.path.join(self.store.data_dir, "batches")
        try:
            ids = [batch_id] if batch_id else sorted(os.listdir(root))
        except OSError:
            return []
        gone = []
        for bid in ids:
            gone += remove_stale_temporaries(os.path.join(root, bid, "out"))
        if gone:
            log.info("removed %d stale temporary file(s): %s", len(gone), gone[:5])
        return gone

    def _remove_stale_locks(self, keys) -> None:
        for bid, idx in keys:
            with contextlib.suppress(Exception):
                row = self.store.item_by_index(bid, idx)
                if row is not None:
                    remove_stale_lock(row["out"])

    def _finish(self, batch_id: str) -> None:
        """Mark the batch done if nothing is left; then clear its temporaries."""
        if self.store.maybe_finish(batch_id):
            self.remove_stale_temporaries(batch_id)

    def _log_once(self, key: str, text: str, every_s: float = 30.0) -> None:
        """Log ``text`` at most every ``every_s`` seconds per ``key`` (a
        fault that lasts, e.g. a full disk, must not flood the log)."""
        now = time.monotonic()
        if now - self._last_log.get(key, float("-inf")) >= every_s:
            self._last_log[key] = now
            log.error("%s", text)

    def _loop(self) -> None:
        try:  # what a killed server left being written (its writers hold their locks if still alive)
            self.remove_stale_temporaries()
        except Exception:
            log.exception("removing stale temporaries failed")
        while not self._stop.is_set():
            try:
                self._tick()
            except Exception as e:  # keep the runner alive; the error is logged (rate-limited)
                self._log_once(f"tick:{type(e).__name__}", f"batch runner step failed: {type(e).__name__}: {e}")
            self._wake.wait(self.config.poll_s)
            self._wake.clear()

    def remove_expired_inputs(self) -> list[str]:
        """Delete the uploaded inputs of batches past their retention period
        (results and the store's records are kept). Returns the folders."""
        import shutil

        if self.config.input_retention_s < 0:
            return []
        gone = self.store.expired_inputs(self.config.input_retention_s)
        for d in gone:
            shutil.rmtree(d, ignore_errors=True)
        return gone

    def remove_expired_batches(self) -> list[str]:
        """Delete the batches (results and all) finished or cancelled more than
        ``result_retention_s`` ago (:meth:`JobStore.delete_batch`). Returns their ids.
        A batch whose zip is being downloaded (:attr:`downloads`) is kept until a
        later sweep: its results are read while the zip streams."""
        if self.config.result_retention_s < 0:
            return []
        gone = []
        for bid in self.store.expired_batches(self.config.result_retention_s):
            with self.downloads.removing(bid) as busy:
                if busy:
                    log.info("batch %s expired, kept while its zip is downloaded (%d): removed later", bid, busy)
                elif self.store.delete_batch(bid, expired_after=self.config.result_retention_s) is not None:
                    gone.append(bid)
        return gone

    def remove_orphan_folders(self) -> list[str]:
        """Remove the batch folders no batch owns: made by a ``POST
        /v1/batches`` that a crash (kill -9, power loss) cut before the batch
        was accepted, so the client never got its id (the uploads half
        written, no manifest or no record). Nothing lists, runs or expires
        them, so they would stay for ever, and a store rebuilt from the folders
        would bring them back as batches nobody asked for. A folder is one
        when the store (asked without error) does not know it, it is not
        waiting for registration (the store busy at creation), and nothing in
        it changed for ``orphan_age_s`` (an upload in progress keeps writing).
        Returns their ids."""
        import shutil

        root = os.path.join(self.store.data_dir, "batches")
        try:
            ids = sorted(os.listdir(root))
        except OSError:
            return []
        gone, now = [], time.time()
        for bid in ids:
            bdir = os.path.join(root, bid)
            if bid in self._deferred or os.path.exists(os.path.join(bdir, UNREGISTERED)):
                continue
            try:
                newest = max(os.lstat(os.path.join(d, n)).st_mtime for d, dirs, files in os.walk(bdir)
                             for n in dirs + files + ["."])
                if now - newest < self.config.orphan_age_s or self.store.batch(bid) is not None:
                    continue
            except (OSError, ValueError, sqlite3.Error):   # unreadable, or the store cannot say: keep it
                continue
            shutil.rmtree(bdir, ignore_errors=True)
            gone.append(bid)
        if gone:
            log.warning("removed %d batch folder(s) that no batch owns (a creation cut by a crash): %s",
                        len(gone), gone[:5])
        return gone

    def _set_error(self, text: str | None) -> None:
        if text is None:
            self.executor_error = self.error_since = None
        elif self.executor_error is None or text.split(":")[0] != self.executor_error.split(":")[0]:
            self.executor_error, self.error_since = text, time.time()
        else:
            self.executor_error = text

    def _replace_broken_executor(self) -> None:
        """A pool one of whose workers died, or a Dask client that closed
        itself, runs nothing more: end it and make a new one at the next use.
        Its items in flight come back through their futures (requeued)."""
        ex = self._executor
        why = getattr(ex, "broken", None) if ex is not None else None
        if not why:
            return
        log.error("the batch executor is broken (%s): replacing it", why)
        self._executor = None
        self.executor_rebuilds += 1
        with contextlib.suppress(Exception):
            if hasattr(ex, "terminate"):
                ex.terminate(grace_s=1.0)
            else:
                ex.shutdown(wait=False)

    def _capacity(self) -> int | None:
        """Items that may be in flight now, or None when there is nowhere to
        run them (the reason in :attr:`executor_error`)."""
        now = time.monotonic()
        if self._executor is None and now < self._next_connect:
            return None
        try:
            ex = self.executor
        except Exception as e:  # e.g. the Dask scheduler is unreachable: items wait, the error is shown
            self._next_connect = time.monotonic() + self.config.reconnect_s
            self._set_error(f"executor_unavailable: {type(e).__name__}: {e}; items wait and the runner "
                            f"tries again every {self.config.reconnect_s:g} s")
            return None
        workers = ex.workers
        if workers <= 0:
            why = getattr(ex, "workers_error", None)
            self._set_error(f"waiting_for_workers: the Dask cluster at {self.config.dask_scheduler} "
                            + (f"does not answer ({why})" if why else "has no worker") + "; items wait")
            return None
        if now < self._paused_until:   # an output could not be written for want of space: wait a little
            return None
        self._set_error(None)
        return 2 * workers

    def _tick(self) -> None:
        self._flush_unrecorded()
        for bid in sorted(self._deferred):   # made while the store was busy: register them now
            if self.store.adopt_batch(bid):
                log.info("batch %s registered (its creation found the store busy)", bid)
            self._deferred.discard(bid)
        now = time.monotonic()
        if now >= self._next_cleanup:  # at most every 30 s (sooner for a short retention)
            shortest = min(r for r in (self.config.input_retention_s, self.config.result_retention_s, 120.0)
                           if r >= 0)
            self._next_cleanup = now + min(30.0, max(self.config.poll_s, shortest / 4))
            if self.store.check_file():
                log.error("the job store file was lost while running; batches rebuilt from their folders")
            self.remove_expired_inputs()
            self.remove_expired_batches()
            self.remove_orphan_folders()
        self._replace_broken_executor()
        active = self.store.active_batches()[: max(1, self.config.max_concurrent_batches)]
        for bid in active:
            self.store.start_batch(bid)
        if not active:
            if self.config.dask_scheduler and self._executor is None or self._executor is not None \
                    and getattr(self._executor, "kind", "") == "dask":
                if now >= self._next_idle_check:   # a cluster: say now if it cannot run anything
                    self._next_idle_check = now + self.config.reconnect_s
                    self._capacity()
            elif now >= self._paused_until:
                self._set_error(None)
            return
        capacity = self._capacity()
        if capacity is None:
            return
        if (self._suspects or self._light_retry) and self._local():   # a pool broke: find which item ended it
            self._isolation_step()
            for bid in active:
                self._finish(bid)
            return
        for bid in active:
            b = self.store.batch(bid)
            if b is None or b["status"] != "running":
                continue
            options = BatchOptions.from_json(b["options"])
            light = None
            if options.lighting == "shared":
                if b["light"] is None:
                    self._shared_light_step(bid, options)
                    continue
                light = json.loads(b["light"])
            with self._lock:
                room = capacity - len(self._inflight)
            if room > 0:
                for row in self.store.claim(bid, room):
                    try:
                        fut = self.executor.submit(self.item_fn, self._task(row, options, light))
                    except Exception as e:  # a broken pool or closed client: back to pending, replaced next step
                        self._record(self.store.requeue_item, bid, row["idx"],
                                     f"executor_error: {type(e).__name__}: {e}")
                        self._log_once("submit", f"submit failed ({type(e).__name__}: {e}); item re-queued")
                        continue
                    with self._lock:
                        self._inflight[(bid, row["idx"])] = fut
                    fut.add_done_callback(lambda f, k=(bid, row["idx"]): self._done(k, f))
            self._finish(bid)

    def _record(self, fn, *args) -> None:
        """A store transition now, or, if the store cannot take it (disk
        full, locked), at a later step (:meth:`_flush_unrecorded`): never lost."""
        try:
            fn(*args)
        except Exception as e:
            with self._lock:
                self._unrecorded.append((fn, args))
                self.records_deferred += 1
            self._log_once(f"record:{type(e).__name__}", f"a batch item's state could not be recorded "
                           f"({type(e).__name__}: {e}); kept, recorded when the store can take it")

    def _flush_unrecorded(self) -> None:
        with self._lock:
            todo, self._unrecorded = self._unrecorded, []
        for i, (fn, args) in enumerate(todo):
            try:
                fn(*args)
            except Exception:
                with self._lock:
                    self._unrecorded[:0] = todo[i:]
                return
            with contextlib.suppress(Exception):
                self._finish(args[0])

    def _local(self) -> bool:
        """Whether items run on the local process pool (where culprit isolation applies)."""
        if self._executor is not None:
            return getattr(self._executor, "kind", "local") == "local"
        return not self.config.dask_scheduler

    def _isolation_step(self) -> None:
        """Culprit isolation: once nothing is in flight, run one suspect (an
        item in flight when the pool broke) alone in the pool. A suspect no
        longer pending (cancelled, removed, finished) is dropped. The same
        for a shared batch's images whose light is still to be estimated."""
        for bid in sorted(self._light_retry):
            b = self.store.batch(bid)
            if b is None or b["status"] not in ("queued", "running"):
                with self._lock:
                    self._light_retry.pop(bid, None)
                    self._light_jobs.pop(bid, None)
            elif bid in self._light_jobs:     # collect the estimate that ran alone
                self._shared_light_step(bid, BatchOptions.from_json(b["options"]))
        with self._lock:
            if self._solo is not None or self._inflight or any(
                    not f.done() for est, lf in self._light_jobs.values() for f in
                    [f for _, f in est] + ([lf] if lf is not None else [])):
                return
            keys = sorted(self._suspects)
        for key in keys:
            bid, idx = key
            b, row = self.store.batch(bid), self.store.item_by_index(bid, idx)
            if row is None or row["status"] not in ("pending", "running") or b is None \
                    or b["status"] not in ("queued", "running"):
                with self._lock:
                    self._suspects.pop(key, None)
                continue
            if row["status"] != "pending" or not self.store.claim(bid, 1, idx):  # a requeue not yet recorded
                continue
            light = json.loads(b["light"]) if b["light"] else None
            task = self._task(row, BatchOptions.from_json(b["options"]), light)
            try:
                fut = self.executor.submit(self.item_fn, task)
            except Exception as e:   # a broken pool: back to pending, still a suspect
                self._record(self.store.requeue_item, bid, idx, f"executor_error: {type(e).__name__}: {e}")
                return
            with self._lock:
                self._inflight[key] = fut
                self._solo = key
            fut.add_done_callback(lambda f, k=key: self._done(k, f))
            return
        for bid in sorted(self._light_retry):   # then one image of a shared batch, alone
            b = self.store.batch(bid)
            if b is not None and b["status"] == "running" and b["light"] is None:
                self._shared_light_step(bid, BatchOptions.from_json(b["options"]))
                return

    def _lost_in_pool(self, key, solo: bool, e: BaseException) -> None:
        """A local pool worker died under item ``key``: not charged unless it
        ran alone (then it was the culprit); failed as ``worker_killed`` once
        its worker died in ``max_attempts`` runs alone."""
        bid, idx = key
        with self._lock:
            n = self._suspects.get(key, 0) + int(solo)
            give_up = solo and n >= self.config.max_attempts
            if give_up:
                self._suspects.pop(key, None)
            else:
                if key not in self._suspects:
                    self._log_once("isolate", "a pool worker died: the items that were in flight run again one "
                                   "at a time, alone in the pool, to find which one ended it")
                self._suspects[key] = n
        if give_up:
            self.worker_kills += 1
            self._record(self.store.requeue_item, bid, idx, f"worker_lost: {type(e).__name__}", None,
                         f"worker_killed: processing this item ended its worker process {n} times when it ran "
                         f"alone in the pool ({type(e).__name__}: the file may crash the decoder, or need more "
                         "memory than a worker may take)")
        else:
            self._record(self.store.requeue_item, bid, idx, f"worker_lost: {type(e).__name__}: {e}"
                         + (" (it ran alone)" if solo else "; it runs again alone in the pool"))
        self._record(self._finish, bid)
        self._wake.set()

    def _done(self, key, fut) -> None:
        """An item's future ended: record its state (:meth:`_settle`). It
        leaves the in-flight set only once recorded, so a stop that looks
        at the set meanwhile re-queues it itself (a no-op if done twice)."""
        with self._lock:
            solo = self._solo == key
            if solo:
                self._solo = None
        try:
            self._settle(key, fut, solo)
        finally:
            with self._lock:
                if self._inflight.get(key) is fut:
                    del self._inflight[key]
            self._wake.set()

    def _settle(self, key, fut, solo: bool) -> None:
        bid, idx = key
        stopping = self._stop.is_set()
        if stopping or fut.cancelled() or fut.exception() is None:   # not a worker death: no longer a suspect
            with self._lock:
                self._suspects.pop(key, None)
        if fut.cancelled():  # dropped before it started
            if stopping:
                self._record(self.store.requeue_item, bid, idx, "stopped: the server stopped before it ran")
            else:
                self._record(self.store.cancel_item, bid, idx)
                self._record(self._finish, bid)
            return
        try:
            result = fut.result()
        except BaseException as e:  # the worker died (a stop, the OOM killer, a lost Dask worker or client)
            reason = f"worker_lost: {type(e).__name__}: {e}"
            if stopping:
                self._record(self.store.requeue_item, bid, idx, reason)
            elif self._local() and _worker_lost(e):
                self._lost_in_pool(key, solo, e)
            else:
                self._record(self.store.requeue_item, bid, idx, reason, self.config.max_attempts)
                self._record(self._finish, bid)
                self._wake.set()
            return
        if result.get("status") == "cancelled":  # stopped by the batch's cancel, nothing written
            self._record(self.store.cancel_item, bid, idx)
        elif result.get("retry"):  # the output could not be written for want of space: pending again, pause
            self.disk_full_retries += 1
            self._paused_until = time.monotonic() + self.config.disk_full_pause_s
            self._set_error(f"insufficient_storage: an output could not be written ({result.get('error')}); "
                            f"items wait {self.config.disk_full_pause_s:g} s between tries")
            self._record(self.store.requeue_item, bid, idx, str(result.get("error")))
        else:
            self._record(self.store.finish_item, bid, idx, result)
        self._record(self._finish, bid)
        self._wake.set()

    def _light_retry_step(self, bid: str, got: list, lost: list, solo: bool) -> list | None:
        """Shared mode after a lost worker: keep the estimates made, charge an
        image whose worker died while it was estimated alone (``failed`` as
        ``worker_killed`` after ``max_attempts`` such runs, and left out of
        the light), and estimate the rest one at a time. Returns every
        estimate once none is left to make, else None."""
        with self._lock:
            retry = self._light_retry.setdefault(bid, {"samples": {}, "losses": {}})
        for r, s in got:
            retry["samples"][r["idx"]] = (r, s)
        for r, e in lost:
            if not solo or self._stop.is_set():
                continue
            n = retry["losses"][r["idx"]] = retry["losses"].get(r["idx"], 0) + 1
            if n >= self.config.max_attempts:
                self.worker_kills += 1
                self.store.fail_item(bid, r["idx"], f"worker_killed: estimating this image's light ended its worker "
                                     f"process {n} times when it ran alone ({type(e).__name__}: the file may crash "
                                     "the decoder, or need more memory than a worker may take)")
        if lost:
            self._log_once("light", f"shared light of batch {bid}: a worker was lost ({type(lost[0][1]).__name__}); "
                           "the images not yet estimated run again one at a time")
        left = [r for r in self.store.items(bid) if r["status"] in ("pending", "running", "done")
                and r["idx"] not in retry["samples"]]
        with self._lock:
            if left:
                self._light_jobs.pop(bid, None)
                return None
            self._light_retry.pop(bid, None)
        return [rs for rs in retry["samples"].values() if self.store.item_by_index(bid, rs[0]["idx"])["status"]
                in ("pending", "running", "done")]

    def _shared_light_step(self, bid: str, options: BatchOptions) -> None:
        """Shared mode: estimate every pending/running image's own light (in
        the pool), combine them into one light (:func:`shared_light`), store it. Items whose file
        cannot be read fail here, with their error."""
        with self._lock:
            fut = self._light_jobs.get(bid)
            retry = self._light_retry.get(bid)
        if fut is None:
            rows = [r for r in self.store.items(bid) if r["status"] in ("pending", "running", "done")]
            if retry is not None:   # a worker was lost: the images not yet estimated, one at a time
                rows = [r for r in rows if r["idx"] not in retry["samples"]][:1]
            futs = [(r, self.executor.submit(self.sample_fn, self._task(r, options, None))) for r in rows]
            with self._lock:
                self._light_jobs[bid] = (futs, None)
            return
        futs, light_fut = fut
        if light_fut is None:
            if not all(f.done() for _, f in futs):
                return
            got, lost = [], []
            for r, f in futs:
                try:
                    got.append((r, f.result()))
                except BaseException as e:
                    lost.append((r, e))
            if lost or retry is not None:
                got = self._light_retry_step(bid, got, lost, solo=len(futs) == 1)
                if got is None:   # images left to estimate, one at a time (alone in the pool: isolation step)
                    return
            cams: dict = {}
            for r, s in got:
                if s["status"] != "ok":
                    self.store.fail_item(bid, r["idx"], s["error"])
                    continue
                cams.setdefault(s["camera"].name, []).append((r, s))
            if not cams:
                self.store.set_light(bid, None, "no image of the batch could be read")
                with self._lock:
                    self._light_jobs.pop(bid, None)
                self._finish(bid)
                return
            main = max(cams, key=lambda k: len(cams[k]))
            for name, lst in cams.items():
                if name != main:
                    for r, _ in lst:
                        self.store.fail_item(bid, r["idx"], f"camera_mismatch: shared lighting pools images of "
                                             f"one camera; this image is from {name!r}, the batch from {main!r}")
            light_fut = self.executor.submit(shared_light, [s for _, s in cams[main]], options)
            with self._lock:
                if bid in self._light_jobs:
                    self._light_jobs[bid] = (futs, light_fut)
            return
        if not light_fut.done():
            return
        with self._lock:
            self._light_jobs.pop(bid, None)
        try:
            light = light_fut.result()
            self.store.set_light(bid, light)
        except BaseException as e:
            if _worker_lost(e):   # not the light's fault: estimate it again at the next step
                self._log_once("light", f"shared light of batch {bid}: a worker was lost ({type(e).__name__}); "
                               "estimating again")
                return
            err = _error_text(e)
            self.store.set_light(bid, None, err)
            for r in self.store.items(bid):
                if r["status"] in ("pending", "running"):
                    self.store.fail_item(bid, r["idx"], f"shared light could not be estimated: {err}")
            self._finish(bid)
        self._wake.set()


def _worker_lost(e: BaseException) -> bool:
    """Whether a future's exception says its worker went away (a broken or
    stopped pool, a cancelled future, a lost Dask worker, scheduler or
    client) rather than that the work itself failed."""
    from concurrent.futures import BrokenExecutor, CancelledError

    return isinstance(e, (BrokenExecutor, CancelledError)) or type(e).__name__ in (
        "FutureCancelledError", "KilledWorker", "CommClosedError", "ClosedClientError", "CancelledError")


def scan_folder(root: str, folder: str, limit: int | None = None) -> tuple[list[tuple[str, str]], dict]:
    """The RAW files directly in ``folder`` (relative to ``root``) as
    ``(name, real path)``, refusing anything that resolves outside the root
    (``..``, absolute paths, symlinks leading out), and ``refused``: index ->
    error for files kept as failed items (a name that is not UTF-8: it is
    listed, by its bytes, and fails, the rest of the folder runs).

    The folder is read entry by entry (``os.scandir``) and the scan stops as
    soon as more than ``limit`` files would be items: 413 ``too_many_items``
    after ``limit + 1`` entries, whatever the folder's size. (Items are read
    at run time under the root with no symlink followed:
    :func:`~service.batch.items.open_under`.)"""
    if not root:
        raise ServiceError(403, "folder_mode_disabled", "folder batches need a server-side root: set "
                           "WANDELL_BATCH_ROOT; upload the files instead")
    if os.path.isabs(folder) or folder.startswith(("/", "\\")) or "\x00" in folder:
        raise ServiceError(403, "path_outside_root", f"folder must be relative to the batch root, got {folder!r}")
    rootr = os.path.realpath(root)
    target = os.path.realpath(os.path.join(rootr, folder))
    if os.path.commonpath([rootr, target]) != rootr:
        raise ServiceError(403, "path_outside_root", f"folder {folder!r} is outside the batch root")
    if not os.path.isdir(target):
        raise ServiceError(404, "folder_not_found", f"folder {folder!r} does not exist under the batch root")
    found = []
    with os.scandir(target) as it:
        for entry in it:
            name = entry.name
            if name.startswith(".") or not name.lower().endswith(RAW_SUFFIXES):
                continue
            try:
                if entry.is_symlink():
                    real = os.path.realpath(entry.path)
                    if os.path.commonpath([rootr, real]) != rootr:
                        continue  # a symlink leading out of the root is never read
                    if not os.path.isfile(real):
                        continue
                elif entry.is_file():
                    real = entry.path
                else:
                    continue
            except OSError:
                continue
            found.append((name, real))
            if limit is not None and len(found) > limit:
                raise ServiceError(413, "too_many_items", f"folder {folder!r} holds more than {limit} RAW/TIFF/PNG "
                                   f"files, the batch limit (WANDELL_MAX_BATCH_ITEMS); split it into subfolders")
    if not found:
        raise ServiceError(422, "empty_folder", f"folder {folder!r} holds no RAW/TIFF/PNG files "
                           f"({', '.join(RAW_SUFFIXES[:6])}, ...)")
    found.sort(key=lambda p: os.fsencode(p[0]))
    out, refused = [], {}
    for i, (name, real) in enumerate(found):
        try:
            name.encode("utf-8")
            real.encode("utf-8")
        except UnicodeEncodeError:   # os.listdir's surrogate escapes: the name's bytes are not UTF-8
            shown = os.fsencode(name).decode("utf-8", "replace")   # U+FFFD for the odd bytes
            refused[i] = (f"invalid_name: the file name {os.fsencode(name)!r} is not UTF-8, so it cannot be "
                          "recorded; rename it (e.g. with convmv) and submit it again")
            out.append((shown, ""))
            continue
        out.append((name, real))
    return out, refused


def folder_sources(root: str, folder: str, limit: int | None = None) -> list[tuple[str, str]]:
    """The readable items of :func:`scan_folder` (names that are not UTF-8 left out)."""
    out, refused = scan_folder(root, folder, limit)
    return [s for i, s in enumerate(out) if i not in refused]
