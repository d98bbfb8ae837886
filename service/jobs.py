"""Batch jobs: a SQLite job store, the per-item function, a runner on a local
process pool or a Dask cluster, resume after a crash (issue 6).

No FastAPI here (options are validated by :mod:`service.options`, errors are
:class:`~service.errors.ServiceError`): the HTTP router
(:mod:`service.routers.batches`) and the CLI (:mod:`service.cli`) both drive
this module.

Every item is the white-balance pipeline of ``POST /v1/white-balance``
(:func:`service.pipeline.analyze` and :func:`service.pipeline.render_corrected`)
(Wandell 1985, Fig. 6 and eq. 22-25/36: estimate the light, then one 3x3
matrix per pixel from camera RGB to the display). In ``shared`` lighting
mode one light is made for all the images of the batch, and every image is
corrected with it: each image's own estimate (as per-image mode makes it)
combined by :func:`shared_light`, their confidence-weighted mean. (Pooling
the pixels into one stacked image, as before issue 19, made the light
depend on the number and layout of the images: N copies of one image moved
it 0.8 degrees.)

Exactly-once outputs
--------------------
An item's output appears only through ``os.replace`` of a complete temporary
file, so a partially written file never has the final name. The whole
"is it done already? else compute, write, rename" step runs under an
exclusive ``flock`` on the item's lock file, so a worker orphaned by a killed
server and the worker of the restarted server never both write: the second
finds the output (and its ``.json`` sidecar with the estimate, renamed into
place first) and adopts it. Every rename appends one line to the batch's
``writes.log``, which the tests use to check that nothing was written twice.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import sqlite3
import tempfile
import threading
import time
import uuid
from concurrent.futures import Future
from dataclasses import dataclass, field

from .errors import ServiceError, service_error
from .options import FORMATS, check_camera_name
from .schemas.options import LIGHTING, BatchOptions  # noqa: F401 (LIGHTING: named here too)

#: The environment variables that cap the internal thread pools of the
#: numerical libraries; set to 1 in every pool worker so that N workers use
#: N cores and do not fight over them.
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
              "VECLIB_MAXIMUM_THREADS", "OPENCV_FOR_THREADS_NUM")

RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".rw2", ".orf",
                ".pef", ".srw", ".x3f", ".3fr", ".iiq", ".erf", ".kdc", ".dcr", ".mrw", ".mos", ".rwl",
                ".tif", ".tiff", ".png")


# ---------------------------------------------------------------------------
# Options
# ---------------------------------------------------------------------------

def batch_options(**kw) -> BatchOptions:
    """Validated :class:`BatchOptions` (declared in :mod:`service.schemas.options`,
    with the checks of the white-balance endpoint, and a camera name checked
    now since the batch runs later); :class:`~service.errors.ServiceError`
    (422) naming the bad option and what is accepted. ``None`` and ``""``
    mean the default."""
    kw = {k: v for k, v in kw.items() if v is not None and v != ""}
    unknown = set(kw) - set(BatchOptions.model_fields)
    if unknown:
        raise ServiceError(422, "invalid_parameter", f"unknown options {sorted(unknown)}")
    opts = BatchOptions(**kw)
    check_camera_name(opts.camera)
    return opts


# ---------------------------------------------------------------------------
# The per-item functions (run in a pool worker or on a Dask worker)
# ---------------------------------------------------------------------------

def limit_threads() -> None:
    """Cap the numerical libraries at one thread in this process (pool and
    Dask workers: one item per core)."""
    for k in THREAD_ENV:
        os.environ[k] = "1"
    try:
        import cv2

        cv2.setNumThreads(1)
    except Exception:  # pragma: no cover - OpenCV is a dependency
        pass
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except Exception:
        pass


def _pool_worker_init() -> None:
    """Pool worker start-up: one numerical thread, and exit when the parent
    (the server or the CLI) is gone, so a killed server leaves no orphans
    (an item cut short this way is simply run again after the restart; its
    output never got its final name).

    Ctrl-C is the parent's to handle: a terminal sends SIGINT to the whole
    process group, and a worker dying of KeyboardInterrupt mid-item (or
    while idle) breaks the pool and prints tracebacks. The parent stops the
    workers with SIGTERM (:meth:`LocalExecutor.terminate`): the worker
    removes the temporary file it was writing and exits at once."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _exit_on_term)
    limit_threads()
    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


#: Temporary files this process is writing (:func:`atomic_write`), removed
#: when a pool worker is terminated.
_PARTS: set = set()


def _exit_on_term(signum, frame) -> None:  # pragma: no cover - runs in a pool worker
    for p in list(_PARTS):
        with contextlib.suppress(OSError):
            os.unlink(p)
    os._exit(128 + signum)


@dataclass(frozen=True)
class ItemTask:
    """Everything a worker needs for one item (plain data, picklable)."""

    src: str
    out: str
    name: str
    options: BatchOptions
    max_pixels: int
    estimation_pixels: int
    light: dict | None = None          # shared mode: the batch's light (light_json)
    write_log: str | None = None
    threads: int = 1
    #: False (single-file CLI): no lock, no sidecar, an existing output is replaced
    exactly_once: bool = True
    #: True (CLI --force): a finished output is computed again and replaced
    force: bool = False
    #: a file whose existence means "the batch was cancelled": the item
    #: stops at its next step without writing (:meth:`BatchRunner.cancel`)
    cancel_file: str | None = None
    #: the item's index in its batch (recorded in the sidecar; None: the CLI)
    index: int | None = None


class ItemCancelled(Exception):
    """The item's batch was cancelled while it ran (see ``ItemTask.cancel_file``)."""


def _check_cancel(task: ItemTask) -> None:
    if task.cancel_file and os.path.exists(task.cancel_file):
        raise ItemCancelled(task.name)


def _estimate_json(est, camera, profile=None) -> dict:
    from .pipeline import illuminant_json

    from recovery.api import LOW_CONFIDENCE

    conf = est.diagnostics.get("confidence")
    conf = float(conf) if isinstance(conf, (int, float)) else None
    return dict(illuminant_json(est, profile, camera), method=est.method, camera=camera.name, confidence=conf,
                low_confidence=conf is not None and conf < LOW_CONFIDENCE)


