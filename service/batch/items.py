"""One batch item, run in a pool worker or on a Dask worker: :class:`ItemTask` (plain, picklable
data), :func:`process_item` (decode, estimate, render, write exactly once under the item's
lock), the atomic write and the stale temporaries, the shared light's samples and their
combination (:func:`shared_light`), the worker's thread limits.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
import threading
import time
from dataclasses import dataclass

from ..errors import service_error
from ..options import FORMATS


#: The environment variables that cap the internal thread pools of the
#: numerical libraries; set to 1 in every pool worker so that N workers use
#: N cores and do not fight over them.
THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
              "VECLIB_MAXIMUM_THREADS", "OPENCV_FOR_THREADS_NUM")

RAW_SUFFIXES = (".dng", ".cr2", ".cr3", ".nef", ".nrw", ".arw", ".srf", ".sr2", ".raf", ".rw2", ".orf",
                ".pef", ".srw", ".x3f", ".3fr", ".iiq", ".erf", ".kdc", ".dcr", ".mrw", ".mos", ".rwl",
                ".tif", ".tiff", ".png")


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
#: Item lock files this process holds (:func:`_item_lock`), removed with them
#: when a pool worker is terminated (a graceful stop leaves no ``.lock``).
_LOCKS: set = set()


def _exit_on_term(signum, frame) -> None:  # pragma: no cover - runs in a pool worker
    for p in list(_PARTS) + list(_LOCKS):   # a held lock's file: nobody else owns this name now
        with contextlib.suppress(OSError):
            os.unlink(p)
    os._exit(128 + signum)


def remove_stale_lock(out: str) -> bool:
    """Remove ``out``'s lock file if no process holds its lock (a writer that
    was killed, SIGKILL, leaves its file but not its lock); True if removed.
    A writer still at work holds the lock, so its file stays."""
    import fcntl

    path = meta_path(out, ".lock")
    try:
        fd = os.open(path, os.O_RDWR | os.O_NOFOLLOW)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        os.close(fd)
        return False
    try:
        if os.stat(path).st_ino != os.fstat(fd).st_ino:
            return False
        os.unlink(path)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


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
    #: the folder ``src`` must be read from (folder batches: the batch root;
    #: uploads: the batch's folder): opened component by component from it,
    #: no symbolic link followed (:func:`open_under`); None: opened as given
    root: str | None = None
    #: the largest file read (the upload limit, checked on the open file); None: no limit
    max_bytes: int | None = None


class ItemCancelled(Exception):
    """The item's batch was cancelled while it ran (see ``ItemTask.cancel_file``)."""


def _check_cancel(task: ItemTask) -> None:
    if task.cancel_file and os.path.exists(task.cancel_file):
        raise ItemCancelled(task.name)


def _estimate_json(est, camera, profile=None) -> dict:
    from ..pipeline import illuminant_json

    from recovery.api import LOW_CONFIDENCE

    conf = est.diagnostics.get("confidence")
    conf = float(conf) if isinstance(conf, (int, float)) else None
    low = est.diagnostics.get("low_confidence")          # the estimator's own flag (recovery.api.with_confidence)
    return dict(illuminant_json(est, profile, camera), method=est.method, camera=camera.name, confidence=conf,
                low_confidence=bool(low) if isinstance(low, bool) else (conf is not None and conf < LOW_CONFIDENCE))


def _flag_threshold(est) -> float:
    """The confidence below which ``est`` is flagged low confidence: the
    learnt flag's own threshold when it has one
    (``diagnostics["confidence_flag_threshold"]``), else
    :data:`recovery.api.LOW_CONFIDENCE` (what :func:`_estimate_json` and
    ``recovery.api`` use then)."""
    from recovery.api import LOW_CONFIDENCE

    t = est.diagnostics.get("confidence_flag_threshold")
    return float(t) if isinstance(t, (int, float)) and not isinstance(t, bool) else LOW_CONFIDENCE


def _estimate_from_json(light: dict, camera):
    """The shared light as an estimate for ``camera``: the light's own camera
    RGB when it was estimated for this camera (shared lighting pools one
    camera), else the camera's response to the light's spectrum (eq. 1:
    rho_k = sum_n E R_k); its confidence and flag are the shared estimate's."""
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
    if isinstance(light.get("low_confidence"), bool):       # the shared light's flag (shared_light)
        diag["low_confidence"] = light["low_confidence"]
    return IlluminantEstimate(rgb, spd, camera.wavelengths, light.get("method", "shared"), diag, [])


