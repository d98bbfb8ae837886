"""The SQLite job store (:class:`JobStore`): batches and items, their transitions in
transactions, the batch manifest and journal, recovery of a damaged store and adoption of
what is on disk (the files' safe names: :mod:`service.batch.names`).
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import sqlite3
import threading
import time
import uuid

from ..errors import ServiceError
from ..schemas.options import BatchOptions
from .items import _clean, atomic_write, is_finished, is_temporary, meta_path, write_text
from .names import DISK_NAME_BYTES, MAX_NAME_BYTES, clip_name, safe_name, unique  # noqa: F401 (re-exported)
from .summary import LIGHT_FIELDS, flagged, flagged_first


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
CREATE TABLE IF NOT EXISTS removed (
    id TEXT PRIMARY KEY,
    removed REAL NOT NULL,
    retention REAL NOT NULL
);
"""

#: Tombstones of the batches the result retention removed (id, when, the retention), so that
#: their URLs say why they are gone (probe round 9c): at most this many, the newest, and
#: none older than :data:`TOMBSTONE_AGE_S` (10,000 take some 0.6 MB of jobs.sqlite).
TOMBSTONES_KEPT = 10_000
TOMBSTONE_AGE_S = 30 * 24 * 3600.0


#: Beside each batch's ``in/`` and ``out/``: the manifest of its items
#: (written once, with the batch) and the journal of their state changes,
#: from which a damaged job store is rebuilt.
MANIFEST = "batch.json"
JOURNAL = "states.jsonl"
#: Marker of a batch whose folder and manifest were written while the store
#: was busy (locked): the runner registers it from the manifest when it can.
UNREGISTERED = "unregistered"


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


#: Seconds a store call waits for another connection's write lock (a second
#: server on the same data directory, a backup, an ``sqlite3`` shell) before
#: it gives up with "database is locked": the HTTP layer answers 503 with
#: ``Retry-After``, the runner tries again at its next step.
BUSY_TIMEOUT_S = 5.0

#: How many times an item is run before a lost worker fails it for good
#: (a worker killed, e.g. by the OOM killer, or a Dask worker lost).
MAX_ATTEMPTS = 3


#: An item index in a URL: ASCII digits only (``str.isdigit`` also accepts
#: ``²`` and other digits ``int`` refuses), at most 18 of them (64-bit).
_INDEX_TEXT = re.compile(r"[0-9]{1,18}")


