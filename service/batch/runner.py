"""The batch runner (:class:`BatchRunner`): claims queued items of the active batches, runs them
on an executor, the shared light first in ``shared`` mode, cancels, resumes after a restart,
removes stale temporaries and expired inputs; :func:`folder_sources` for a folder batch.
"""

from __future__ import annotations

import contextlib
import json
import os
import threading
import time
from dataclasses import dataclass, field

from ..errors import ServiceError
from ..schemas.options import BatchOptions
from .executors import make_executor
from .items import ItemTask, RAW_SUFFIXES, _error_text, estimation_sample, process_item, remove_stale_temporaries, shared_light
from .store import JobStore


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
    #: seconds a finished or cancelled batch (results and all) is kept; negative: for ever
    result_retention_s: float = -1.0
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
        self._light_jobs: dict = {}        # batch -> Future of the shared light
        #: why items are not running (e.g. no Dask scheduler), shown in progress
        self.executor_error: str | None = None
        self._next_cleanup = 0.0

    @property
    def executor(self):
        if self._executor is None:
            self._executor = make_executor(self.config.workers or None, self.config.dask_scheduler,
                                           self.config.dask_timeout)
        return self._executor

    def start(self) -> int:
        n = self.store.resume()
        self._thread = threading.Thread(target=self._loop, name="batch-runner", daemon=True)
        self._thread.start()
        return n

    def stop(self, wait: bool = True) -> None:
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=30)
        if self._executor is not None:
            if not wait and hasattr(self._executor, "terminate"):
                # the server is going away: items in flight are run again after
                # the restart (resume); never wait for them
                self._executor.terminate()
            else:
                self._executor.shutdown(wait=wait)

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
        kept. The progress document says ``settled`` once all have answered."""
        ok = self.store.cancel(batch_id)
        if ok:
            with contextlib.suppress(OSError):
                with open(self.cancel_file(batch_id), "w") as f:
                    f.write(f"{time.time()}\n")
        with self._lock:
            futs = [fut for (b, _), fut in self._inflight.items() if b == batch_id]
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

    # -- internals -----------------------------------------------------------
    def _task(self, row, options: BatchOptions, light: dict | None) -> ItemTask:
        return ItemTask(src=row["src"], out=row["out"], name=row["name"], options=options, index=row["idx"],
                        max_pixels=self.config.max_pixels, estimation_pixels=self.config.estimation_pixels,
                        light=light, write_log=os.path.join(self.store.batch_dir(row["batch_id"]), "writes.log"),
                        cancel_file=self.cancel_file(row["batch_id"]))

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
            import logging

            logging.getLogger("service.jobs").info("removed %d stale temporary file(s): %s", len(gone), gone[:5])
        return gone

    def _finish(self, batch_id: str) -> None:
        """Mark the batch done if nothing is left; then clear its temporaries."""
        if self.store.maybe_finish(batch_id):
            self.remove_stale_temporaries(batch_id)

    def _loop(self) -> None:
        try:  # what a killed server left being written (its writers hold their locks if still alive)
            self.remove_stale_temporaries()
        except Exception:
            import logging

            logging.getLogger("service.jobs").exception("removing stale temporaries failed")
        while not self._stop.is_set():
            try:
                self._tick()
            except Exception:  # keep the runner alive; the error is logged
                import logging

                logging.getLogger("service.jobs").exception("batch runner step failed")
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
        ``result_retention_s`` ago (:meth:`JobStore.delete_batch`). Returns their ids."""
        if self.config.result_retention_s < 0:
            return []
        return [bid for bid in self.store.expired_batches(self.config.result_retention_s)
                if self.store.delete_batch(bid) is not None]

    def _tick(self) -> None:
        now = time.monotonic()
        if now >= self._next_cleanup:  # at most every 30 s (sooner for a short retention)
            shortest = min(r for r in (self.config.input_retention_s, self.config.result_retention_s, 120.0)
                           if r >= 0)
            self._next_cleanup = now + min(30.0, max(self.config.poll_s, shortest / 4))
            self.remove_expired_inputs()
            self.remove_expired_batches()
        active = self.store.active_batches()[: max(1, self.config.max_concurrent_batches)]
        for bid in active:
            self.store.start_batch(bid)
        if not active:
            return
        try:
            capacity = 2 * self.executor.workers
            self.executor_error = None
        except Exception as e:  # e.g. the Dask scheduler is unreachable: items wait, the error is shown
            self.executor_error = f"executor_unavailable: {type(e).__name__}: {e}"
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
                        fut = self.executor.submit(process_item, self._task(row, options, light))
                    except Exception as e:  # a broken pool: fail the item, never leave it running
                        self.store.fail_item(bid, row["idx"], f"executor_error: {type(e).__name__}: {e}")
                        continue
                    with self._lock:
                        self._inflight[(bid, row["idx"])] = fut
                    fut.add_done_callback(lambda f, k=(bid, row["idx"]): self._done(k, f))
            self._finish(bid)

    def _done(self, key, fut) -> None:
        bid, idx = key
        with self._lock:
            self._inflight.pop(key, None)
        if fut.cancelled():  # dropped before it started
            self.store.cancel_item(bid, idx)
            self._finish(bid)
            return
        try:
            result = fut.result()
        except BaseException as e:  # the worker died (e.g. killed by the OOM killer)
            result = {"status": "failed", "error": f"worker_lost: {type(e).__name__}: {e}"}
        if result.get("status") == "cancelled":  # stopped by the batch's cancel, nothing written
            self.store.cancel_item(bid, idx)
        else:
            self.store.finish_item(bid, idx, result)
        self._finish(bid)
        self._wake.set()

    def _shared_light_step(self, bid: str, options: BatchOptions) -> None:
        """Shared mode: estimate every pending/running image's own light (in
        the pool), combine them into one light (:func:`shared_light`), store it. Items whose file
        cannot be read fail here, with their error."""
        fut = self._light_jobs.get(bid)
        if fut is None:
            rows = [r for r in self.store.items(bid) if r["status"] in ("pending", "running", "done")]
            futs = [(r, self.executor.submit(estimation_sample, self._task(r, options, None))) for r in rows]
            self._light_jobs[bid] = (futs, None)
            return
        futs, light_fut = fut
        if light_fut is None:
            if not all(f.done() for _, f in futs):
                return
            samples, cams = [], {}
            for r, f in futs:
                try:
                    s = f.result()
                except BaseException as e:
                    s = {"status": "failed", "error": f"worker_lost: {e}"}
                if s["status"] != "ok":
                    self.store.fail_item(bid, r["idx"], s["error"])
                    continue
                cams.setdefault(s["camera"].name, []).append((r, s))
            if not cams:
                self.store.set_light(bid, None, "no image of the batch could be read")
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
            self._light_jobs[bid] = (futs, light_fut)
            return
        if not light_fut.done():
            return
        self._light_jobs.pop(bid, None)
        try:
            light = light_fut.result()
            self.store.set_light(bid, light)
        except Exception as e:
            err = _error_text(e)
            self.store.set_light(bid, None, err)
            for r in self.store.items(bid):
                if r["status"] in ("pending", "running"):
                    self.store.fail_item(bid, r["idx"], f"shared light could not be estimated: {err}")
            self._finish(bid)
        self._wake.set()


def folder_sources(root: str, folder: str) -> list[tuple[str, str]]:
    """The RAW files directly in ``folder`` (relative to ``root``), refusing
    anything that resolves outside the root (``..``, absolute paths,
    symlinks leading out)."""
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
    out = []
    for entry in sorted(os.listdir(target)):
        p = os.path.join(target, entry)
        real = os.path.realpath(p)
        if os.path.commonpath([rootr, real]) != rootr:
            continue  # a symlink leading out of the root is never read
        if os.path.isfile(real) and entry.lower().endswith(RAW_SUFFIXES) and not entry.startswith("."):
            out.append((entry, real))
    if not out:
        raise ServiceError(422, "empty_folder", f"folder {folder!r} holds no RAW/TIFF/PNG files "
                           f"({', '.join(RAW_SUFFIXES[:6])}, ...)")
    return out