def _open(task: "ItemTask", prefetch: bool = False, render: bool = False, data: bytes | None = None) -> tuple:
    """Decode an item's file and choose its camera (:func:`service.pipeline.open_image`;
    ``prefetch``: start the demosaic on a thread for the render that follows;
    ``render``: the render follows, later (the RAW's mosaic is kept for it));
    ``data``: the file's bytes, read already (:func:`read_source`)."""
    from .. import pipeline

    data = read_source(task) if data is None else data
    decoded, cam, warns, _ = pipeline.open_image(data, task.name or os.path.basename(task.src), task,
                                                 task.options.camera, prefetch=prefetch,
                                                 keep_mosaic=prefetch or render,
                                                 quality=getattr(task.options, "quality", None))
    return decoded, cam, warns


def open_under(root: str, path: str) -> int:
    """A read-only descriptor of ``path``, which must lie under ``root``,
    opened one component at a time from ``root`` (``openat``) with
    ``O_NOFOLLOW``: no symbolic link on the way is followed, so a folder
    swapped for a link to somewhere else after the batch was made is refused
    at open time, not only when the batch was checked.

    Raises :class:`~service.errors.ServiceError` 403 ``path_outside_root``."""
    from ..errors import ServiceError

    rootr = os.path.realpath(root)
    for base in (os.path.abspath(root), rootr):   # the path as stored: under the root as given or resolved
        rel = os.path.relpath(os.path.abspath(path), base)
        if not rel.startswith(".."):
            break
    parts = rel.split(os.sep)
    if rel in (".", "") or os.path.isabs(rel) or ".." in parts:
        raise ServiceError(403, "path_outside_root", f"{path!r} is not under {root!r}")
    nofollow = os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
    fd = os.open(rootr, os.O_RDONLY | os.O_DIRECTORY | nofollow)
    try:
        for i, part in enumerate(parts):
            last = i == len(parts) - 1
            flags = os.O_RDONLY | nofollow | (0 if last else os.O_DIRECTORY)
            try:
                nxt = os.open(part, flags, dir_fd=fd)
            except OSError as e:
                import errno

                if e.errno in (errno.ELOOP, errno.ENOTDIR, errno.EMLINK):
                    raise ServiceError(403, "path_outside_root", f"{'/'.join(parts[:i + 1])!r} under the batch "
                                       "root is now a symbolic link (or not a folder): it is not followed") from None
                raise
            os.close(fd)
            fd = nxt
        return fd
    except BaseException:
        os.close(fd)
        raise


def read_source(task: "ItemTask") -> bytes:
    """The bytes of the item's input: opened under ``task.root`` with no
    symbolic link followed (:func:`open_under`) when a root is given, a
    regular file, at most ``task.max_bytes`` bytes (checked on the open file,
    so a file that grew after the batch was made is refused too)."""
    import stat

    from ..errors import ServiceError

    fd = open_under(task.root, task.src) if task.root else os.open(task.src, os.O_RDONLY)
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise ServiceError(422, "not_a_file", f"{task.name!r} is not a regular file")
        if task.max_bytes is not None and st.st_size > task.max_bytes:
            raise ServiceError(413, "file_too_large", f"{task.name!r} is {st.st_size} bytes, above the upload "
                               f"limit of {task.max_bytes} bytes")
        data = f.read() if task.max_bytes is None else f.read(task.max_bytes + 1)
    if task.max_bytes is not None and len(data) > task.max_bytes:
        raise ServiceError(413, "file_too_large", f"{task.name!r} grew above the upload limit of "
                           f"{task.max_bytes} bytes while it was read")
    return data


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
    _LOCKS.add(path)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)  # still holding the lock: nobody else owns this name now
        _LOCKS.discard(path)
        os.close(fd)  # closing releases the lock