class JobStore:
    """Batches and items in SQLite (WAL), every state change one atomic
    ``UPDATE ... WHERE status = <expected>`` inside a transaction."""

    def __init__(self, data_dir: str, busy_timeout: float = BUSY_TIMEOUT_S):
        self.data_dir = os.path.abspath(data_dir)
        os.makedirs(os.path.join(self.data_dir, "batches"), exist_ok=True)
        self.path = os.path.join(self.data_dir, "jobs.sqlite")
        self.busy_timeout = float(busy_timeout)
        self._local = threading.local()
        #: bumped when the store file was found gone and reopened: every
        #: thread's connection to the old file is then replaced
        self._generation = 0
        #: where a damaged store was moved at start-up, and the batches whose
        #: results were re-registered from disk (None: it opened cleanly)
        self.recovered: dict | None = None
        lost = self._lost_reason()
        try:
            self._open_checked()
        except sqlite3.DatabaseError as e:
            self._recover(e)
        else:
            self._rebuild_if_lost(lost)

    def _lost_reason(self) -> str | None:
        """Why the store file cannot hold the batches that are on disk:
        ``missing`` or ``empty`` (0 bytes: SQLite opens both as a valid,
        empty database), None when it is there."""
        try:
            size = os.path.getsize(self.path)
        except OSError:
            return "missing"
        return "empty" if size == 0 else None

    def _rebuild_if_lost(self, lost: str | None) -> int:
        """A store that is gone (deleted, truncated) while batch folders
        remain is rebuilt from them (:meth:`adopt_from_disk`, as a damaged
        one), and :attr:`recovered` says so (``/health``)."""
        if lost is None:
            return 0
        n = self.adopt_from_disk()
        if n:
            import logging

            logging.getLogger("service.jobs").error(
                "the job store %s was %s while %d batch folder(s) remained; rebuilt them from their manifests and "
                "journals", self.path, lost, n)
            self.recovered = {"damaged_copy": None, "error": f"store_lost: jobs.sqlite was {lost}",
                              "batches_recovered": n}
        return n

    def check_file(self) -> int:
        """While running: if ``jobs.sqlite`` was deleted or replaced since it
        was opened (a cache cleaner, by hand), open the file now at its path
        and rebuild the batches from their folders. Returns how many."""
        try:
            st = os.stat(self.path)
            ident = (st.st_dev, st.st_ino)
            lost = "empty" if st.st_size == 0 else None
        except OSError:
            ident, lost = None, "missing"
        if ident is not None and ident == getattr(self, "_ident", ident) and lost is None:
            return 0
        self._generation += 1
        self._local = threading.local()
        self._open_checked()
        return self._rebuild_if_lost(lost or "replaced")

    def _open_checked(self) -> None:
        db = self._db()
        check = db.execute("PRAGMA quick_check").fetchone()[0]
        if check != "ok":
            raise sqlite3.DatabaseError(f"quick_check: {check}")
        db.executescript(_SCHEMA)
        with contextlib.suppress(OSError):
            st = os.stat(self.path)
            self._ident = (st.st_dev, st.st_ino)

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
        return sum(self.adopt_batch(bid) for bid in sorted(os.listdir(root)))

    def adopt_batch(self, bid: str) -> bool:
        """Register one batch folder the store does not know (see
        :meth:`adopt_from_disk`); True if it was registered now. A batch
        whose registration was deferred (the store was busy when it was
        made: the ``unregistered`` marker) loses its marker."""
        bdir = self.batch_dir(bid)
        if not os.path.isdir(bdir) or self.batch(bid) is not None:
            with contextlib.suppress(OSError):
                os.unlink(os.path.join(bdir, UNREGISTERED))
            return False
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
            return False
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
        with contextlib.suppress(OSError):
            os.unlink(os.path.join(bdir, UNREGISTERED))
        return True

    def unregistered(self) -> list[str]:
        """Batches made while the store was busy (their folder and manifest
        written, the store's rows not): registered by the runner
        (:meth:`adopt_batch`) as soon as the store can take them."""
        root = os.path.join(self.data_dir, "batches")
        try:
            return sorted(b for b in os.listdir(root) if os.path.exists(os.path.join(root, b, UNREGISTERED)))
        except OSError:
            return []

    def defer(self, batch_id: str) -> None:
        """Mark a batch whose manifest is written but whose rows could not be
        (the store busy): :meth:`unregistered` lists it until it is adopted."""
        write_text(os.path.join(self.batch_dir(batch_id), UNREGISTERED), f"{time.time()}\n")

    def manifest_progress(self, batch_id: str) -> dict | None:
        """The progress document of a deferred batch (not yet in the store)
        from its manifest: every item pending."""
        bdir = self.batch_dir(batch_id)
        if not os.path.exists(os.path.join(bdir, UNREGISTERED)):
            return None
        try:
            with open(os.path.join(bdir, MANIFEST)) as f:
                m = json.load(f)
            items = [{"index": int(it["index"]), "name": str(it["name"]), "status": "pending", "output": None}
                     for it in m["items"]]
        except (OSError, ValueError, KeyError, TypeError):
            return None
        n = len(items)
        return {"id": batch_id, "status": "queued", "settled": False, "lighting": m["options"].get("lighting"),
                "options": m["options"], "counts": {"done": 0, "failed": 0, "pending": n, "running": 0,
                                                    "cancelled": 0, "total": n},
                "rate_per_minute": None, "time_left_s": None, "elapsed_s": 0.0, "rate": None, "eta_s": None,
                "created": m.get("created"), "items": items,
                "registration": "deferred: the job store was busy when the batch was made; it is kept on disk "
                                "and registered as soon as the store is free"}

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
        local = self._local
        db = getattr(local, "db", None)
        if db is None:
            db = sqlite3.connect(self.path, timeout=self.busy_timeout, isolation_level=None)
            db.row_factory = sqlite3.Row
            db.execute("PRAGMA journal_mode=WAL")
            db.execute("PRAGMA synchronous=NORMAL")
            local.db = db
        return db

    def _drop_connection(self) -> None:
        """Forget this thread's connection (after an error that may have left
        it inside a transaction, e.g. a full disk): the next call opens a new one."""
        db = getattr(self._local, "db", None)
        self._local.db = None
        if db is not None:
            with contextlib.suppress(Exception):
                db.close()

    @contextlib.contextmanager
    def _tx(self):
        db = self._db()
        try:
            db.execute("BEGIN IMMEDIATE")
        except sqlite3.Error:
            if db.in_transaction:
                self._drop_connection()
            raise
        try:
            yield db
        except BaseException:
            try:
                db.execute("ROLLBACK")
            except sqlite3.Error:
                self._drop_connection()
            raise
        try:
            db.execute("COMMIT")
        except sqlite3.Error:
            with contextlib.suppress(sqlite3.Error):
                db.execute("ROLLBACK")
            if db.in_transaction:
                self._drop_connection()
            raise

    # -- creation ----------------------------------------------------------
    def batch_dir(self, batch_id: str) -> str:
        return os.path.join(self.data_dir, "batches", batch_id)

    def new_batch_id(self) -> str:
        bid = uuid.uuid4().hex[:16]
        os.makedirs(os.path.join(self.batch_dir(bid), "in"), exist_ok=True)
        os.makedirs(os.path.join(self.batch_dir(bid), "out"), exist_ok=True)
        return bid

    def create_batch(self, batch_id: str, options: BatchOptions, sources: list[tuple[str, str]],
                     refused: dict | None = None) -> None:
        """Register a batch of ``(name, source path)`` items, all pending
        except those in ``refused`` (index -> error: recorded ``failed`` at
        once, e.g. a folder file whose name is not UTF-8). Names are made
        unique (``a.dng``, ``a (2).dng``); output names are ``<stem>.<ext>``,
        made unique the same way."""
        refused = refused or {}
        seen, outs, rows = set(), set(), []
        out_dir = os.path.join(self.batch_dir(batch_id), "out")
        for i, (name, src) in enumerate(sources):
            nm = unique(safe_name(name), seen)
            stem = os.path.splitext(nm)[0]
            # the output's name on disk stays short enough for its temporaries and sidecars
            out = unique(clip_name(f"{stem}.{options.extension}", DISK_NAME_BYTES - 12), outs)
            src = "" if i in refused else os.path.abspath(src)
            rows.append((batch_id, i, nm, src, os.path.join(out_dir, out)))
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
            db.executemany("INSERT INTO items (batch_id, idx, name, src, out, status, error, finished) "
                           "VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                           [(*r, "failed" if r[1] in refused else "pending", refused.get(r[1]),
                             created if r[1] in refused else None) for r in rows])
        for idx, err in sorted(refused.items()):
            self._journal(batch_id, idx=idx, status="failed", error=err)

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

    def claim(self, batch_id: str, limit: int, idx: int | None = None) -> list:
        """Move up to ``limit`` pending items (or only item ``idx``) to running; returns them."""
        with self._tx() as db:
            rows = db.execute("SELECT * FROM items WHERE batch_id = ? AND status = 'pending' AND (? IS NULL OR "
                              "idx = ?) ORDER BY idx LIMIT ?", (batch_id, idx, idx, limit)).fetchall()
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

    def requeue_item(self, batch_id: str, idx: int, reason: str, max_attempts: int | None = None,
                     give_up: str | None = None) -> str | None:
        """``running`` -> ``pending`` again: its worker went away before it
        answered (a graceful stop, a killed pool worker, a lost Dask worker
        or client). With ``max_attempts``, an item already run that many
        times is ``failed`` instead, with ``reason`` and the count; with
        ``give_up``, it is ``failed`` with that text. Returns
        the new status (None: the item was no longer running). Journalled,
        so a store rebuilt from the folders finds it pending too."""
        with self._tx() as db:
            row = db.execute("SELECT attempts FROM items WHERE batch_id = ? AND idx = ? AND status = 'running'",
                             (batch_id, idx)).fetchone()
            if row is None:
                return None
            cancelled = db.execute("SELECT status FROM batches WHERE id = ?", (batch_id,)).fetchone()
            if cancelled is not None and cancelled["status"] == "cancelled":   # nothing to run it for
                db.execute("UPDATE items SET status = 'cancelled', finished = ? WHERE batch_id = ? AND idx = ? "
                           "AND status = 'running'", (time.time(), batch_id, idx))
                err, status = None, "cancelled"
            elif give_up is not None or max_attempts is not None and row["attempts"] >= max_attempts:
                err = give_up or f"{reason} (run {row['attempts']} times, each time its worker was lost)"
                db.execute("UPDATE items SET status = 'failed', error = ?, finished = ? WHERE batch_id = ? "
                           "AND idx = ? AND status = 'running'", (err, time.time(), batch_id, idx))
                status = "failed"
            else:
                err = None
                db.execute("UPDATE items SET status = 'pending', started = NULL WHERE batch_id = ? AND idx = ? "
                           "AND status = 'running'", (batch_id, idx))
                status = "pending"
        self._journal(batch_id, idx=idx, status=status, error=err, requeued=reason)
        return status

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
                it["illuminant"] = {k: ill.get(k) for k in LIGHT_FIELDS}
            items.append(it)
        items = flagged_first(items)      # each keeps its index
        opts = json.loads(b["options"])
        # settled: the batch is over and every count final (a cancelled
        # batch's running items are still stopping until this is true)
        settled = b["status"] in ("done", "cancelled") and left == 0
        doc = {"id": batch_id, "status": b["status"], "settled": settled,
               "lighting": opts.get("lighting"), "options": opts,
               # each count is the items of that status, as GET /v1/batches counts them (pending was
               # "pending or running" here before probe round 9c; left is both)
               "counts": {"done": c["done"], "failed": c["failed"], "pending": c["pending"], "running": c["running"],
                          "cancelled": c["cancelled"], "total": len(rows)},
               "rate_per_minute": rate, "time_left_s": eta, "elapsed_s": elapsed,
               "rate": rate, "eta_s": eta,  # short names the web page reads
               "created": b["created"], "items": items,
               "low_confidence": [it["name"] for it in items if flagged(it)]}
        if opts.get("lighting") == "shared" and not b["light"] and b["status"] == "running":
            doc["phase"] = "estimating the shared light from all images"
        if b["light"]:
            doc["shared_light"] = json.loads(b["light"])
            doc["warnings"] = shared_light_warnings(doc["shared_light"])
        if b["light_error"]:
            doc["shared_light_error"] = b["light_error"]
        return doc


    # -- removal (issue 29, item 6: disk the user controls) -------------------
    def disk_bytes(self, batch_id: str) -> int:
        """Bytes of the batch's folder (its uploaded inputs and results)."""
        return _tree_bytes(self.batch_dir(batch_id))

    def summaries(self) -> list[dict]:
        """Every batch, newest first: id, status, times, counts, disk bytes."""
        out = []
        for b in self._db().execute("SELECT id, status, created, finished FROM batches ORDER BY created DESC"):
            c = self.counts(b["id"])
            out.append({"id": b["id"], "status": b["status"], "created": b["created"], "finished": b["finished"],
                        "counts": {"done": c["done"], "failed": c["failed"], "pending": c["pending"],
                                   "running": c["running"], "cancelled": c["cancelled"], "total": sum(c.values())},
                        "bytes": self.disk_bytes(b["id"])})
        return out

    def delete_batch(self, batch_id: str, expired_after: float | None = None) -> int | None:
        """Remove a settled batch (done or cancelled, nothing pending or
        running) with its folder: its records go in one transaction, then its
        folder, first renamed out of ``batches/`` (so a store rebuilt from the
        folders never brings it back) and then deleted. Returns the bytes
        freed; ``None`` when the batch is not settled (nothing removed).
        ``expired_after``: the result retention that removes it (seconds),
        kept in a tombstone (:meth:`removal`) in the same transaction."""
        bdir = self.batch_dir(batch_id)
        size = self.disk_bytes(batch_id)
        trash = os.path.join(self.data_dir, f".deleting-{batch_id}")
        with self._tx() as db:
            b = db.execute("SELECT status FROM batches WHERE id = ?", (batch_id,)).fetchone()
            busy = db.execute("SELECT COUNT(*) FROM items WHERE batch_id = ? AND status IN ('pending', 'running')",
                              (batch_id,)).fetchone()[0]
            if b is None or b["status"] not in ("done", "cancelled") or busy:
                return None
            db.execute("DELETE FROM items WHERE batch_id = ?", (batch_id,))
            db.execute("DELETE FROM batches WHERE id = ?", (batch_id,))
            if expired_after is not None:
                self._bury(db, batch_id, float(expired_after))
            if os.path.isdir(bdir):
                os.replace(bdir, trash)     # a failure here rolls the records back
        shutil.rmtree(trash, ignore_errors=True)
        return size

    @staticmethod
    def _bury(db, batch_id: str, retention_s: float) -> None:
        """Record that the retention removed ``batch_id``, and drop the
        tombstones past :data:`TOMBSTONE_AGE_S` or beyond the newest
        :data:`TOMBSTONES_KEPT` (so they never grow without limit)."""
        now = time.time()
        db.execute("INSERT OR REPLACE INTO removed (id, removed, retention) VALUES (?, ?, ?)",
                   (batch_id, now, retention_s))
        db.execute("DELETE FROM removed WHERE removed < ?", (now - TOMBSTONE_AGE_S,))
        db.execute("DELETE FROM removed WHERE id NOT IN (SELECT id FROM removed ORDER BY removed DESC LIMIT ?)",
                   (TOMBSTONES_KEPT,))

    def removal(self, batch_id: str) -> dict | None:
        """The tombstone of a batch the result retention removed: ``removed``
        (epoch seconds) and ``retention_s``; None for a batch never known, removed
        by hand (``DELETE ?remove=true``, ``wandell batches --remove``) or whose
        tombstone is gone (older than :data:`TOMBSTONE_AGE_S`, beyond
        :data:`TOMBSTONES_KEPT`, or a store rebuilt from the folders)."""
        row = self._db().execute("SELECT removed, retention FROM removed WHERE id = ? AND removed >= ?",
                                 (str(batch_id), time.time() - TOMBSTONE_AGE_S)).fetchone()
        return None if row is None else {"removed": row["removed"], "retention_s": row["retention"]}

    def expired_batches(self, retention_s: float) -> list[str]:
        """Batches finished or cancelled more than ``retention_s`` seconds ago
        with nothing pending or running (``WANDELL_BATCH_RESULT_RETENTION``)."""
        return [r["id"] for r in self._db().execute(
            "SELECT id FROM batches WHERE status IN ('done', 'cancelled') AND finished IS NOT NULL "
            "AND finished <= ? AND id NOT IN (SELECT batch_id FROM items WHERE status IN ('pending', 'running'))",
            (time.time() - retention_s,))]


def _tree_bytes(path: str) -> int:
    total = 0
    for root, _, files in os.walk(path):
        for f in files:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, f)).st_size
    return total


def shared_light_warnings(light: dict) -> list[str]:
    """The batch-level warnings of a shared light (what ``wandell batch
    --lighting shared`` prints and the page shows): each of its warnings
    (e.g. the images' own lights disagree: "they may not all be under one
    light") with its confidence, and a low confidence said as such."""
    conf = light.get("confidence")
    tail = f" (shared light confidence {conf:.2f})" if isinstance(conf, (int, float)) else ""
    out = [f"shared light: {w}{tail}" for w in light.get("warnings") or []]
    if light.get("low_confidence") and not out:
        out.append(f"shared light: low confidence{tail}: check the white balance of these images")
    return out
