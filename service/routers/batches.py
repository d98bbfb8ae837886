"""``/v1/batches``: batch white balance over HTTP (issue 6), a thin shell
over :mod:`service.jobs` (SQLite store, local process pool or Dask).

The runner starts with the app (:func:`lifespan`) and resumes what a killed
server left unfinished; it is also started lazily by the first request, so
an app used without its lifespan still works.
"""

from __future__ import annotations

import contextlib
import errno
import json
import logging
import os
import shutil
import sqlite3
import threading
import time
import zipfile

from fastapi import APIRouter, Depends, File, Form, Path, Query, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, JSONResponse, StreamingResponse

from .. import jobs
from ..batch.summary import SUMMARY
from ..errors import ServiceError
from ..headers import content_disposition
from ..jsonsafe import clean
from ..options import FORMATS, MEDIA_TYPES
from ..schemas import BatchOptions
from ..schemas.forms import form
from ..schemas.responses import BatchCreated, BatchDeleted, BatchList, BatchProgress
from ..settings import Settings, get_settings

router = APIRouter(prefix="/v1", tags=["batches"])

#: The batch options as form fields (service.schemas.BatchOptions, as the CLI's flags).
_OPTIONS = form(BatchOptions)
log = logging.getLogger("service")

#: What a result download is (the batch's format decides which), and the zip.
_BINARY = {"schema": {"type": "string", "format": "binary"}}
_ITEM_FILE = {200: {"description": "the item's result, in the batch's format: 16-bit TIFF, PNG or JPEG, or "
                                   "with format=dng the RAW as a DNG with its white balance inside (NAME.dng, "
                                   "image/x-adobe-dng)",
                    "content": {"image/tiff": _BINARY, "image/png": _BINARY, "image/jpeg": _BINARY,
                                "image/x-adobe-dng": _BINARY}},
              404: {"description": "no such batch or item (`not_found`), or the batch was removed after its "
                                   "result retention (`batch_expired`: when, the retention, the setting)"}, 409: {"description": "not finished yet (`not_ready`), failed or cancelled "
                                                                           "without a result (`item_failed`, `item_cancelled`), or "
                                                                           "ambiguous (`ambiguous_item`)"},
              410: {"description": "done, but its result file is no longer on the server (removed outside the "
                                   "service)"}}
_ZIP = {200: {"description": "every finished result, batch.json (the batch's document, flagged items first), "
                             "and FAILURES.txt and manifest.json when items are missing",
              "content": {"application/zip": _BINARY}},
        404: {"description": "no such batch (`not_found`), or removed after its result retention "
                             "(`batch_expired`)"}, 409: {"description": "nothing finished yet"},
        410: {"description": "items are done but none of their result files is still on the server"}}

_runner: jobs.BatchRunner | None = None
_runner_lock = threading.Lock()
#: why the last start of the runner failed (an unusable data directory), shown by ``/health``
_start_error: str | None = None


def get_runner(settings: Settings | None = None) -> jobs.BatchRunner:
    """The process's batch runner (created and started on first use)."""
    global _runner, _start_error
    with _runner_lock:
        if _runner is None:
            s = settings or get_settings()
            cfg = jobs.RunnerConfig(data_dir=s.data_dir or jobs.default_data_dir(), workers=s.batch_workers,
                                    max_concurrent_batches=s.max_concurrent_batches, max_pixels=s.max_pixels,
                                    estimation_pixels=s.estimation_pixels, dask_scheduler=s.dask_scheduler or None,
                                    input_retention_s=s.batch_input_retention,
                                    result_retention_s=s.batch_result_retention, batch_root=s.batch_root,
                                    max_input_bytes=s.max_upload_bytes)
            try:
                runner = jobs.BatchRunner(cfg)
                runner.start()
            except (OSError, sqlite3.Error) as e:  # e.g. an unwritable data directory
                _start_error = (f"the batch job store under {cfg.data_dir!r} cannot be opened "
                                f"({type(e).__name__}: {e}); single-file endpoints still work")
                raise ServiceError(503, "job_store_unavailable", _start_error) from None
            _runner, _start_error = runner, None
        return _runner


def store_health() -> dict:
    """The job store's state for ``/health``: ``ok``, ``recovered`` (a damaged
    store was moved aside at start-up: where to, and why) or ``not_started``."""
    runner = _runner
    if runner is None:   # never asked for yet, or it could not start (then the batch endpoints answer 503)
        return {"status": "unavailable", "error": _start_error} if _start_error else {"status": "not_started"}
    if runner.read_only:
        return {"status": "read_only", "error": runner.read_only}
    if runner.store.recovered:
        return {"status": "recovered", **runner.store.recovered}
    return {"status": "ok"}


