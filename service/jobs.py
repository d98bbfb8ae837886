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
mode the light is estimated once from all the images of the batch pooled
together: images taken under one light lie in the same D(S)-dimensional
subspace of sensor space (eq. 26-29), so pooling only adds evidence for the
subspace normal (eq. 30), and every image is then corrected with that light.

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
from dataclasses import asdict, dataclass, field

from .errors import ServiceError, service_error
from .options import FORMATS, IMAGE_FORMATS, check_camera_name, check_output, check_target, choose_format, \
    estimate_options, parse_exposure

#: The environment variables that cap the internal thread pools of the
#: numerical libraries; set to 1 in every pool worker so that N workers use
#: N cores and do not fight over them.
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
              "VECLIB_MAXIMUM_THREADS", "OPENCV_FOR_THREADS_NUM")

LIGHTING = ("per-image", "shared")
RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".rw2", ".orf",
                ".pef", ".srw", ".x3f", ".3fr", ".iiq", ".erf", ".kdc", ".dcr", ".mrw", ".mos", ".rwl",
                ".tif", ".tiff", ".png")


def shared_pool_pixels() -> int:
    """Pixels of pooled estimation data in ``shared`` mode (split between the
    images): the same budget as one image's estimation without a quality
    preset (:data:`recovery.DEFAULT_ANALYSIS_PIXELS`; imported here, not at
    the top, so that the CLI's start-up imports no numerical library)."""
    from recovery import DEFAULT_ANALYSIS_PIXELS

    return DEFAULT_ANALYSIS_PIXELS