def _estimate_from_json(light: dict, camera):
    """The shared light as an estimate for ``camera``: the light's own camera
    RGB when it was estimated for this camera (shared lighting pools one
    camera), else the camera's response to the light's spectrum (eq. 1:
    rho_k = sum_n E R_k); its confidence is the shared estimate's."""
    import numpy as np

    from recovery import IlluminantEstimate

    spd = np.asarray(light["spectrum"], float)
    wl = np.asarray(light["wavelengths"], float)
    if wl.shape != camera.wavelengths.shape or not np.allclose(wl, camera.wavelengths):
        spd = np.interp(camera.wavelengths, wl, spd)
    rgb = np.asarray(light.get("camera_rgb") or [], float)
    if light.get("camera") != camera.name or rgb.shape != (camera.channels,):
        rgb = spd @ camera.sensitivities
        rgb = rgb / np.linalg.norm(rgb)
    diag = {"lighting": "shared"}
    if isinstance(light.get("confidence"), (int, float)):
        diag["confidence"] = float(light["confidence"])
    return IlluminantEstimate(rgb, spd, camera.wavelengths, light.get("method", "shared"), diag, [])


def _open(task: "ItemTask", prefetch: bool = False) -> tuple:
    """Decode an item's file and choose its camera (:func:`service.pipeline.open_image`;
    ``prefetch``: start the demosaic on a thread for the render that follows)."""
    from . import pipeline

    with open(task.src, "rb") as f:
        data = f.read()
    decoded, cam, warns, _ = pipeline.open_image(data, task.name or os.path.basename(task.src), task,
                                                 task.options.camera, prefetch=prefetch)
    return decoded, cam, warns


def _error_text(exc: BaseException) -> str:
    err = service_error(exc)
    if err is not None:
        return f"{err.code}: {err.detail}"
    code = getattr(exc, "code", None)
    detail = getattr(exc, "detail", None) or str(exc)
    return f"{code or type(exc).__name__}: {detail}"


def meta_path(out: str, suffix: str) -> str:
    """Where an output's sidecar (``.json``: the estimate) and lock file
    live: a hidden ``.wandell`` folder beside it."""
    d, base = os.path.split(out)
    return os.path.join(d, ".wandell", base + suffix)