def runner_health() -> dict:
    """The batch runner's state for ``/health``: ``ok``, ``degraded`` (items
    cannot run now: no Dask scheduler or worker, a full disk; the reason in
    ``runner_error``, since when in ``since``) or ``not_started``."""
    runner = _runner
    if runner is None:
        return {"status": "not_started"}
    return runner.health()


class StoreBusy(ServiceError):
    """The job store is write-locked by another connection (a second server
    on the same data directory, a backup, an ``sqlite3`` shell) for longer
    than :data:`~service.batch.store.BUSY_TIMEOUT_S`: 503 with ``Retry-After``."""

    def __init__(self, detail: str):
        super().__init__(503, "job_store_busy", detail)
        self.headers = {"Retry-After": "5"}


@contextlib.contextmanager
def store_errors():
    """The job store's operational errors as answers: locked or busy -> 503
    ``job_store_busy`` with ``Retry-After`` (after a bounded wait, never
    30 s of a blocked server), full -> 507 ``insufficient_storage``."""
    try:
        yield
    except sqlite3.OperationalError as e:
        text = str(e).lower()
        if "locked" in text or "busy" in text:
            raise StoreBusy(f"the batch job store is locked by another process ({e}); nothing was changed, "
                            f"try again in a few seconds") from None
        if "readonly" in text:
            raise ServiceError(503, "job_store_read_only", f"the batch job store cannot be written ({e}): the data "
                               "directory is read-only; nothing was changed") from None
        if "full" in text:
            raise ServiceError(507, "insufficient_storage", f"the service's data directory is full ({e}); "
                               "nothing was changed, try again when space is freed") from None
        raise


async def _in_thread(fn, *args):
    """``fn(*args)`` off the event loop, its store errors mapped (:func:`store_errors`)."""
    def call():
        with store_errors():
            return fn(*args)

    return await run_in_threadpool(call)


def stop_runner() -> None:
    """Stop the runner (app shutdown, tests)."""
    global _runner
    with _runner_lock:
        if _runner is not None:
            _runner.stop(wait=False)
            _runner = None


@contextlib.asynccontextmanager
async def lifespan(app):
    """Start the batch runner with the app (resuming unfinished batches). A
    store that cannot be opened even after recovery does not stop the
    service: the batch endpoints answer 503 until it can be."""
    try:
        await run_in_threadpool(get_runner)
    except ServiceError as e:
        log.error("batch runner not started: %s", e.detail)
    try:
        yield
    finally:
        await run_in_threadpool(stop_runner)


async def _save_uploads(files: list[UploadFile], dest: str, settings: Settings) -> list[tuple[str, str]]:
    """Stream each upload to ``dest`` (per-file size limit), returning
    ``(name, path)`` pairs."""
    out = []
    for i, f in enumerate(files):
        name = jobs.safe_name(f.filename or f"file{i}")
        path = os.path.join(dest, f"{i:05d}-{jobs.clip_name(name)}")
        size = 0
        with open(path, "wb") as fh:
            while chunk := await f.read(1 << 20):
                size += len(chunk)
                if size > settings.max_upload_bytes:
                    raise ServiceError(413, "file_too_large", f"{name!r} exceeds the upload limit of "
                                   f"{settings.max_upload_bytes} bytes")
                fh.write(chunk)
        await f.close()
        if size == 0:
            raise ServiceError(422, "empty_file", f"{name!r} is empty")
        out.append((name, path))
    return out