# ---------------------------------------------------------------------------
# Options
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class BatchOptions:
    """The white-balance options of ``POST /v1/white-balance`` plus the
    lighting mode; validated by :func:`batch_options`."""

    camera: str | None = None
    method: str = "auto"
    quality: str | None = None
    target: str = "D65"
    output: str = "sRGB"
    format: str = "tiff"
    lighting: str = "per-image"
    surface_model: str | None = None
    light_model: str | None = None
    surface_dim: str | None = None
    light_dim: str | None = None
    region_size: int | None = None
    exposure: float | None = None          # EV; None: the auto rule (recovery.synthesis.exposure_gain)

    @property
    def extension(self) -> str:
        return FORMATS[self.format].extension

    def estimate_kwargs(self) -> dict:
        """Keyword options of :func:`recovery.estimate_illuminant` (the same
        validation as the white-balance endpoint)."""
        return estimate_options(self.method, self.surface_dim, self.light_dim, self.region_size, False,
                                self.surface_model, self.light_model, self.quality)

    def to_json(self) -> str:
        return json.dumps(asdict(self), sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "BatchOptions":
        return cls(**json.loads(text))


def batch_options(**kw) -> BatchOptions:
    """Validated :class:`BatchOptions`; :class:`~service.errors.ServiceError`
    (422) naming the bad option and what is accepted."""
    kw = {k: v for k, v in kw.items() if v is not None and v != ""}
    unknown = set(kw) - set(BatchOptions.__dataclass_fields__)
    if unknown:
        raise ServiceError(422, "invalid_parameter", f"unknown options {sorted(unknown)}")
    if "exposure" in kw:
        kw["exposure"] = parse_exposure(kw["exposure"])
    opts = BatchOptions(**kw)
    choose_format(opts.format, IMAGE_FORMATS)
    check_output(opts.output)
    if opts.lighting not in LIGHTING:
        raise ServiceError(422, "invalid_parameter",
                           f"lighting {opts.lighting!r} unknown; accepted: {list(LIGHTING)}")
    check_target(opts.target)
    check_camera_name(opts.camera)
    opts.estimate_kwargs()
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
    output never got its final name)."""
    limit_threads()
    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


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


def _estimate_json(est, camera_name: str) -> dict:
    from .pipeline import illuminant_json

    from recovery.api import LOW_CONFIDENCE

    conf = est.diagnostics.get("confidence")
    conf = float(conf) if isinstance(conf, (int, float)) else None
    return dict(illuminant_json(est), method=est.method, camera=camera_name, confidence=conf,
                low_confidence=conf is not None and conf < LOW_CONFIDENCE)


def _estimate_from_json(light: dict, camera):
    """The shared light as an estimate for ``camera``: its camera RGB is the
    camera's response to the light's spectrum (eq. 1: rho_k = sum_n E R_k)."""
    import numpy as np

    from recovery import IlluminantEstimate

    spd = np.asarray(light["spectrum"], float)
    wl = np.asarray(light["wavelengths"], float)
    if wl.shape != camera.wavelengths.shape or not np.allclose(wl, camera.wavelengths):
        spd = np.interp(camera.wavelengths, wl, spd)
    rgb = spd @ camera.sensitivities
    rgb = rgb / np.linalg.norm(rgb)
    return IlluminantEstimate(rgb, spd, camera.wavelengths, light.get("method", "shared"),
                              {"lighting": "shared"}, [])


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
    import fcntl

    os.makedirs(os.path.dirname(meta_path(out, ".lock")), exist_ok=True)
    fd = os.open(meta_path(out, ".lock"), os.O_CREAT | os.O_RDWR, 0o644)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        os.close(fd)  # closing releases the lock


def atomic_write(path: str, write) -> None:
    """``write(tmp)`` a temporary file beside ``path``, fsync it, then
    rename it to ``path``: the final name only ever holds a complete file."""
    d, base = os.path.split(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=".part", dir=d or ".")
    os.close(fd)
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


def is_finished(out: str) -> bool:
    """An output counts as finished only when both the image and its sidecar
    (renamed into place before the image) exist under their final names."""
    return os.path.exists(out) and os.path.exists(meta_path(out, ".json"))


def process_item(task: ItemTask) -> dict:
    """Decode -> estimate (or take the shared light) -> correct -> encode ->
    write atomically, for one file (the white-balance pipeline of
    :mod:`service.pipeline`: eq. 36 and 23, Wandell 1985, one 3x3 matrix).

    Returns ``{"status": "done", "illuminant": ..., "adopted": bool,
    "seconds": ...}`` or ``{"status": "failed", "error": text}``; never
    raises for a bad file (a corrupt file fails its item only).
    """
    from . import pipeline

    t0, c0 = time.perf_counter(), time.process_time()
    try:
        with (_item_lock(task.out) if task.exactly_once else contextlib.nullcontext()):
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
                if task.light is None:
                    run = pipeline.run_estimate(decoded, cam, warns, method=task.options.method, options=opts)
                else:
                    run = pipeline.EstimateRun(_estimate_from_json(task.light, cam), cam, list(warns))
            except BaseException:
                pipeline.drain_prefetch(decoded)
                raise
            fmt = FORMATS[task.options.format]
            out, M, info, meta = pipeline.render_corrected(decoded, run, target=task.options.target,
                                                           output=task.options.output, fmt=fmt,
                                                           surface_basis=opts.get("surface_basis"),
                                                           threads=task.threads, exposure=task.options.exposure)
            file_warnings = list(decoded.warnings)
            del decoded
            illum = _estimate_json(run.estimate, cam.name)
            illum["warnings"] = list(run.camera_warnings) + file_warnings + list(run.estimate.warnings)
            side = {"name": task.name, "illuminant": illum, "correction_matrix": M.tolist(),
                    "rendering": pipeline.rendering_json(info),
                    "options": asdict(task.options)}
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


def estimation_sample(task: ItemTask, pixels: int) -> dict:
    """Shared mode, step 1: an image's estimation data (RAW: binned CFA
    cells, no demosaic) block-averaged to at most ``pixels`` pixels, with its
    usable-pixel mask and camera. Block means of surfaces under one light
    stay in that light's subspace (eq. 29), so averaging loses no validity."""
    from recovery.resolution import block_average

    try:
        decoded, cam, _ = _open(task)
        img, mask, _ = block_average(decoded.estimation, ~decoded.saturated, pixels)
        return {"status": "ok", "image": img, "mask": mask, "camera": cam}
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