def atomic_write(path: str, write, durable: bool = True) -> None:
    """``write(tmp)`` a temporary file beside ``path``, fsync it (``durable``),
    then rename it to ``path``: the final name only ever holds a complete
    file. Without ``durable`` the data reaches the disk when the system
    writes it back, as with any image tool; the batch's exactly-once items,
    whose resume trusts a finished file after a crash, are durable (issue
    19: the fsync of a 144 MB TIFF forced 0.3-1.5 s of disk writing into
    each ``wandell white-balance``)."""
    d, base = os.path.split(path)
    if len(base.encode("utf-8")) > 240:   # ".NAME.XXXXXXXX.part" past NAME_MAX: the write failed (probe round 8)
        from .store import clip_name

        base = clip_name(base, 200)       # a batch's outputs are never this long (DISK_NAME_BYTES)
    fd, tmp = tempfile.mkstemp(prefix=f".{base}.", suffix=".part", dir=d or ".")
    os.close(fd)
    _PARTS.add(tmp)
    os.chmod(tmp, 0o644)  # mkstemp makes 0600; results are ordinary files
    try:
        write(tmp)
        if durable:
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
    :mod:`service.pipeline`: eq. 36 and 23, Wandell 1985, one 3x3 matrix);
    ``format=dng``: the RAW as a DNG with its light inside instead
    (:func:`_dng_result`), nothing rendered.

    Returns ``{"status": "done", "illuminant": ..., "adopted": bool,
    "seconds": ...}`` or ``{"status": "failed", "error": text}``, or
    ``{"status": "cancelled"}`` when the batch was cancelled before the item
    wrote anything (checked between the steps); never raises for a bad file
    (a corrupt file fails its item only).
    """
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        _check_cancel(task)
        _not_the_input(task)
        with (_item_lock(task.out) if task.exactly_once else contextlib.nullcontext()):
            if task.exactly_once:  # under the lock: a temporary of this output is an earlier run's, killed
                remove_stale_temporaries(os.path.dirname(task.out), {os.path.basename(task.out)}, task.out)
            if task.exactly_once and not task.force and is_finished(task.out):  # written by an earlier run: adopt, never write twice
                with open(meta_path(task.out, ".json")) as f:
                    side = json.load(f)
                return {"status": "done", "illuminant": side.get("illuminant"), "adopted": True,
                        "seconds": time.perf_counter() - t0}
            fmt = FORMATS[task.options.format]
            if fmt.encoder == "dng":    # the RAW itself with its white balance inside: nothing rendered
                illum, side, write = _dng_result(task)
            else:
                illum, side, write = _rendered_result(task, fmt)
            if task.exactly_once:
                atomic_write(meta_path(task.out, ".json"), lambda p: write_text(p, json.dumps(_clean(side))))
            atomic_write(task.out, write, durable=task.exactly_once)
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
        from ..errors import disk_full

        if disk_full(exc):  # nothing of the item was kept; it can run again once space is freed
            return {"status": "failed", "retry": True,
                    "error": f"insufficient_storage: the output folder is full, nothing was written "
                             f"({type(exc).__name__}: {exc})"}
        return {"status": "failed", "error": _error_text(exc)}


def _not_the_input(task: ItemTask) -> None:
    """Refuse (422 ``output_is_input``) an output that is the item's input
    file: ``wandell batch IN IN --format dng`` names IMG.dng's result IMG.dng
    (a TIFF's, IMG.tif), which would replace the original."""
    from ..errors import ServiceError

    with contextlib.suppress(OSError):
        if os.path.samefile(task.src, task.out):
            raise ServiceError(422, "output_is_input", f"the result of {task.name!r} would be written over the "
                               f"file itself ({task.out}); the original is only ever read: choose another output "
                               "folder or format")


def _light(task: ItemTask, decoded, cam, warns):
    """The item's light: its own estimate, or the batch's shared light."""
    from .. import pipeline

    if task.light is None:
        return pipeline.run_estimate(decoded, cam, warns, method=task.options.method,
                                     options=task.options.estimate_kwargs())
    return pipeline.EstimateRun(_estimate_from_json(task.light, cam), cam, list(warns))


def _item_illuminant(run, cam, decoded) -> dict:
    """The item's light as its sidecar and the progress document keep it, with every warning."""
    from .. import pipeline

    illum = _estimate_json(run.estimate, cam, pipeline.profile_of(decoded))
    illum["warnings"] = list(run.camera_warnings) + list(decoded.warnings) + list(run.estimate.warnings)
    return illum


def _rendered_result(task: ItemTask, fmt) -> tuple:
    """The corrected image (Wandell 1985, eq. 36 and 23: one 3x3 matrix per
    pixel): ``(illuminant, sidecar, write)``, ``write(path)`` writing the file."""
    from .. import pipeline

    # the demosaic overlaps the estimate when this item may use several
    # threads (wandell white-balance) and writes a TIFF; a pool worker
    # (one per core) does not, nor a PNG or JPEG: those are demosaicked
    # strip by strip as they are encoded (pipeline.render_encoded)
    strips = fmt.encoder in pipeline.STRIP_ENCODERS
    decoded, cam, warns = _open(task, prefetch=task.threads != 1 and not strips, render=True)
    opts = task.options.estimate_kwargs()
    try:
        _check_cancel(task)
        run = _light(task, decoded, cam, warns)
        _check_cancel(task)
    except BaseException:
        pipeline.drain_prefetch(decoded)
        raise
    render = pipeline.render_encoded if strips else pipeline.render_corrected
    out, M, info, meta = render(decoded, run, target=task.options.target, output=task.options.output,
                                fmt=fmt, surface_basis=opts.get("surface_basis"), threads=task.threads,
                                exposure=task.options.exposure)
    _check_cancel(task)  # the last point before anything is written
    illum = _item_illuminant(run, cam, decoded)
    del decoded
    side = {"name": task.name, "index": task.index, "illuminant": illum, "correction_matrix": M.tolist(),
            "rendering": pipeline.rendering_json(info), "options": task.options.as_dict()}
    if strips:          # out: the file's bytes
        return illum, side, lambda p: write_bytes(p, out)
    return illum, side, lambda p: pipeline.encode_image(out, fmt.encoder, p, meta=meta, threads=task.threads)


def _dng_result(task: ItemTask) -> tuple:
    """``format=dng``: the item's RAW as a DNG with its light inside, the
    bytes ``POST /v1/white-balance format=dng`` answers for the same file and
    options (:func:`service.pipeline.white_balanced_dng`: a DNG's copy with
    the Camera Raw packet and AsShotNeutral, another RAW's raw data written
    as a DNG); ``(illuminant, sidecar, write)``. A linear image (TIFF, PNG)
    is refused before its estimate: 422 ``not_a_raw``, this item only.

    References
    ----------
    Adobe, *Digital Negative (DNG) Specification* 1.4.0.0 (2012): AsShotNeutral, the XMP packet in IFD 0.
    """
    from .. import pipeline

    data = read_source(task)
    decoded, cam, warns = _open(task, data=data)
    pipeline.dng_possible(data, decoded)
    _check_cancel(task)
    run = _light(task, decoded, cam, warns)
    _check_cancel(task)
    text, _, summary = pipeline.xmp_sidecar(decoded, run)
    body = pipeline.white_balanced_dng(data, decoded, text, summary["camera_rgb"])
    _check_cancel(task)  # the last point before anything is written
    illum = _item_illuminant(run, cam, decoded)
    side = {"name": task.name, "index": task.index, "illuminant": illum, "dng": summary,
            "options": task.options.as_dict()}
    return illum, side, lambda p: write_bytes(p, body)


def write_bytes(path: str, data: bytes) -> None:
    """Write ``data`` to ``path`` (for :func:`atomic_write`)."""
    with open(path, "wb") as f:
        f.write(data)


def write_text(path: str, text: str) -> None:
    """Write ``text`` to ``path`` (for :func:`atomic_write`)."""
    with open(path, "w") as f:
        f.write(text)


def _clean(obj):
    from ..jsonsafe import clean

    return clean(obj)


def estimation_sample(task: ItemTask, pixels: int | None = None) -> dict:
    """Shared mode, step 1: an image's own estimate, made exactly as in
    per-image mode (:func:`service.pipeline.run_estimate` with the batch's
    method and options, on the analysis image of its ``quality``), with its
    camera and colour profile. ``pixels`` is not used (it was the share of a
    pooled image, which made the light depend on the number of images)."""
    from .. import pipeline

    try:
        _check_cancel(task)
        decoded, cam, warns = _open(task)
        _check_cancel(task)
        run = pipeline.run_estimate(decoded, cam, warns, method=task.options.method,
                                    options=task.options.estimate_kwargs())
        profile = pipeline.profile_of(decoded)
        return {"status": "ok", "estimate": _clean(_estimate_json(run.estimate, cam, profile)),
                "warnings": list(run.estimate.warnings), "camera": cam, "profile": profile,
                "flag_threshold": _flag_threshold(run.estimate)}
    except ItemCancelled:
        return {"status": "cancelled", "error": "cancelled: the batch was cancelled"}
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
    warning says so. It is flagged ``low_confidence`` below the images'
    own flag thresholds, weighted alike (one image is flagged as in
    per-image mode). Returns the light as JSON (``camera_rgb``,
    ``spectrum``, ``cct``..., ``confidence``, ``images``: how many were
    combined, ``image_angles_deg``: each image's light to the shared one)."""
    import numpy as np

    from recovery import IlluminantEstimate, angular_error

    from ..pipeline import VISIBLE_WB_ERROR_DEG

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
        # flagged as the images are: below their own thresholds (the learnt flag's, else 0.5), weighted
        # alike, so one image, or N identical ones, is flagged exactly as in per-image mode
        from recovery.api import LOW_CONFIDENCE

        thresholds = np.array([s.get("flag_threshold", LOW_CONFIDENCE) for s in samples], float)
        diag["confidence_flag_threshold"] = float(w @ thresholds)
        diag["low_confidence"] = bool(diag["confidence"] < diag["confidence_flag_threshold"])
    methods = {e.get("method") for e in ests}
    est = IlluminantEstimate(rgb, spd, wl, methods.pop() if len(methods) == 1 else "shared", diag, warnings)
    light = _estimate_json(est, cam, samples[0].get("profile"))
    light["images"] = len(samples)
    light["image_angles_deg"] = angles.tolist()
    light["warnings"] = warnings
    return _clean(light)