@router.post("/batches", status_code=202, response_model=BatchCreated)
async def create_batch(files: list[UploadFile] | None = File(None, description="RAW files (repeat the field)"),
                       folder: str | None = Form(None, description="folder relative to WANDELL_BATCH_ROOT"),
                       opts: BatchOptions = Depends(_OPTIONS),
                       settings: Settings = Depends(get_settings)):
    """Start a batch: several ``files`` fields, or a ``folder`` under the
    server's batch root, with the white-balance options. Answers ``{"id"}``
    at once (202); follow it with ``GET /v1/batches/{id}``. With
    ``format=dng`` each RAW's result is ``NAME.dng``, the RAW with its white
    balance inside (what ``/v1/white-balance`` answers with ``format=dng``);
    a linear TIFF/PNG item fails alone (``not_a_raw``)."""
    files = [f for f in (files or []) if f is not None and (f.filename or f.size)]
    if bool(files) == bool(folder):
        raise ServiceError(422, "invalid_parameter", "give either files (one or more 'files' fields) or folder")
    opts = jobs.batch_options(**opts.as_dict())   # the batch's own checks too (the camera name)
    refused: dict = {}
    if folder:   # off the event loop, stopping at the item limit
        sources, refused = await run_in_threadpool(jobs.scan_folder, settings.batch_root, folder,
                                                   settings.max_batch_items)
    else:
        sources = None
    n = len(sources) if sources is not None else len(files)
    if n > settings.max_batch_items:
        raise ServiceError(413, "too_many_items", f"{n} items exceed the batch limit of {settings.max_batch_items}")
    for f in files:
        base = os.path.basename((f.filename or "").replace("\\", "/"))
        if len(base.encode("utf-8", "surrogatepass")) > jobs.MAX_NAME_BYTES:
            raise ServiceError(422, "name_too_long", f"file name {base[:60]!r}... is {len(base.encode('utf-8', 'surrogatepass'))} "
                           f"bytes; at most {jobs.MAX_NAME_BYTES} (UTF-8)")
    if sources is not None:  # folder mode: the same per-file limit as an upload (again when each is read)
        big = await run_in_threadpool(lambda: [name for i, (name, path) in enumerate(sources)
                                               if i not in refused and _size(path) > settings.max_upload_bytes])
        if big:
            raise ServiceError(413, "file_too_large", f"{len(big)} file(s) in the folder exceed the upload limit of "
                           f"{settings.max_upload_bytes} bytes: {', '.join(map(repr, big[:5]))}")
    runner = await run_in_threadpool(get_runner, settings)
    if runner.read_only:
        raise ServiceError(503, "job_store_read_only", f"no batch can be made: {runner.read_only}")
    store = runner.store
    bid = None
    try:
        bid = await run_in_threadpool(store.new_batch_id)
        if sources is None:
            sources = await _save_uploads(files, os.path.join(store.batch_dir(bid), "in"), settings)
        try:
            await _in_thread(store.create_batch, bid, opts, sources, refused)
        except StoreBusy as busy:   # the manifest is on disk: accepted, registered when the store is free
            await run_in_threadpool(runner.defer, bid)
            deferred = busy.detail
        else:
            deferred = None
    except BaseException as e:
        if bid is not None:
            await run_in_threadpool(shutil.rmtree, store.batch_dir(bid), True)
        if _disk_full(e) and not isinstance(e, ServiceError):
            log.error("batch not created, the data directory is full: %s", e)
            raise ServiceError(507, "insufficient_storage", f"the service's data directory is full ({e}); nothing "
                           "was kept of this batch, try again when space is freed") from None
        raise
    runner.wake()
    content = {"id": bid, "status": "queued", "counts": {"done": 0, "failed": len(refused),
                                                         "pending": n - len(refused)},
               "lighting": opts.lighting, "url": f"/v1/batches/{bid}"}
    if runner.executor_error:   # accepted, but nothing can run now: say why (no scheduler, no worker, disk full)
        content["runner_error"] = runner.executor_error
    if deferred:
        content["registration"] = (f"deferred: {deferred}; the batch is kept on disk and registered (then run) "
                                   "as soon as the store is free")
    return JSONResponse(status_code=202, content=clean(content))


def _valid_id(bid: str) -> bool:
    """A batch id as :meth:`JobStore.new_batch_id` makes them (never a path)."""
    return len(bid) == 16 and all(c in "0123456789abcdef" for c in bid)


def _no_batch(store: jobs.JobStore, batch_id: str) -> ServiceError:
    """The 404 of a batch the store does not hold: ``batch_expired`` (when it
    was removed, by which retention, the setting's name) if the result
    retention removed it and its tombstone is kept (:meth:`JobStore.removal`),
    else ``not_found``. Still a 404, as before: clients and the page take a 404
    as final."""
    gone = store.removal(batch_id) if _valid_id(batch_id) else None
    if gone is None:
        return ServiceError(404, "not_found", f"no batch {batch_id!r}")
    when = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(gone["removed"]))
    days = f" ({gone['retention_s'] / 86400:g} days)" if gone["retention_s"] >= 86400 else ""
    return ServiceError(404, "batch_expired",
                        f"batch {batch_id!r} was removed with its files at {when}, its result retention of "
                        f"{gone['retention_s']:g} s{days} after it ended (WANDELL_BATCH_RESULT_RETENTION); submit "
                        "the files again",
                        extra={"removed": gone["removed"], "retention_s": gone["retention_s"],
                               "setting": "WANDELL_BATCH_RESULT_RETENTION"})