def shared_light(samples: list, options: BatchOptions) -> dict:
    """Shared mode, step 2: one light from all images pooled (Maloney &
    Wandell: one light, one subspace normal for every image, eq. 30-35).

    ``samples`` are :func:`estimation_sample` results of one camera.
    Returns the light as JSON (``camera_rgb``, ``spectrum``, ``cct``...,
    ``images``: how many were pooled)."""
    cam = samples[0]["camera"]
    img, mask = pool_images([s["image"] for s in samples], [s["mask"] for s in samples])
    from recovery import estimate_illuminant

    est = estimate_illuminant(img, cam, options.method, mask=mask, **options.estimate_kwargs())
    light = _estimate_json(est, cam.name)
    light["images"] = len(samples)
    light["warnings"] = list(est.warnings)
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

    def submit(self, fn, *args) -> Future:
        return self._pool.submit(fn, *args)

    def shutdown(self, wait: bool = True) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=True)


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
        is on disk: each finished output (its ``.json`` sidecar names the
        item and holds the estimate and options) as a ``done`` item, each
        input without an output as ``failed``. Returns how many batches."""
        root = os.path.join(self.data_dir, "batches")
        n = 0
        for bid in sorted(os.listdir(root)):
            bdir = os.path.join(root, bid)
            if not os.path.isdir(bdir) or self.batch(bid) is not None:
                continue
            out_dir, in_dir = os.path.join(bdir, "out"), os.path.join(bdir, "in")
            rows, options, done_names = [], None, set()
            if os.path.isdir(out_dir):
                for entry in sorted(os.listdir(out_dir)):
                    out = os.path.join(out_dir, entry)
                    if entry.startswith(".") or not is_finished(out):
                        continue
                    try:
                        with open(meta_path(out, ".json")) as f:
                            side = json.load(f)
                        options = options or BatchOptions(**side.get("options", {}))
                    except (OSError, ValueError, TypeError):
                        continue
                    name = str(side.get("name") or entry)
                    done_names.add(name)
                    rows.append((name, "", out, "done", None, json.dumps(side.get("illuminant"))))
            if os.path.isdir(in_dir):
                for entry in sorted(os.listdir(in_dir)):
                    name = entry.split("-", 1)[1] if re.match(r"\d{5}-", entry) else entry
                    if name not in done_names:
                        rows.append((name, os.path.join(in_dir, entry), os.path.join(out_dir, name), "failed",
                                     "store_recovered: the job store was damaged before this item finished; "
                                     "submit it again", None))
            if not rows:
                continue
            now = time.time()
            with self._tx() as db:
                db.execute("INSERT INTO batches (id, created, started, finished, status, options, dir) "
                           "VALUES (?, ?, ?, ?, 'done', ?, ?)",
                           (bid, os.path.getmtime(bdir), now, now, (options or BatchOptions()).to_json(), bdir))
                db.executemany("INSERT INTO items (batch_id, idx, name, src, out, status, error, illuminant, "
                               "finished) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
                               [(bid, i, *r, now) for i, r in enumerate(rows)])
            n += 1
        return n

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
        with self._tx() as db:
            db.execute("INSERT INTO batches (id, created, status, options, dir) VALUES (?, ?, 'queued', ?, ?)",
                       (batch_id, time.time(), options.to_json(), self.batch_dir(batch_id)))
            db.executemany("INSERT INTO items (batch_id, idx, name, src, out, status) "
                           "VALUES (?, ?, ?, ?, ?, 'pending')", rows)

    # -- reading -------------------------------------------------------------
    def batch(self, batch_id: str):
        return self._db().execute("SELECT * FROM batches WHERE id = ?", (batch_id,)).fetchone()

    def items(self, batch_id: str) -> list:
        return self._db().execute("SELECT * FROM items WHERE batch_id = ? ORDER BY idx", (batch_id,)).fetchall()

    def item(self, batch_id: str, key: str):
        """An item by index (digits) or by name."""
        db = self._db()
        row = db.execute("SELECT * FROM items WHERE batch_id = ? AND name = ?", (batch_id, key)).fetchone()
        if row is None and str(key).isdigit():
            row = db.execute("SELECT * FROM items WHERE batch_id = ? AND idx = ?", (batch_id, int(key))).fetchone()
        return row

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
        return n == 1

    def fail_item(self, batch_id: str, idx: int, error: str) -> None:
        with self._tx() as db:
            db.execute("UPDATE items SET status = 'failed', error = ?, finished = ? "
                       "WHERE batch_id = ? AND idx = ? AND status IN ('pending', 'running')",
                       (error, time.time(), batch_id, idx))

    def cancel_item(self, batch_id: str, idx: int) -> None:
        """``running`` -> ``cancelled`` for an item dropped before it started."""
        with self._tx() as db:
            db.execute("UPDATE items SET status = 'cancelled', finished = ? WHERE batch_id = ? AND idx = ? "
                       "AND status = 'running'", (time.time(), batch_id, idx))

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

    def maybe_finish(self, batch_id: str) -> bool:
        """``running`` -> ``done`` once no item is pending or running."""
        with self._tx() as db:
            left = db.execute("SELECT COUNT(*) FROM items WHERE batch_id = ? AND status IN ('pending', 'running')",
                              (batch_id,)).fetchone()[0]
            if left:
                return False
            return db.execute("UPDATE batches SET status = 'done', finished = ? WHERE id = ? AND status = "
                              "'running'", (time.time(), batch_id)).rowcount == 1

    def cancel(self, batch_id: str) -> bool:
        """Cancel: pending items are cancelled, running ones finish (their
        results are kept); the batch is ``cancelled``. False if it had
        already finished."""
        with self._tx() as db:
            n = db.execute("UPDATE batches SET status = 'cancelled', finished = ? WHERE id = ? AND status IN "
                           "('queued', 'running')", (time.time(), batch_id)).rowcount
            if n:
                db.execute("UPDATE items SET status = 'cancelled' WHERE batch_id = ? AND status = 'pending'",
                           (batch_id,))
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
        doc = {"id": batch_id, "status": b["status"], "lighting": opts.get("lighting"), "options": opts,
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
            self._executor.shutdown(wait=wait)

    def wake(self) -> None:
        self._wake.set()

    def cancel(self, batch_id: str) -> bool:
        ok = self.store.cancel(batch_id)
        with self._lock:
            futs = [fut for (b, _), fut in self._inflight.items() if b == batch_id]
        for fut in futs:  # outside the lock: cancel() runs the done callback at once
            fut.cancel()  # not yet started: dropped; started: finishes, result kept
        self._wake.set()
        return ok

    def wait(self, batch_id: str, timeout: float = 120.0) -> dict:
        """Block until the batch is no longer queued/running (tests, CLI)."""
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            doc = self.store.progress(batch_id)
            if doc and doc["status"] not in ("queued", "running"):
                return doc
            time.sleep(0.1)
        raise TimeoutError(f"batch {batch_id} still running after {timeout} s")

    # -- internals -----------------------------------------------------------
    def _task(self, row, options: BatchOptions, light: dict | None) -> ItemTask:
        return ItemTask(src=row["src"], out=row["out"], name=row["name"], options=options,
                        max_pixels=self.config.max_pixels, estimation_pixels=self.config.estimation_pixels,
                        light=light, write_log=os.path.join(self.store.batch_dir(row["batch_id"]), "writes.log"))

    def _loop(self) -> None:
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
            self.store.maybe_finish(bid)

    def _done(self, key, fut) -> None:
        bid, idx = key
        with self._lock:
            self._inflight.pop(key, None)
        if fut.cancelled():  # dropped before it started
            self.store.cancel_item(bid, idx)
            self.store.maybe_finish(bid)
            return
        try:
            result = fut.result()
        except BaseException as e:  # the worker died (e.g. killed by the OOM killer)
            result = {"status": "failed", "error": f"worker_lost: {type(e).__name__}: {e}"}
        self.store.finish_item(bid, idx, result)
        self.store.maybe_finish(bid)
        self._wake.set()

    def _shared_light_step(self, bid: str, options: BatchOptions) -> None:
        """Shared mode: sample every pending/running image (in the pool),
        pool the samples, estimate one light, store it. Items whose file
        cannot be read fail here, with their error."""
        fut = self._light_jobs.get(bid)
        if fut is None:
            rows = [r for r in self.store.items(bid) if r["status"] in ("pending", "running", "done")]
            pixels = max(4096, shared_pool_pixels() // max(1, len(rows)))
            futs = [(r, self.executor.submit(estimation_sample, self._task(r, options, None), pixels)) for r in rows]
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
                self.store.maybe_finish(bid)
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
            self.store.maybe_finish(bid)
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