@contextlib.contextmanager
def _item_lock(out: str):
    """One writer per output at a time (``flock`` on ``.wandell/NAME.lock``),
    the lock file removed when the item is done, so a batch leaves none.
    Removing a locked file is safe with the usual check: a process that
    got the lock on a file since unlinked (or replaced) opens it again."""
    import fcntl

    path = meta_path(out, ".lock")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    while True:
        fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                same = os.stat(path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
        except BaseException:
            os.close(fd)
            raise
        if same:
            break
        os.close(fd)  # the holder before us removed it: lock the current one
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # still holding the lock: nobody else owns this name now
        os.close(fd)  # closing releases the lock


def atomic_write(path: str, write) -> None:
    """``write(tmp)`` a temporary file beside ``path``, fsync it, then
    rename it to ``path``: the final name only ever holds a complete file."""
    d, base = os.path.split(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=".part", dir=d or ".")
    os.close(fd)
    _PARTS.add(tmp)
    os.chmod(tmp, 0o644)  # mkstemp makes 0600; results are ordinary files
    try:
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    finally:
        _PARTS.discard(tmp)


#: The temporaries :func:`atomic_write` makes: ``.NAME.XXXXXXXX.part``
#: (``tempfile.mkstemp``: 8 characters of ``a-z0-9_``); nothing else is one.
_TEMPORARY = re.compile(r"\.(.+)\.[a-z0-9_]{8}\.part", re.S)


def is_temporary(entry: str) -> bool:
    """Whether a file name is one of :func:`atomic_write`'s temporaries."""
    return _TEMPORARY.fullmatch(entry) is not None


def remove_stale_temporaries(out_dir: str, outputs=None, locked: str | None = None) -> list[str]:
    """Remove the temporaries (``.NAME.XXXXXXXX.part``) that a writer killed
    mid-write left in ``out_dir`` and its ``.wandell`` folder; returns them.

    Only :func:`atomic_write`'s own pattern is touched, only for outputs
    named in ``outputs`` (None: any), and each only while holding the item
    lock of its output (a writer still at work holds it, so its temporary is
    left alone); ``locked``: the output whose lock the caller holds."""
    import fcntl

    removed = []
    for d in (out_dir, os.path.dirname(meta_path(os.path.join(out_dir, "x"), ""))):
        try:
            entries = sorted(os.listdir(d))
        except OSError:
            continue
        for entry in entries:
            m = _TEMPORARY.fullmatch(entry)
            if m is None:
                continue
            final = m[1]
            if d != out_dir:  # a sidecar's: .<output>.json.XXXXXXXX.part
                if not final.endswith(".json"):
                    continue
                final = final[:-5]
            if outputs is not None and final not in outputs:
                continue
            path, out = os.path.join(d, entry), os.path.join(out_dir, final)
            if os.path.islink(path) or not os.path.isfile(path):
                continue
            fd = None
            if out != locked:
                try:
                    fd = os.open(meta_path(out, ".lock"), os.O_CREAT | os.O_RDWR, 0o644)
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:  # being written now (or no lock possible): not stale
                    if fd is not None:
                        os.close(fd)
                    continue
            try:
                os.unlink(path)
                removed.append(path)
            except OSError:
                pass
            finally:
                if fd is not None:
                    os.close(fd)
    return removed


def is_finished(out: str) -> bool:
    """An output counts as finished only when both the image and its sidecar
    (renamed into place before the image) exist under their final names."""
    return os.path.exists(out) and os.path.exists(meta_path(out, ".json"))


def process_item(task: ItemTask) -> dict:
    """Decode -> estimate (or take the shared light) -> correct -> encode ->
    write atomically, for one file (the white-balance pipeline of
    :mod:`service.pipeline`: eq. 36 and 23, Wandell 1985, one 3x3 matrix).

    Returns ``{"status": "done", "illuminant": ..., "adopted": bool,
    "seconds": ...}`` or ``{"status": "failed", "error": text}``, or
    ``{"status": "cancelled"}`` when the batch was cancelled before the item
    wrote anything (checked between the steps); never raises for a bad file
    (a corrupt file fails its item only).
    """
    from . import pipeline

    t0, c0 = time.perf_counter(), time.process_time()
    try:
        _check_cancel(task)
        with (_item_lock(task.out) if task.exactly_once else contextlib.nullcontext()):
            if task.exactly_once:  # under the lock: a temporary of this output is an earlier run's, killed
                remove_stale_temporaries(os.path.dirname(task.out), {os.path.basename(task.out)}, task.out)
            if task.exactly_once and not task.force and is_finished(task.out):  # written by an earlier run: adopt, never write twice
                with open(meta_path(task.out, ".json")) as f:
                    side = json.load(f)
                return {"status": "done", "illuminant": side.get("illuminant"), "adopted": True,
                        "seconds": time.perf_counter() - t0}
            # the demosaic overlaps the estimate when this item may use several
            # threads (wandell white-balance); a pool worker (one per core) does not
            decoded, cam, warns = _open(task, prefetch=task.threads != 1)
            opts = task.options.estimate_kwargs()
            try:
                _check_cancel(task)
                if task.light is None:
                    run = pipeline.run_estimate(decoded, cam, warns, method=task.options.method, options=opts)
                else:
                    run = pipeline.EstimateRun(_estimate_from_json(task.light, cam), cam, list(warns))
                _check_cancel(task)
            except BaseException:
                pipeline.drain_prefetch(decoded)
                raise
            fmt = FORMATS[task.options.format]
            out, M, info, meta = pipeline.render_corrected(decoded, run, target=task.options.target,
                                                           output=task.options.output, fmt=fmt,
                                                           surface_basis=opts.get("surface_basis"),
                                                           threads=task.threads, exposure=task.options.exposure)
            _check_cancel(task)  # the last point before anything is written
            file_warnings = list(decoded.warnings)
            profile = pipeline.profile_of(decoded)
            del decoded
            illum = _estimate_json(run.estimate, cam, profile)
            illum["warnings"] = list(run.camera_warnings) + file_warnings + list(run.estimate.warnings)
            side = {"name": task.name, "index": task.index, "illuminant": illum, "correction_matrix": M.tolist(),
                    "rendering": pipeline.rendering_json(info),
                    "options": task.options.as_dict()}
            if task.exactly_once:
                atomic_write(meta_path(task.out, ".json"), lambda p: write_text(p, json.dumps(_clean(side))))
            atomic_write(task.out, lambda p: pipeline.encode_image(out, fmt.encoder, p, meta=meta,
                                                                           threads=task.threads))
            if task.write_log:
                with open(task.write_log, "a") as f:
                    f.write(json.dumps({"name": task.name, "out": os.path.basename(task.out),
                                        "pid": os.getpid(), "time": time.time()}) + "\n")
            return {"status": "done", "illuminant": _clean(illum), "adopted": False,
                    "seconds": time.perf_counter() - t0, "cpu_seconds": time.process_time() - c0}
    except ItemCancelled:
        return {"status": "cancelled", "seconds": time.perf_counter() - t0}
    except MemoryError:
        return {"status": "failed", "error": "too_many_pixels: not enough memory for this image"}
    except Exception as exc:
        return {"status": "failed", "error": _error_text(exc)}


def write_text(path: str, text: str) -> None:
    """Write ``text`` to ``path`` (for :func:`atomic_write`)."""
    with open(path, "w") as f:
        f.write(text)


def _clean(obj):
    from .jsonsafe import clean

    return clean(obj)


def estimation_sample(task: ItemTask, pixels: int | None = None) -> dict:
    """Shared mode, step 1: an image's own estimate, made exactly as in
    per-image mode (:func:`service.pipeline.run_estimate` with the batch's
    method and options, on the analysis image of its ``quality``), with its
    camera and colour profile. ``pixels`` is not used (it was the share of a
    pooled image, which made the light depend on the number of images)."""
    from . import pipeline

    try:
        decoded, cam, warns = _open(task)
        run = pipeline.run_estimate(decoded, cam, warns, method=task.options.method,
                                    options=task.options.estimate_kwargs())
        profile = pipeline.profile_of(decoded)
        return {"status": "ok", "estimate": _clean(_estimate_json(run.estimate, cam, profile)),
                "warnings": list(run.estimate.warnings), "camera": cam, "profile": profile}
    except MemoryError:
        return {"status": "failed", "error": "too_many_pixels: not enough memory for this image"}
    except Exception as exc:
        return {"status": "failed", "error": _error_text(exc)}


def pool_images(images: list, masks: list):
    """Stack images (H_i, W_i, C) into one (sum H_i, max W_i, C) image, the
    padding masked out, so the estimator sees every image's regions."""
    import numpy as np

    width = max(im.shape[1] for im in images)
    rows, mrows = [], []
    for im, mk in zip(images, masks):
        pad = width - im.shape[1]
        m = np.ones(im.shape[:2], bool) if mk is None else np.asarray(mk, bool)
        rows.append(np.pad(np.asarray(im, np.float32), ((0, 0), (0, pad), (0, 0))))
        mrows.append(np.pad(m, ((0, 0), (0, pad)), constant_values=False))
    return np.concatenate(rows, 0), np.concatenate(mrows, 0)


#: Above this angle (degrees) between an image's own light and the shared
#: one, the shared light warns that the images may not share one light.
SHARED_SPREAD_WARN_DEG = 3.0


def shared_light(samples: list, options: BatchOptions) -> dict:
    """Shared mode, step 2: one light for all the images, from their own
    estimates (:func:`estimation_sample`, one camera): the mean of their
    lights (camera RGB and spectrum, each scaled to a unit camera response,
    then back to the mean scale), weighted by their confidence when every
    one has one, else equally. N identical images therefore give that
    image's own estimate whatever N (pooling their pixels into one image
    did not: the light moved with the number and layout of the images).

    Its ``confidence`` is the weighted mean of theirs times
    ``1 / (1 + (rms / 3 deg)^2)``, ``rms`` the weighted RMS angle of the
    images' lights to the shared one (the just-visible error of
    :data:`service.pipeline.VISIBLE_WB_ERROR_DEG`): images that agree keep
    their confidence, images that disagree lower it, and above 3 degrees a
    warning says so. Returns the light as JSON (``camera_rgb``,
    ``spectrum``, ``cct``..., ``confidence``, ``images``: how many were
    combined, ``image_angles_deg``: each image's light to the shared one)."""
    import numpy as np

    from recovery import IlluminantEstimate, angular_error

    from .pipeline import VISIBLE_WB_ERROR_DEG

    cam = samples[0]["camera"]
    ests = [s["estimate"] for s in samples]
    rgbs = np.array([e["camera_rgb"] for e in ests], float)
    spds = np.array([e["spectrum"] for e in ests], float)
    wl = np.asarray(ests[0]["wavelengths"], float)
    norms = np.linalg.norm(rgbs, axis=1)
    confs = [e.get("confidence") for e in ests]
    have_conf = all(isinstance(c, (int, float)) and c > 0 for c in confs)
    w = np.array(confs, float) if have_conf else np.ones(len(ests))
    w = w / w.sum()
    scale = float(w @ norms)
    rgb = (w @ (rgbs / norms[:, None])) * scale
    spd = (w @ (spds / norms[:, None])) * scale
    angles = np.array([float(angular_error(r, rgb)) for r in rgbs])
    rms = float(np.sqrt(w @ angles ** 2))
    warnings = [x for x in dict.fromkeys(x for s in samples for x in s.get("warnings", []))
                if all(x in s.get("warnings", []) for s in samples)]
    if angles.max() > SHARED_SPREAD_WARN_DEG:
        warnings.append(f"the images' own lights are up to {angles.max():.1f} degrees from the shared light "
                        f"(RMS {rms:.1f}): they may not all be under one light")
    diag = {"lighting": "shared"}
    if have_conf:
        diag["confidence"] = float(w @ np.array(confs, float)) / (1.0 + (rms / VISIBLE_WB_ERROR_DEG) ** 2)
    methods = {e.get("method") for e in ests}
    est = IlluminantEstimate(rgb, spd, wl, methods.pop() if len(methods) == 1 else "shared", diag, warnings)
    light = _estimate_json(est, cam, samples[0].get("profile"))
    light["images"] = len(samples)
    light["image_angles_deg"] = angles.tolist()
    light["warnings"] = warnings
    return _clean(light)


# ---------------------------------------------------------------------------
# Executors: a local process pool or a Dask cluster, one interface
# ---------------------------------------------------------------------------

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


class LocalExecutor:
    """A process pool (spawn: no fork of a threaded server), each worker
    capped at one numerical thread."""

    kind = "local"

    def __init__(self, workers: int):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.workers = max(1, int(workers))
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
    installed and the data directory (or batch root) at the same path."""

    kind = "dask"

    def __init__(self, scheduler=None, client=None, timeout: float = 20.0):
        from distributed import Client

        self._own = client is None
        self.client = client if client is not None else Client(scheduler, timeout=f"{timeout}s")
        self.workers = max(1, sum(w.get("nthreads", 1)
                                  for w in self.client.scheduler_info().get("workers", {}).values()))

    def submit(self, fn, *args) -> Future:
        fut: Future = Future()
        dfut = self.client.submit(_dask_call, fn, *args, pure=False)

        def done(df):
            try:
                fut.set_result(df.result())
            except BaseException as e:  # a lost worker, a cancelled task
                fut.set_exception(e)

        fut.set_running_or_notify_cancel()
        dfut.add_done_callback(done)
        return fut

    def shutdown(self, wait: bool = True) -> None:
        if self._own:
            self.client.close()


def make_executor(workers: int | None = None, scheduler: str | None = None, timeout: float = 20.0):
    """Dask when a scheduler address is given, else the local pool."""
    if scheduler:
        return DaskExecutor(scheduler, timeout=timeout)
    return LocalExecutor(workers or default_workers())


# ---------------------------------------------------------------------------
# The SQLite job store
# ---------------------------------------------------------------------------

_SCHEMA = """
CREATE TABLE IF NOT EXISTS batches (
    id TEXT PRIMARY KEY,
    created REAL NOT NULL,
    started REAL,
    finished REAL,
    status TEXT NOT NULL CHECK (status IN ('queued', 'running', 'done', 'cancelled')),
    options TEXT NOT NULL,
    dir TEXT NOT NULL,
    light TEXT,
    light_error TEXT
);
CREATE TABLE IF NOT EXISTS items (
    batch_id TEXT NOT NULL REFERENCES batches(id),
    idx INTEGER NOT NULL,
    name TEXT NOT NULL,
    src TEXT NOT NULL,
    out TEXT NOT NULL,
    status TEXT NOT NULL CHECK (status IN ('pending', 'running', 'done', 'failed', 'cancelled')),
    error TEXT,
    illuminant TEXT,
    attempts INTEGER NOT NULL DEFAULT 0,
    completions INTEGER NOT NULL DEFAULT 0,
    started REAL,
    finished REAL,
    PRIMARY KEY (batch_id, idx)
);
CREATE INDEX IF NOT EXISTS items_status ON items(batch_id, status);
"""


#: Longest file name, in UTF-8 bytes, the batch endpoint accepts (the usual
#: file-system limit, NAME_MAX); longer ones are refused (422).
MAX_NAME_BYTES = 255
#: Longest name the service itself gives a file on disk (inputs, outputs):
#: room for the ``.<name>.XXXXXXXX.part`` temporaries and ``.json``/``.lock``
#: sidecars next to them within NAME_MAX.
DISK_NAME_BYTES = 200


def clip_name(name: str, limit: int = DISK_NAME_BYTES) -> str:
    """``name`` cut to at most ``limit`` UTF-8 bytes on a character boundary,
    keeping its extension (so the format is still recognised)."""
    if len(name.encode("utf-8")) <= limit:
        return name
    stem, ext = os.path.splitext(name)
    if len(ext.encode("utf-8")) > limit // 4:
        stem, ext = name, ""
    return stem.encode("utf-8")[:limit - len(ext.encode("utf-8"))].decode("utf-8", "ignore") + ext


def safe_name(name: str) -> str:
    """A file name with no directory part, no control characters and no
    unpaired surrogates, at most :data:`MAX_NAME_BYTES` bytes."""
    base = os.path.basename(str(name).replace("\\", "/")) or "file"
    base = base.encode("utf-8", "replace").decode("utf-8")
    base = re.sub(r"[\x00-\x1f/]", "_", base).strip() or "file"
    return clip_name(base, MAX_NAME_BYTES)


#: Beside each batch's ``in/`` and ``out/``: the manifest of its items
#: (written once, with the batch) and the journal of their state changes,
#: from which a damaged job store is rebuilt.
MANIFEST = "batch.json"
JOURNAL = "states.jsonl"


def _read_sidecar(out: str) -> dict | None:
    """The ``.json`` sidecar of a finished output, or None (not finished, unreadable)."""
    if not is_finished(out):
        return None
    try:
        with open(meta_path(out, ".json")) as f:
            side = json.load(f)
    except (OSError, ValueError):
        return None
    return side if isinstance(side, dict) else None


#: An item index in a URL: ASCII digits only (``str.isdigit`` also accepts
#: ``²`` and other digits ``int`` refuses), at most 18 of them (64-bit).
_INDEX_TEXT = re.compile(r"[0-9]{1,18}")


class JobStore:
    """Batches and items in SQLite (WAL), every state change one atomic
    ``UPDATE ... WHERE status = <expected>`` inside a transaction."""

    def __init__(self, data_dir: str):
        self.data_dir = os.path.abspath(data_dir)
        os.makedirs(os.path.join(self.data_dir, "batches"), exist_ok=True)
        self.path = os.path.join(self.data_dir, "jobs.sqlite")
        self._local = threading.local()
        #: where a damaged store was moved at start-up, and the batches whose
        #: results were re-registered from disk (None: it opened cleanly)
        self.recovered: dict | None = None
        try:
            self._open_checked()
        except sqlite3.DatabaseError as e:
            self._recover(e)

    def _open_checked(self) -> None:
        db = self._db()
        check = db.execute("PRAGMA quick_check").fetchone()[0]
        if check != "ok":
            raise sqlite3.DatabaseError(f"quick_check: {check}")
        db.executescript(_SCHEMA)

    def _recover(self, error: Exception) -> None:
        """A damaged ``jobs.sqlite`` (and its WAL) is moved aside, kept for
        inspection, and a fresh store started; the results already on disk
        are registered again (:meth:`adopt_from_disk`), so they stay
        reachable. Single-file endpoints never depended on the store."""
        import logging

        db = getattr(self._local, "db", None)
        if db is not None:
            with contextlib.suppress(Exception):
                db.close()
            self._local.db = None
        aside = f"{self.path}.damaged-{time.strftime('%Y%m%d-%H%M%S')}-{uuid.uuid4().hex[:6]}"
        for suffix in ("", "-wal", "-shm"):
            if os.path.exists(self.path + suffix):
                os.replace(self.path + suffix, aside + suffix)
        logging.getLogger("service.jobs").error("the job store %s was damaged (%s: %s); moved to %s and a fresh "
                                                "store started", self.path, type(error).__name__, error, aside)
        self._open_checked()
        adopted = self.adopt_from_disk()
        self.recovered = {"damaged_copy": aside, "error": f"{type(error).__name__}: {error}",
                          "batches_recovered": adopted}

    def adopt_from_disk(self) -> int:
        """Register every batch directory the store does not know, from what
        is on disk. A batch's manifest (``batch.json``, written with the
        batch: each item's index, name, input and output) and its state
        journal (``states.jsonl``: every item's end, the batch's end, the
        shared light) give back the same items at the same indices in the
        same states: done where the output and its sidecar are finished on
        disk, failed or cancelled as journalled, and items that had not
        finished pending again (their batch re-queued) while their input is
        still there. Batches from before the manifest are rebuilt from their
        inputs' names (:meth:`_legacy_rows`). Returns how many batches."""
        root = os.path.join(self.data_dir, "batches")
        n = 0
        for bid in sorted(os.listdir(root)):
            bdir = os.path.join(root, bid)
            if not os.path.isdir(bdir) or self.batch(bid) is not None:
                continue
            try:
                with open(os.path.join(bdir, MANIFEST)) as f:
                    manifest = json.load(f)
                options = BatchOptions(**manifest["options"])
                items = [(int(it["index"]), str(it["name"]), str(it["src"]), str(it["out"]))
                         for it in manifest["items"]]
            except (OSError, ValueError, TypeError, KeyError):
                manifest = None
            if manifest is None:
                rows, options = self._legacy_rows(bdir)
                status, created, light = "done", os.path.getmtime(bdir), (None, None)
            else:
                rows, status, light = self._manifest_rows(bdir, items)
                created = float(manifest.get("created") or os.path.getmtime(bdir))
            if not rows:
                continue
            now = time.time()
            with self._tx() as db:
                db.execute("INSERT INTO batches (id, created, started, finished, status, options, dir, light, "
                           "light_error) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                           (bid, created, None if status == "queued" else now,
                            None if status == "queued" else now, status, (options or BatchOptions()).to_json(),
                            bdir, *light))
                db.executemany("INSERT INTO items (batch_id, idx, name, src, out, status, error, illuminant, "
                               "completions, finished) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                               [(bid, *r, int(r[4] == "done"), None if r[4] == "pending" else now)
                                for r in rows])
            n += 1
        return n

    def _manifest_rows(self, bdir: str, items: list) -> tuple[list, str, tuple]:
        """Rows ``(idx, name, src, out, status, error, illuminant)`` of a
        batch with a manifest, its status and its (light, light_error)."""
        states, batch_state, light = {}, None, (None, None)
        with contextlib.suppress(OSError):
            with open(os.path.join(bdir, JOURNAL)) as f:
                for line in f:
                    try:
                        rec = json.loads(line)
                    except ValueError:  # a line torn by a crash
                        continue
                    if "idx" in rec:
                        states[rec["idx"]] = rec
                    elif "batch" in rec:
                        batch_state = rec["batch"]
                    elif "light" in rec:
                        light = (None if rec["light"] is None else json.dumps(rec["light"]), rec.get("light_error"))
        rows, waiting = [], False
        for idx, name, src, out in items:
            src = src if os.path.isabs(src) else os.path.join(bdir, src)
            out = os.path.join(bdir, "out", out)
            rec = states.get(idx) or {}
            side = _read_sidecar(out)
            if side is not None:
                rows.append((idx, name, src, out, "done", None, json.dumps(side.get("illuminant"))))
            elif rec.get("status") in ("failed", "cancelled"):
                rows.append((idx, name, src, out, rec["status"], rec.get("error"), None))
            elif batch_state == "cancelled":
                rows.append((idx, name, src, out, "cancelled", None, None))
            elif os.path.isfile(src) and batch_state != "done":
                rows.append((idx, name, src, out, "pending", None, None))
                waiting = True
            else:
                rows.append((idx, name, src, out, "failed", "store_recovered: the job store was damaged before "
                             "this item finished and its input is gone; submit it again", None))
        status = "cancelled" if batch_state == "cancelled" else ("queued" if waiting else "done")
        return rows, status, light

    def _legacy_rows(self, bdir: str) -> tuple[list, "BatchOptions | None"]:
        """Rows of a batch written before manifests: the uploaded inputs
        (``NNNNN-name``: index and name) named again as
        :meth:`create_batch` named them, so uniquified names (``A (2).dng``)
        and their outputs match; finished outputs (``.``-names included)
        done, the other inputs failed; outputs with no input (folder mode,
        inputs removed) after them."""
        out_dir, in_dir = os.path.join(bdir, "out"), os.path.join(bdir, "in")
        done, options = {}, None
        if os.path.isdir(out_dir):
            for entry in sorted(os.listdir(out_dir)):
                out = os.path.join(out_dir, entry)
                side = None if is_temporary(entry) or not os.path.isfile(out) else _read_sidecar(out)
                if side is None:
                    continue
                with contextlib.suppress(TypeError):
                    options = options or BatchOptions(**side.get("options", {}))
                done[entry] = side
        inputs = []
        if os.path.isdir(in_dir):
            for entry in os.listdir(in_dir):
                m = re.fullmatch(r"([0-9]{5})-(.*)", entry, re.S)
                if m:
                    inputs.append((int(m[1]), m[2], os.path.join(in_dir, entry)))
        ext = (options or BatchOptions()).extension
        rows, seen, outs = [], set(), set()
        for idx, orig, src in sorted(inputs):
            name = unique(safe_name(orig), seen)
            out = unique(clip_name(f"{os.path.splitext(name)[0]}.{ext}", DISK_NAME_BYTES - 12), outs)
            side = done.pop(out, None)
            if side is not None:
                rows.append((idx, name, src, os.path.join(out_dir, out), "done", None,
                             json.dumps(side.get("illuminant"))))
            else:
                rows.append((idx, name, src, os.path.join(out_dir, out), "failed", "store_recovered: the job "
                             "store was damaged before this item finished; submit it again", None))
        nxt = max([r[0] for r in rows], default=-1) + 1
        for entry, side in done.items():
            rows.append((nxt, str(side.get("name") or entry), "", os.path.join(out_dir, entry), "done", None,
                         json.dumps(side.get("illuminant"))))
            nxt += 1
        return rows, options

    def _journal(self, batch_id: str, **record) -> None:
        """Append one state change to the batch's ``states.jsonl`` (what
        :meth:`adopt_from_disk` rebuilds a damaged store from). Best effort:
        a full disk loses a line, never the transition."""
        record["t"] = time.time()
        with contextlib.suppress(OSError, TypeError, ValueError):
            line = json.dumps(_clean(record)) + "\n"
            with open(os.path.join(self.batch_dir(batch_id), JOURNAL), "a") as f:
                f.write(line)

    def _db(self) -> sqlite3.Connection:
        db = getattr(self._local, "db", None)
        if db is None:
            db = sqlite3.connect(self.path, timeout=30, isolation_level=None)
            db.row_factory = sqlite3.Row
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=NORMAL")
            self._local.db = db
        return db

    @contextlib.contextmanager
    def _tx(self):
        db = self._db()
        db.execute("BEGIN IMMEDIATE")
        try:
            yield db
        except BaseException:
            db.execute("ROLLBACK")
            raise
        db.execute("COMMIT")

    # -- creation ----------------------------------------------------------
    def batch_dir(self, batch_id: str) -> str:
        return os.path.join(self.data_dir, "batches", batch_id)

    def new_batch_id(self) -> str:
        bid = uuid.uuid4().hex[:16]
        os.makedirs(os.path.join(self.batch_dir(bid), "in"), exist_ok=True)
        os.makedirs(os.path.join(self.batch_dir(bid), "out"), exist_ok=True)
        return bid

    def create_batch(self, batch_id: str, options: BatchOptions, sources: list[tuple[str, str]]) -> None:
        """Register a batch of ``(name, source path)`` items, all pending.
        Names are made unique (``a.dng``, ``a (2).dng``); output names are
        ``<stem>.<ext>``, made unique the same way."""
        seen, outs, rows = set(), set(), []
        out_dir = os.path.join(self.batch_dir(batch_id), "out")
        for i, (name, src) in enumerate(sources):
            nm = unique(safe_name(name), seen)
            stem = os.path.splitext(nm)[0]
            # the output's name on disk stays short enough for its temporaries and sidecars
            out = unique(clip_name(f"{stem}.{options.extension}", DISK_NAME_BYTES - 12), outs)
            rows.append((batch_id, i, nm, os.path.abspath(src), os.path.join(out_dir, out)))
        bdir, created = self.batch_dir(batch_id), time.time()
        manifest = {"id": batch_id, "created": created, "options": options.as_dict(),
                    "items": [{"index": r[1], "name": r[2], "out": os.path.basename(r[4]),
                               "src": os.path.relpath(r[3], bdir) if r[3].startswith(bdir + os.sep) else r[3]}
                              for r in rows]}
        os.makedirs(bdir, exist_ok=True)
        atomic_write(os.path.join(bdir, MANIFEST), lambda p: write_text(p, json.dumps(manifest)))
        with self._tx() as db:
            db.execute("INSERT INTO batches (id, created, status, options, dir) VALUES (?, ?, 'queued', ?, ?)",
                       (batch_id, created, options.to_json(), bdir))
            db.executemany("INSERT INTO items (batch_id, idx, name, src, out, status) "
                           "VALUES (?, ?, ?, ?, ?, 'pending')", rows)

    # -- reading -------------------------------------------------------------
    def batch(self, batch_id: str):
        return self._db().execute("SELECT * FROM batches WHERE id = ?", (batch_id,)).fetchone()

    def items(self, batch_id: str) -> list:
        return self._db().execute("SELECT * FROM items WHERE batch_id = ? ORDER BY idx", (batch_id,)).fetchall()

    def item_by_index(self, batch_id: str, index):
        """The item at ``index`` (an int, or its ASCII decimal digits); None
        for anything else: other Unicode digits (``²``), signs, spaces, or
        more digits than any index can have (never an error)."""
        if not isinstance(index, int):
            if not isinstance(index, str) or not _INDEX_TEXT.fullmatch(index):
                return None
            index = int(index)
        if not 0 <= index < 2 ** 63:
            return None
        return self._db().execute("SELECT * FROM items WHERE batch_id = ? AND idx = ?", (batch_id, index)).fetchone()

    def item_by_name(self, batch_id: str, name: str):
        """The item of this (stored, made-unique) name, or None."""
        return self._db().execute("SELECT * FROM items WHERE batch_id = ? AND name = ?",
                                  (batch_id, str(name))).fetchone()

    def item(self, batch_id: str, key: str):
        """An item by name or by index (the ``items/{key}`` URL, which takes
        both). A key that names one item and is the index of another is
        ambiguous: :class:`~service.errors.ServiceError` 409
        ``ambiguous_item``, never the wrong file (``by-index`` / ``by-name``
        say which is meant)."""
        by_name = self.item_by_name(batch_id, key)
        by_index = self.item_by_index(batch_id, key)
        if by_name is not None and by_index is not None and by_name["idx"] != by_index["idx"]:
            raise ServiceError(409, "ambiguous_item",
                               f"{key!r} is the name of item {by_name['idx']} and the index of item "
                               f"{by_index['idx']} ({by_index['name']!r}): ask for items/by-index/{key} (item "
                               f"{by_index['idx']}) or items/by-name/{key} (item {by_name['idx']})")
        return by_name if by_name is not None else by_index

    def counts(self, batch_id: str) -> dict:
        c = {s: 0 for s in ("pending", "running", "done", "failed", "cancelled")}
        for row in self._db().execute("SELECT status, COUNT(*) FROM items WHERE batch_id = ? GROUP BY status",
                                      (batch_id,)):
            c[row[0]] = row[1]
        return c

    def active_batches(self) -> list:
        return [r["id"] for r in self._db().execute(
            "SELECT id FROM batches WHERE status IN ('queued', 'running') ORDER BY created")]

    # -- transitions -----------------------------------------------------------
    def resume(self) -> int:
        """After a crash: items left ``running`` go back to ``pending``
        (their worker died with the server; the item lock and the adopt rule
        of :func:`process_item` keep a still-running orphan from writing
        twice). Returns how many were re-queued."""
        with self._tx() as db:
            n = db.execute("UPDATE items SET status = 'pending' WHERE status = 'running' AND batch_id IN "
                           "(SELECT id FROM batches WHERE status IN ('queued', 'running'))").rowcount
            # a batch cancelled while items ran: their workers died with the server
            db.execute("UPDATE items SET status = 'cancelled', finished = ? WHERE status = 'running' AND "
                       "batch_id IN (SELECT id FROM batches WHERE status = 'cancelled')", (time.time(),))
        return n

    def start_batch(self, batch_id: str) -> bool:
        with self._tx() as db:
            return db.execute("UPDATE batches SET status = 'running', started = COALESCE(started, ?) "
                              "WHERE id = ? AND status = 'queued'", (time.time(), batch_id)).rowcount == 1

    def claim(self, batch_id: str, limit: int) -> list:
        """Move up to ``limit`` pending items to running; returns them."""
        with self._tx() as db:
            rows = db.execute("SELECT * FROM items WHERE batch_id = ? AND status = 'pending' ORDER BY idx LIMIT ?",
                              (batch_id, limit)).fetchall()
            for r in rows:
                db.execute("UPDATE items SET status = 'running', attempts = attempts + 1, started = ? "
                           "WHERE batch_id = ? AND idx = ? AND status = 'pending'", (time.time(), batch_id, r["idx"]))
        return rows

    def finish_item(self, batch_id: str, idx: int, result: dict) -> bool:
        """``running`` -> ``done`` (with the estimate) or ``failed`` (with the
        error), in one transaction; False if the item was no longer running
        (cancelled meanwhile)."""
        ok = result.get("status") == "done"
        with self._tx() as db:
            n = db.execute(
                "UPDATE items SET status = ?, error = ?, illuminant = ?, finished = ?, "
                "completions = completions + 1 WHERE batch_id = ? AND idx = ? AND status = 'running'",
                ("done" if ok else "failed", None if ok else str(result.get("error")),
                 json.dumps(result.get("illuminant")) if ok else None, time.time(), batch_id, idx)).rowcount
        if n == 1:
            self._journal(batch_id, idx=idx, status="done" if ok else "failed",
                          error=None if ok else str(result.get("error")))
        return n == 1

    def fail_item(self, batch_id: str, idx: int, error: str) -> None:
        with self._tx() as db:
            n = db.execute("UPDATE items SET status = 'failed', error = ?, finished = ? "
                           "WHERE batch_id = ? AND idx = ? AND status IN ('pending', 'running')",
                           (error, time.time(), batch_id, idx)).rowcount
        if n:
            self._journal(batch_id, idx=idx, status="failed", error=error)

    def cancel_item(self, batch_id: str, idx: int) -> None:
        """``running`` -> ``cancelled`` for an item dropped before it started."""
        with self._tx() as db:
            n = db.execute("UPDATE items SET status = 'cancelled', finished = ? WHERE batch_id = ? AND idx = ? "
                           "AND status = 'running'", (time.time(), batch_id, idx)).rowcount
        if n:
            self._journal(batch_id, idx=idx, status="cancelled")

    def expired_inputs(self, retention_s: float) -> list[str]:
        """The upload folders (``<batch>/in``) of batches finished or cancelled
        more than ``retention_s`` seconds ago with nothing still running and
        something left to remove. Folder-mode sources are never listed: they
        are the user's files, outside the data directory."""
        rows = self._db().execute(
            "SELECT id FROM batches WHERE status IN ('done', 'cancelled') AND finished IS NOT NULL "
            "AND finished <= ? AND id NOT IN (SELECT batch_id FROM items WHERE status = 'running')",
            (time.time() - retention_s,)).fetchall()
        out = []
        for r in rows:
            d = os.path.join(self.batch_dir(r["id"]), "in")
            if os.path.isdir(d) and os.listdir(d):
                out.append(d)
        return out

    def set_light(self, batch_id: str, light: dict | None, error: str | None = None) -> None:
        with self._tx() as db:
            db.execute("UPDATE batches SET light = ?, light_error = ? WHERE id = ?",
                       (None if light is None else json.dumps(light), error, batch_id))
        self._journal(batch_id, light=light, light_error=error)

    def maybe_finish(self, batch_id: str) -> bool:
        """``running`` -> ``done`` once no item is pending or running."""
        with self._tx() as db:
            left = db.execute("SELECT COUNT(*) FROM items WHERE batch_id = ? AND status IN ('pending', 'running')",
                              (batch_id,)).fetchone()[0]
            if left:
                return False
            done = db.execute("UPDATE batches SET status = 'done', finished = ? WHERE id = ? AND status = "
                              "'running'", (time.time(), batch_id)).rowcount == 1
        if done:
            self._journal(batch_id, batch="done")
        return done

    def cancel(self, batch_id: str) -> bool:
        """Cancel: pending items are cancelled at once; running ones stay
        ``running`` until their worker answers (``cancelled`` when it
        stopped, ``done`` and kept when it had finished: see
        :meth:`BatchRunner.cancel`); the batch is ``cancelled``. False if it
        had already finished."""
        with self._tx() as db:
            n = db.execute("UPDATE batches SET status = 'cancelled', finished = ? WHERE id = ? AND status IN "
                           "('queued', 'running')", (time.time(), batch_id)).rowcount
            if n:
                db.execute("UPDATE items SET status = 'cancelled' WHERE batch_id = ? AND status = 'pending'",
                           (batch_id,))
        if n:
            self._journal(batch_id, batch="cancelled")
        return n == 1

    def progress(self, batch_id: str) -> dict | None:
        """The status document of ``GET /v1/batches/{id}``."""
        b = self.batch(batch_id)
        if b is None:
            return None
        rows = self.items(batch_id)
        c = self.counts(batch_id)
        now = time.time()
        finished = c["done"] + c["failed"]
        left = c["pending"] + c["running"]
        elapsed = ((b["finished"] or now) - b["started"]) if b["started"] else 0.0
        rate = finished / elapsed * 60 if elapsed > 0 and finished else None
        eta = (left / (rate / 60)) if rate and b["status"] in ("queued", "running") else (0.0 if not left else None)
        items = []
        for r in rows:
            it = {"index": r["idx"], "name": r["name"], "status": r["status"],
                  "output": os.path.basename(r["out"]) if r["status"] == "done" else None}
            if r["error"]:
                it["error"] = r["error"]
            if r["illuminant"]:
                ill = json.loads(r["illuminant"])
                it["illuminant"] = {k: ill.get(k) for k in ("camera_rgb", "wb_multipliers", "cct", "duv",
                                                            "method", "camera", "warnings", "confidence",
                                                            "low_confidence")}
            items.append(it)
        opts = json.loads(b["options"])
        # settled: the batch is over and every count final (a cancelled
        # batch's running items are still stopping until this is true)
        settled = b["status"] in ("done", "cancelled") and left == 0
        doc = {"id": batch_id, "status": b["status"], "settled": settled,
               "lighting": opts.get("lighting"), "options": opts,
               "counts": {"done": c["done"], "failed": c["failed"], "pending": left, "running": c["running"],
                          "cancelled": c["cancelled"], "total": len(rows)},
               "rate_per_minute": rate, "time_left_s": eta, "elapsed_s": elapsed,
               "rate": rate, "eta_s": eta,  # short names the web page reads
               "created": b["created"], "items": items}
        if opts.get("lighting") == "shared" and not b["light"] and b["status"] == "running":
            doc["phase"] = "estimating the shared light from all images"
        if b["light"]:
            doc["shared_light"] = json.loads(b["light"])
        if b["light_error"]:
            doc["shared_light_error"] = b["light_error"]
        return doc


def unique(name: str, seen: set) -> str:
    """``name``, or ``stem (k).ext`` with the smallest free k."""
    cand, k = name, 2
    stem, ext = os.path.splitext(name)
    while cand.lower() in seen:
        cand = f"{stem} ({k}){ext}"
        k += 1
    seen.add(cand.lower())
    return cand


# ---------------------------------------------------------------------------
# The runner
# ---------------------------------------------------------------------------

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

    def _tick(self) -> None:
        now = time.monotonic()
        if now >= self._next_cleanup:  # at most every 30 s (sooner for a short retention)
            self._next_cleanup = now + min(30.0, max(self.config.poll_s, self.config.input_retention_s / 4))
            self.remove_expired_inputs()
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