def _size(path: str) -> int:
    try:
        return os.path.getsize(path)
    except OSError:
        return 0


def _disk_full(e: BaseException) -> bool:
    """No space (or quota) left, from the file system or from SQLite."""
    if isinstance(e, OSError) and e.errno in (errno.ENOSPC, errno.EDQUOT):
        return True
    return isinstance(e, sqlite3.OperationalError) and "full" in str(e).lower()


def _progress(bid: str) -> dict:
    runner = get_runner()
    with store_errors():
        doc = runner.store.progress(bid)
    if doc is None and _valid_id(bid):
        doc = runner.store.manifest_progress(bid)   # made while the store was busy, not yet registered
    if doc is None:
        with store_errors():
            raise _no_batch(runner.store, bid)
    if runner.executor_error and doc["status"] in ("queued", "running"):
        # nothing runs now: say why and since when, and promise no time left
        doc["runner_error"] = runner.executor_error
        doc["runner_error_since"] = runner.error_since
        doc["time_left_s"] = doc["eta_s"] = None
    for it in doc["items"]:
        if it["status"] == "done":
            it["url"] = f"/v1/batches/{bid}/items/by-index/{it['index']}"  # never taken for a name
    return doc


@router.get("/batches/{batch_id}", response_model=BatchProgress)
def batch_status(batch_id: str):
    """Progress (done, failed, pending, rate per minute, time left) and
    each item's status with its estimate or error; ``settled`` is true once
    the batch is over and every count final (poll until then)."""
    return JSONResponse(clean(_progress(batch_id)))


@router.get("/batches/{batch_id}/items/by-index/{index}", response_class=FileResponse, responses=_ITEM_FILE)
def batch_item_by_index(batch_id: str, index: str = Path(description="the item's index in the batch (0-based), "
                                                                       "as its url in the progress document",
                                                           examples=["0"])):
    """Download one result by its index (the ``url`` of each item in the
    progress document): only ever that item, whatever the files are named."""
    store = _store_of(batch_id)
    return _item_file(store, batch_id, store.item_by_index(batch_id, index), index, "index")


@router.get("/batches/{batch_id}/items/by-name/{name}", response_class=FileResponse, responses=_ITEM_FILE)
def batch_item_by_name(batch_id: str, name: str = Path(description="the item's name as the progress document "
                                                                    "lists it (URL-encoded)",
                                                        examples=["a.dng"])):
    """Download one result by its item name (as listed, made unique:
    ``a (2).dng``)."""
    store = _store_of(batch_id)
    return _item_file(store, batch_id, store.item_by_name(batch_id, name), name, "name")


@router.get("/batches/{batch_id}/items/{item}", response_class=FileResponse, responses=_ITEM_FILE)
def batch_item(batch_id: str, item: str):
    """Download one result, by item name or index; a key that is the name of
    one item and the index of another is refused (409 ``ambiguous_item``):
    ``items/by-index/{index}`` and ``items/by-name/{name}`` never are."""
    store = _store_of(batch_id)
    return _item_file(store, batch_id, store.item(batch_id, item), item, "name or index")


def _store_of(batch_id: str) -> jobs.JobStore:
    store = get_runner().store
    with store_errors():
        if store.batch(batch_id) is None:
            raise _no_batch(store, batch_id)
    return store


def _item_file(store: jobs.JobStore, batch_id: str, row, key: str, kind: str):
    if row is None:
        raise ServiceError(404, "not_found", f"batch {batch_id!r} has no item {key!r} (by {kind})")
    if row["status"] == "done" and not os.path.exists(row["out"]):
        raise ServiceError(410, "result_gone", f"item {row['name']!r} is done, but its result file is no longer on "
                           "the server (removed outside the service); run it again in a new batch")
    if row["status"] in ("failed", "cancelled"):
        # settled without a result: waiting will not bring one (not_ready would say it might)
        raise ServiceError(409, f"item_{row['status']}", f"item {row['name']!r} is {row['status']} and has no result"
                           + (f": {row['error']}" if row["error"] else "")
                           + ("; run it again in a new batch" if row["status"] == "failed" else ""))
    if row["status"] != "done":
        raise ServiceError(409, "not_ready", f"item {row['name']!r} is {row['status']}"
                       + (f": {row['error']}" if row["error"] else ""))
    fmt = FORMATS.get(jobs.BatchOptions.from_json(store.batch(batch_id)["options"]).format, FORMATS["jpeg"])
    media = MEDIA_TYPES[fmt.encoder]
    return FileResponse(row["out"], media_type=media,
                        headers={"Content-Disposition": content_disposition(os.path.basename(row["out"]))})


class _Sink:
    """A write-only stream whose bytes are collected between yields (zipfile
    writes to unseekable streams with data descriptors)."""

    def __init__(self):
        self.parts: list[bytes] = []

    def write(self, b) -> int:
        self.parts.append(bytes(b))
        return len(b)

    def flush(self) -> None:
        pass

    def take(self) -> bytes:
        data, self.parts = b"".join(self.parts), []
        return data


class _ZipResponse(StreamingResponse):
    """A batch's zip, counted in the runner's :class:`~service.batch.downloads.Downloads`
    from before its results are listed until it is sent or given up: they are
    opened one after the other while it streams, so ``DELETE ?remove=true``
    waits for it (409 ``downloading``) and the retention sweep postpones the
    batch, instead of removing the files under it (the client got a cut,
    unreadable zip and the log a traceback)."""

    def __init__(self, downloads, batch_id: str, *args, **kw):
        super().__init__(*args, **kw)
        self.downloads, self.batch_id = downloads, batch_id

    async def __call__(self, scope, receive, send) -> None:
        try:
            await super().__call__(scope, receive, send)
        finally:
            self.downloads.end(self.batch_id)


def _zip_stream(entries: list[tuple[str, str]], texts: list[tuple[str, str]] = ()):
    sink = _Sink()
    with zipfile.ZipFile(sink, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
        for arcname, text in texts:  # small, made here: the manifest and the list of failures
            zf.writestr(zipfile.ZipInfo(arcname, time.localtime()[:6]), text.encode("utf-8"))
            yield sink.take()
        for arcname, path in entries:
            info = zipfile.ZipInfo.from_file(path, arcname)  # the result's own time stamp
            with open(path, "rb") as src, zf.open(info, "w", force_zip64=True) as dst:
                while chunk := src.read(1 << 20):
                    dst.write(chunk)
                    yield sink.take()
            yield sink.take()
    yield sink.take()


def zip_texts(batch_id: str, rows: list[dict], zipped: dict) -> list[tuple[str, str]]:
    """What a batch's zip says about itself when some item is not in it
    (failed, cancelled, not finished): ``FAILURES.txt`` (one line per such
    item: name, status, error) and ``manifest.json`` (every item: name,
    status, its output in the zip or its error). A zip of a batch whose
    every item is in it holds only the results."""
    items, bad = [], []
    for r in map(dict, rows):
        out = os.path.basename(r["out"]) if r.get("out") else None
        it = {"name": r["name"], "status": r["status"],
              "output": out if r["status"] == "done" and out in zipped else None}
        if r.get("error"):
            it["error"] = r["error"]
        if r["status"] == "done" and it["output"] is None:
            it["error"] = "the result is no longer on the server"
        items.append(it)
        if r["status"] != "done" or it["output"] is None:
            bad.append(f"{r['name']}\t{r['status']}\t{it.get('error') or 'not finished when the zip was made'}")
    counts = {k: sum(i["status"] == k for i in items) for k in ("done", "failed", "cancelled", "pending", "running")}
    if not bad:
        return []
    return [("FAILURES.txt", f"{len(bad)} of the {len(items)} items of batch {batch_id} are not in this zip "
             "(name, status, error):\n" + "\n".join(bad) + "\n"),
            ("manifest.json", json.dumps({"batch": batch_id, "counts": counts, "items": items}, indent=1) + "\n")]


@router.get("/batches/{batch_id}/zip", response_class=StreamingResponse, responses=_ZIP)
def batch_zip(batch_id: str):
    """Every finished result in one zip, streamed (not built in memory), with
    ``batch.json`` (the batch's document: every item's light, confidence and
    flag or error, the flagged ones first) and, when some item is not in it,
    ``FAILURES.txt`` and ``manifest.json``."""
    runner = get_runner()
    store = runner.store
    if not runner.downloads.begin(batch_id):   # counted before its results are listed; ended by the response
        raise ServiceError(404, "not_found", f"batch {batch_id!r} is being removed")
    try:
        if store.batch(batch_id) is None:
            raise _no_batch(store, batch_id)
        rows = store.items(batch_id)
        entries = [(os.path.basename(r["out"]), r["out"]) for r in rows
                   if r["status"] == "done" and os.path.exists(r["out"])]
        if not entries and any(r["status"] == "done" for r in rows):
            raise ServiceError(410, "result_gone", f"batch {batch_id!r} has done items, but none of their result "
                               "files is still on the server (removed outside the service)")
        if not entries:
            raise ServiceError(409, "not_ready", f"batch {batch_id!r} has no finished results yet")
        # batch.json: the batch's document (GET /v1/batches/{id}), the items flagged low confidence first
        summary = json.dumps(clean(_progress(batch_id)), indent=1) + "\n"
        texts = [(SUMMARY, summary)] + zip_texts(batch_id, rows, dict(entries))
        return _ZipResponse(runner.downloads, batch_id, _zip_stream(entries, texts), media_type="application/zip",
                            headers={"Content-Disposition": content_disposition(f"batch-{batch_id}.zip")})
    except BaseException:
        runner.downloads.end(batch_id)
        raise


@router.get("/batches", response_model=BatchList)
def list_batches():
    """Every batch the service keeps, newest first, with its status, counts
    and disk space; the retention settings say when they go by themselves."""
    runner = get_runner()
    rows = runner.store.summaries()
    for r in rows:
        r["url"] = f"/v1/batches/{r['id']}"
    return JSONResponse(clean({"batches": rows, "bytes": sum(r["bytes"] for r in rows),
                               "result_retention_s": runner.config.result_retention_s,
                               "input_retention_s": runner.config.input_retention_s}))


@router.post("/batches/{batch_id}/cancel", response_model=BatchProgress)
def cancel_batch_only(batch_id: str):
    """Cancel, never delete: pending items are dropped, running ones stop at
    their next step without writing; results finished before are kept. The
    answer is the progress document (``settled`` once the counts are final)."""
    runner = get_runner()
    with store_errors():
        if runner.store.batch(batch_id) is None:
            raise _no_batch(runner.store, batch_id)
        runner.cancel(batch_id)
    return JSONResponse(clean(_progress(batch_id)))


@router.delete("/batches/{batch_id}", response_model=BatchDeleted | BatchProgress,
               responses={409: {"description": "cancelled, but running items have not stopped yet, or its zip "
                                               "is being downloaded: try again"}})
def delete_batch(batch_id: str, remove: bool = Query(
        False, description="also delete the batch and its files once it is over (without it a DELETE only "
                           "cancels, and never deletes results)", examples=[True])):
    """Cancel a batch, as it always did; with ``remove=true``, also remove
    it and its files (inputs and results). Without ``remove`` nothing is
    deleted: the answer is the progress document with ``deleted: false``
    (a client that cancels a batch which has just finished keeps its
    results). With ``remove=true`` a batch that is over (done, or cancelled
    and settled) is deleted and the answer says how many bytes were freed;
    its URLs are 404 from then on; a batch still queued or running is
    cancelled first (``deleted: false``): send it again once ``settled``;
    until then it is a 409 ``not_settled``, and while its zip is being
    downloaded a 409 ``downloading``."""
    runner = get_runner()
    b = runner.store.batch(batch_id)
    if b is None:
        raise _no_batch(runner.store, batch_id)
    if b["status"] in ("queued", "running"):
        with store_errors():
            runner.cancel(batch_id)
        return JSONResponse(clean({**_progress(batch_id), "deleted": False}))
    if not remove:
        return JSONResponse(clean({**_progress(batch_id), "deleted": False,
                                   "note": "over already: nothing to cancel; DELETE with ?remove=true removes the "
                                           "batch and its files"}))
    with runner.downloads.removing(batch_id) as zipping:
        if zipping:
            raise ServiceError(409, "downloading", f"batch {batch_id!r} is being downloaded as a zip ({zipping} "
                               "download(s) in progress); DELETE it again with ?remove=true when they end")
        with store_errors():
            freed = runner.store.delete_batch(batch_id)
    if freed is None:
        raise ServiceError(409, "not_settled", f"batch {batch_id!r} is cancelled but its running items have not "
                           "stopped yet; DELETE it again with ?remove=true when GET /v1/batches/{id} says "
                           "settled: true")
    log.info("batch %s deleted (%d bytes)", batch_id, freed)
    return JSONResponse({"id": batch_id, "deleted": True, "freed_bytes": freed})
