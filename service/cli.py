"""The ``wandell`` command (also ``python -m service.cli``), issue 6.

``wandell batch IN_DIR OUT_DIR [options]``
    White-balance every RAW in ``IN_DIR`` into ``OUT_DIR`` on a local process
    pool (``--workers``) or a Dask cluster (``--dask-scheduler``), with a
    progress bar on stderr and a summary table at the end, followed by the
    subfolders and non-RAW files it did not process (``--recursive`` walks
    the subfolders, the outputs mirroring the tree). Resumable: an
    output already finished (renamed into place with its sidecar, see
    :mod:`service.jobs`) is skipped; a partially written one never counts.
``wandell analyze FILE``
    The estimate as JSON (the body of ``POST /v1/analyze``).
``wandell white-balance FILE OUT``
    One corrected image (``POST /v1/white-balance``).

Options are those of the API, generated from the same declarations
(:mod:`service.schemas.fields`: descriptions, defaults, accepted values):
``--camera``, ``--method``, ``--quality``, ``--surface-dim``,
``--light-dim``, ``--region-size``, ``--surface-model``, ``--light-model``,
``--target``, ``--output``, ``--format``, ``--exposure``, ``--lighting``
(per-image or shared), ``--xmp`` (a flag), ``--xmp-dir DIR``, ``--xmp-name stem|full`` and
``--xmp-overwrite`` (Camera Raw sidecars beside the RAWs, :func:`sidecar_path`,
:func:`service.sidecars._sidecar_job`); plus ``--force`` (batch: compute finished outputs
again), ``--quiet`` (no progress bar or table; failures and warnings still
on stderr) and ``--version``. ``white-balance`` takes the format from OUT's extension
(.tif/.tiff, .png, .jpg/.jpeg); ``--format`` must agree with it. A batch
rerun whose options differ from those stored beside a finished output (its
``.wandell/NAME.json`` sidecar) says so in the summary. Exit status: 0 when
every item succeeded or was already done, 1 when something failed, 2 for a
usage error (bad options, a FILE or IN_DIR that does not exist or is not
a file/folder), 130 when interrupted (Ctrl-C: the pool stops at once, finished
outputs are kept, the summary so far is printed; the same command resumes).

Start-up stays light (``wandell --help`` imports no numerical library): the
heavy modules are imported by the command that needs them.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import re
import shlex
import sys
import threading

from .cli_light import shared_light_of
from .cli_paths import (EXTENSION_FORMATS, check_workers, dng_copies, format_for,  # noqa: F401 - cli.format_for
                        input_file, input_folder, kept_output, output_file, output_folder, own_outputs)
from .errors import ServiceError
from .schemas.cli import add_options
from .schemas.fields import BATCH, BATCH_FORMATS, ESTIMATION, REGIONS, RENDERING, SIDECAR, XMP_NAMES


def _lazy_module(name: str):
    """``name`` imported on first attribute access (:class:`importlib.util.LazyLoader`):
    the batch machinery (and the pydantic options models it loads) costs
    ``wandell --help`` nothing."""
    import importlib.util

    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.find_spec(name)
    spec.loader = importlib.util.LazyLoader(spec.loader)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


jobs = _lazy_module("service.jobs")
sidecars = _lazy_module("service.sidecars")
batch_xmp = _lazy_module("service.batch.xmp")

#: Never written raw to a terminal: C0 controls (ESC, BEL, CR, LF, ...), DEL,
#: C1 controls (CSI U+009B ...), the bidirectional overrides and isolates
#: (they reorder what follows on screen) and lone surrogates (undecodable
#: bytes of a file name, which would also make the write fail).
_UNPRINTABLE = re.compile("[\x00-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069\ud800-\udfff]")


def term_safe(text, keep: str = "") -> str:
    """``text`` with every control character shown as a visible escape
    (``\\x1b``, ``\\x07``, ``\\u202e``; a byte of a name that is not UTF-8 as
    ``\\xff``), except those in ``keep``: what the CLI prints of file names,
    errors, notes and warnings cannot move the cursor, erase lines or set
    the terminal's title."""
    def esc(m):
        ch = m.group()
        if ch in keep:
            return ch
        o = ord(ch)
        if 0xDC80 <= o <= 0xDCFF:  # os.fsdecode's surrogateescape of byte o - 0xDC00
            return f"\\x{o - 0xDC00:02x}"
        return f"\\x{o:02x}" if o < 0x100 else f"\\u{o:04x}"

    return _UNPRINTABLE.sub(esc, str(text))


class _SafeStream:
    """stdout/stderr as the CLI writes them: :func:`term_safe` on everything
    (line breaks and tabs kept, and ``\\r`` for the progress bar), so that no
    message, warning or library text carries a raw control character."""

    def __init__(self, stream):
        self._stream = stream

    def write(self, text) -> int:
        return self._stream.write(term_safe(text, keep="\n\r\t"))

    def __getattr__(self, name):
        return getattr(self._stream, name)


class _ArgumentParser(argparse.ArgumentParser):
    """argparse whose messages (usage errors quote the arguments raw) are
    written through :func:`term_safe`."""

    def _print_message(self, message, file=None):
        if message:
            (file or sys.stderr).write(term_safe(message, keep="\n\t"))


def _add_options(ap: argparse.ArgumentParser, batch: bool | None) -> None:
    """The API's options as flags (from :mod:`service.schemas`: the same
    descriptions, defaults and accepted values as ``/docs``): estimation for
    every command, rendering for ``white-balance`` and ``batch``, the
    lighting mode for ``batch``."""
    add_options(ap, ESTIMATION, describe={"camera": "measured camera name, 'matrix' or 'generic' (default: from "
                                                    "the file)"})
    if batch is None:
        return
    add_options(ap, RENDERING, defaults={"format": None}, choices={"format": BATCH_FORMATS} if batch else None,
                describe={"format": "tiff (16-bit), png (8-bit), png16, jpeg; white-balance: taken from OUT's "
                                    "extension (.tif, .png, .jpg), and an error if this disagrees; batch: default "
                                    "tiff, or dng: each RAW as OUT_DIR/NAME.dng, its white balance inside"})
    ap.add_argument("-q", "--quiet", action="store_true",
                    help="no progress bar and no summary table; failures, notes and warnings still go to stderr")
    if batch:
        ap.add_argument("--force", action="store_true",
                        help="compute finished outputs again, and replace a file of an output's name, or "
                             "OUT_DIR/batch.json, that no batch wrote (default: skip finished outputs, resumable; "
                             "keep other files, their items fail, a batch.json with a warning); a read-only file is "
                             "never replaced")
        add_options(ap, BATCH)
        ap.add_argument("--workers", type=int, default=0,
                        help="local worker processes (0: one per core; at most 4 per core)")
        ap.add_argument("-r", "--recursive", action="store_true",
                        help="also the RAWs of IN_DIR's subfolders, their outputs in the same subfolders of "
                             "OUT_DIR (default: subfolders are listed as not processed)")
        ap.add_argument("--dask-scheduler", default=os.environ.get("WANDELL_DASK_SCHEDULER", ""),
                        help="run on this Dask cluster (tcp://host:8786) instead of the local pool")
    add_options(ap, SIDECAR, describe={
        "xmp": "also write a Camera Raw XMP sidecar (the estimate as Temperature/Tint) for every RAW, beside it "
               "(IMG_0001.dng -> IMG_0001.xmp; into OUT_DIR when the RAW's folder is not writable); for a DNG also a "
               "copy with the white balance inside, IMG_0001.wandell.dng (Lightroom reads a DNG's own XMP, not a "
               "sidecar; the original is left untouched)" if batch else
               "also write a Camera Raw XMP sidecar (the estimate as Temperature/Tint) beside the RAW (IMG_0001.dng "
               "-> IMG_0001.xmp; beside OUT when the RAW's folder is not writable); for a DNG also a copy with the "
               "white balance inside (its XMP and AsShotNeutral), IMG_0001.wandell.dng beside the sidecar: "
               "Lightroom reads a DNG's own XMP, not a sidecar; the original is left untouched",
        "xmp_dir": "write the sidecars into DIR instead (the subfolders of IN_DIR kept; implies --xmp)" if batch else
                   "write the sidecar into DIR instead of beside the RAW (implies --xmp)"})


def _options(args, lighting: str = "per-image") -> jobs.BatchOptions:
    given = {n: getattr(args, n, None) for n in {**ESTIMATION, **RENDERING}}
    return jobs.batch_options(**given, lighting=lighting)


@dataclasses.dataclass(frozen=True)
class _DefaultLimits:
    """The settings the CLI reads, at the embedded defaults of
    :class:`service.settings.Settings` (a test keeps them equal)."""
    max_pixels: int = 120_000_000
    estimation_pixels: int = 1_000_000
    max_surface_regions: int = 10_000


#: ``WANDELL_*`` variables that are not service settings (recovery.bayes's model disk cache)
_NOT_SETTINGS = frozenset({"WANDELL_MODEL_CACHE", "WANDELL_MODEL_CACHE_DIR"})


def _settings():
    """The service settings (``WANDELL_*``): the pixel limits of decoding.
    With no ``WANDELL_*`` variable in the environment (any case, as
    pydantic-settings reads them) they are the embedded defaults, given
    without importing pydantic-settings (0.2 s of start-up, issue 19). The
    model disk cache's variables (:func:`_model_disk_cache`) are not settings."""
    if not any(k.upper().startswith("WANDELL_") and k.upper() not in _NOT_SETTINGS for k in os.environ):
        return _DefaultLimits()
    from .settings import settings_or_exit

    return settings_or_exit("wandell")            # a WANDELL_* variable out of range: a usage error in words


def _limits():
    s = _settings()
    return s.max_pixels, s.estimation_pixels


class Progress:
    """The batch's progress bar on stderr, drawn by tqdm: redrawn in place on
    a terminal, one line per update otherwise (a log or a pipe gets no
    carriage returns). The line gives the counts (done, failed, skipped), the
    rate in images per minute and the time left, both over the images
    worked on (those skipped as already finished are tqdm's ``initial``, so
    they make the run look no faster)."""

    #: The line: tqdm's bar, count and time left; the counts and rate are its description.
    FORMAT = "[{bar:30}] {n_fmt}/{total_fmt}  left {remaining}  {desc}"

    def __init__(self, total: int, stream=None, width: int = 30):
        self.total, self.width = total, width
        self.stream = stream or sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self._bar = None

    def _start(self, skipped: int):
        import io
        import shutil

        from tqdm import tqdm   # here: wandell --help and the other commands do not load it

        # the size given (on a pseudo-terminal of 0 x 0, tqdm would hide its line)
        size = shutil.get_terminal_size()
        return tqdm(total=self.total, initial=skipped, file=self.stream if self.tty else io.StringIO(),
                    bar_format=self.FORMAT.replace("{bar:30}", "{bar:%d}" % self.width), ascii=" #",
                    mininterval=0, miniters=1, ncols=size.columns if self.tty else None,
                    nrows=size.lines if self.tty else None, leave=True)

    def update(self, done: int, failed: int, skipped: int) -> None:
        bar = self._bar = self._bar or self._start(skipped)
        el = bar.format_dict["elapsed"]
        worked = done + failed
        rate = worked / el * 60 if el > 0 and worked else 0.0
        bar.set_description_str(f"done {done}  failed {failed}  skipped {skipped}  {rate:.1f} img/min", refresh=False)
        step = done + failed + skipped - bar.n
        if step:
            bar.update(step)       # redraws on a terminal
        elif self.tty:
            bar.refresh()
        if not self.tty:
            self.stream.write(str(bar) + "\n")
            self.stream.flush()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def _warnings_of(row: dict) -> list[str]:
    ill = row.get("illuminant") or {}
    return [str(w) for w in (ill.get("warnings") or [])]


def _summary(rows: list[dict], stream, quiet: bool = False) -> None:
    """The table (file, status, CCT, seconds, light or error), then notes
    (options that differ from a finished output's) and warnings; with
    ``quiet`` only failures, notes and warnings, on stderr."""
    if quiet:
        for r in rows:
            name = term_safe(r["name"])
            if r["status"] == "failed":
                sys.stderr.write(f"{name}: failed: {term_safe(r.get('error'))}\n")
            if r.get("note"):
                sys.stderr.write(f"{name}: note: {term_safe(r['note'])}\n")
            for w in _warnings_of(r):
                sys.stderr.write(f"{name}: warning: {term_safe(w)}\n")
        return
    names = {id(r): term_safe(r["name"]) for r in rows}
    w = max([4] + [len(n) for n in names.values()])
    stream.write(f"\n{'file':{w}s}  {'status':8s}  {'CCT K':>7s}  {'seconds':>7s}  light camera RGB / error\n")
    for r in rows:
        ill = r.get("illuminant") or {}
        cct = ill.get("cct")
        rgb = ill.get("camera_rgb")
        what = r.get("error") or ("" if rgb is None else "(" + ", ".join(f"{v:.3f}" for v in rgb) + ")")
        sec = r.get("seconds")
        stream.write(f"{names[id(r)]:{w}s}  {r['status']:8s}  {'' if cct is None else f'{cct:7.0f}':>7s}  "
                     f"{'' if sec is None else f'{sec:7.2f}':>7s}  {term_safe(what)}\n")
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "skipped", "failed")}
    notes = [(names[id(r)], term_safe(r["note"])) for r in rows if r.get("note")]
    if notes:
        stream.write("\nnotes:\n" + "".join(f"  {n}: {t}\n" for n, t in notes))
    warns = [(names[id(r)], term_safe(w)) for r in rows for w in _warnings_of(r)]
    if warns:
        stream.write("\nwarnings:\n" + "".join(f"  {n}: {t}\n" for n, t in warns))
    if low := [names[id(r)] for r in rows if (r.get("illuminant") or {}).get("low_confidence")]:
        stream.write(f"\nlow confidence, check these white balances first ({len(low)}):\n" + "".join(f"  {n}\n" for n in low))
    stream.write(f"\n{counts['done']} done, {counts['skipped']} skipped (already finished), "
                 f"{counts['failed']} failed, {len(rows)} in all\n")


def options_difference(stored: dict | None, options: jobs.BatchOptions) -> str | None:
    """How the options stored beside a finished output differ from this
    run's (``None`` when they agree); options the older run did not know
    count as their defaults."""
    now = json.loads(options.to_json())
    if not isinstance(stored, dict):
        return "made by a run that did not record its options"
    base = json.loads(jobs.BatchOptions().to_json())
    before = {**base, **{k: v for k, v in stored.items() if k in base}}
    diff = [f"{k}: {before[k]!r} -> {now[k]!r}" for k in sorted(now) if before.get(k) != now[k]
            and k != "lighting"]
    return "made with other options (" + "; ".join(diff) + ")" if diff else None


def _inputs(in_dir: str, recursive: bool = False, out_dir: str | None = None) -> list[str]:
    return scan_inputs(in_dir, recursive, out_dir)[0]


def scan_inputs(in_dir: str, recursive: bool = False, out_dir: str | None = None) -> tuple[list[str], list]:
    """The RAW/TIFF/PNG files of ``in_dir`` (with ``recursive``, of its
    subfolders too, hidden ones and ``out_dir`` left out), and what was left
    out, for the summary: ``(files, ignored)``, ``ignored`` a list of
    ``(relative path, "folder" | "not RAW")`` (hidden files such as
    ``.DS_Store`` are not listed)."""
    files, ignored = [], []
    skip = os.path.realpath(out_dir) if out_dir else None
    seen = {os.path.realpath(in_dir)}  # a symlink back up the tree is walked once

    def walk(rel: str) -> None:
        here = os.path.join(in_dir, rel) if rel else in_dir
        names = sorted(os.listdir(here))
        copies = dng_copies(names, jobs.RAW_SUFFIXES) | own_outputs(here, names)   # OUT_DIR = IN_DIR: round 7
        for name in names:
            if name.startswith("."):
                continue
            path, relp = os.path.join(here, name), os.path.join(rel, name) if rel else name
            if name in copies:      # --xmp's copies of RAWs here (were inputs again on a rerun: round 6), as sidecars
                continue
            if os.path.isdir(path):
                if skip is not None and os.path.realpath(path) == skip:
                    continue
                if recursive:
                    real = os.path.realpath(path)
                    if real not in seen:
                        seen.add(real)
                        walk(relp)
                else:
                    ignored.append((relp + os.sep, "folder"))
            elif os.path.isfile(path) and name.lower().endswith(jobs.RAW_SUFFIXES):
                files.append(path)
            elif name.lower().endswith(SIDECAR_SUFFIXES):
                continue                    # editors' sidecars of the RAWs (ours among them): not "not processed"
            else:
                ignored.append((relp, "not RAW"))

    walk("")
    return files, ignored


#: Sidecars of RAWs (XMP, RawTherapee's .pp3): not listed as files a batch did not process.
SIDECAR_SUFFIXES = (".xmp", ".pp3")


def _ignored_text(ignored: list, limit: int = 10) -> str:
    """The summary's lines for what the batch did not process."""
    out = []
    for kind, what, hint in (("folder", "subfolder", " (--recursive processes them, mirroring the tree)"),
                             ("not RAW", "file", " not RAW/TIFF/PNG (by name)")):
        names = [n for n, k in ignored if k == kind]
        if names:
            shown = ", ".join(names[:limit]) + (f", and {len(names) - limit} more" if len(names) > limit else "")
            out.append(f"not processed: {len(names)} {what}{'s' if len(names) != 1 else ''}{hint}: {shown}\n")
    return "".join(out)


class BatchInterrupted(Exception):
    """Ctrl-C stopped :func:`run_batch`; ``rows`` as it returns them, unfinished ones ``stopped``."""

    def __init__(self, rows: list[dict]):
        super().__init__("interrupted")
        self.rows = rows


class _CtrlC:
    """SIGINT during a batch (main thread only): the first raises
    KeyboardInterrupt as usual; a second (pressed again while the pool is
    being stopped) kills the workers outright instead of interrupting the
    clean-up; a third leaves at once. So two Ctrl-C never end in a
    traceback or a half-stopped pool."""

    def __init__(self):
        self.hits, self.executor, self._old = 0, None, None

    def __enter__(self):
        import signal

        if threading.current_thread() is threading.main_thread():
            self._old = signal.signal(signal.SIGINT, self._handler)
        return self

    def _handler(self, signum, frame):
        self.hits += 1
        if self.hits == 1:
            raise KeyboardInterrupt
        if self.hits >= 3:
            os._exit(130)
        if hasattr(self.executor, "terminate"):
            with contextlib.suppress(Exception):
                self.executor.terminate(kill=True, grace_s=0.5)

    def __exit__(self, *exc):
        import signal

        if self._old is not None:
            signal.signal(signal.SIGINT, self._old)
        return False


def _stop_now(executor) -> None:
    """After a Ctrl-C: end the pool now (queued items dropped, running ones terminated)."""
    if executor is None:
        return
    if hasattr(executor, "terminate"):
        executor.terminate()
    else:  # a Dask cluster: its tasks are the cluster's; stop waiting for them
        executor.shutdown(wait=False)


def run_batch(in_dir: str, out_dir: str, options: jobs.BatchOptions, workers: int = 0,
              dask_scheduler: str | None = None, executor=None, stream=None, force: bool = False,
              quiet: bool = False, recursive: bool = False, xmp: dict | None = None,
              info: dict | None = None, item_fn=None, sample_fn=None) -> list[dict]:
    """Correct every RAW in ``in_dir`` into ``out_dir``; returns one row per
    file (``name``, ``status`` done/skipped/failed, ``illuminant``,
    ``error``, ``seconds``, ``note``). Finished outputs are skipped (with a
    ``note`` when they were made with other options) unless ``force``.

    Ctrl-C (KeyboardInterrupt) stops the run promptly: the pool is ended
    (:meth:`service.jobs.LocalExecutor.terminate`), what finished is kept,
    and :class:`BatchInterrupted` carries the rows (unfinished ones
    ``stopped``); the same command run again resumes.

    With ``recursive`` the subfolders' files too, named by their path
    under ``in_dir``, their outputs in the same subfolders of ``out_dir``.

    ``xmp`` (``{"folder", "name", "overwrite"}``, ``wandell batch --xmp``):
    then a Camera Raw sidecar for every finished item (done or skipped), on
    the same executor (:func:`service.sidecars._sidecar_job`): beside the RAW, or in
    ``folder`` (the relative tree kept), into ``out_dir`` when the RAW's
    folder is not writable; rows get ``xmp`` (the path written) and a
    ``note`` when it went elsewhere, was kept or could not be made. Each
    image's sidecar is made as soon as the image is finished, so a Ctrl-C
    leaves every finished image with its sidecar (those still being made
    are written before the command exits) and no ``.lock`` file behind.

    ``info`` (a dict, filled in): ``shared_light``, the light of a shared batch. ``OUT_DIR/batch.json``:
    :mod:`service.batch.summary`, the items flagged low confidence first; a ``batch.json`` no batch
    wrote is kept unless ``force`` (a read-only one even then), with a warning on stderr.

    An item whose worker dies abruptly breaks the local pool and every item in flight with it: those
    run again one at a time, each alone (:func:`service.batch.executors.run_alone`), and only one whose
    worker dies while alone fails, as ``worker_killed`` (so too in the shared light's estimation). ``item_fn``,
    ``sample_fn`` (Python only; default :func:`service.jobs.process_item`, ``estimation_sample``): what runs
    an item and estimates an image for the shared light, for the tests' fault injection."""
    import io

    from .batch import summary as batch_summary   # before Ctrl-C can land in its import

    stream = io.StringIO() if quiet else (stream or sys.stderr)
    files = _inputs(in_dir, recursive, out_dir)
    os.makedirs(out_dir, exist_ok=True)
    max_pixels, est_pixels = _limits()
    seen: set = set()
    tasks = []
    for p in files:
        name = os.path.relpath(p, in_dir)
        # a name cut as the server's batches cut theirs, so its records and temporaries fit in NAME_MAX (a 255-byte
        # RAW's item failed with "[Errno 36] File name too long: .wandell/NAME.tif.lock": probe round 8)
        sub, base = os.path.split(f"{os.path.splitext(name)[0]}.{options.extension}")
        out = os.path.join(out_dir, jobs.unique(os.path.join(sub, jobs.clip_name(base, jobs.DISK_NAME_BYTES - 12)),
                                                seen))
        os.makedirs(os.path.dirname(out), exist_ok=True)
        tasks.append(jobs.ItemTask(src=p, out=out, name=name, options=options, max_pixels=max_pixels,
                                   estimation_pixels=est_pixels, force=force))
    # the temporaries a killed run left for this batch's outputs (never another file of OUT_DIR)
    jobs.remove_stale_temporaries(out_dir, {os.path.basename(t.out) for t in tasks} | {"shared-light"})
    rows = {t.name: {"name": t.name, "status": "pending"} for t in tasks}
    todo = []
    for t in tasks:
        finished = jobs.is_finished(t.out)
        if not force and finished:
            with open(jobs.meta_path(t.out, ".json")) as f:
                side = json.load(f)
            rows[t.name].update(status="skipped", illuminant=side.get("illuminant"))
            diff = options_difference(side.get("options"), options)
            if diff:
                rows[t.name]["note"] = diff + "; --force to compute it again with these"
        elif kept := kept_output(t.out, finished, force, t.src):   # the input, read-only, or not ours: kept
            rows[t.name].update(status="failed", error=kept)
        else:
            todo.append(t)
    bar = Progress(len(tasks), stream)
    count = {s: sum(r["status"] == s for r in rows.values()) for s in ("done", "failed", "skipped")}
    bar.update(**count)
    own, interrupted, xmp_jobs = executor is None and bool(todo), False, {}   # xmp_jobs: name -> its sidecar's future
    if xmp is not None:
        batch_xmp.preload()   # before Ctrl-C can land in their first import (it would leave them half-made)
    ctrl_c = _CtrlC().__enter__()
    try:
        if own:
            executor = ctrl_c.executor = jobs.make_executor(workers or None, dask_scheduler or None)
        if todo and options.lighting == "shared":
            light = shared_light_of(tasks, options, out_dir, executor, rows, count, force, sample_fn)
            if own and getattr(executor, "broken", None):      # an image killed its worker: a new pool
                executor.shutdown(wait=False)
                executor = ctrl_c.executor = jobs.make_executor(workers or None, None)
            if info is not None:
                info["shared_light"] = light
            todo = [t for t in todo if rows[t.name]["status"] == "pending"]
            todo = [dataclasses.replace(t, light=light) for t in todo] if light else []
            for t in tasks:
                if light is None and rows[t.name]["status"] == "pending":
                    rows[t.name].update(status="failed", error="the shared light could not be estimated")
                    count["failed"] += 1
        from concurrent.futures import as_completed
        from concurrent.futures.process import BrokenProcessPool

        from .batch.executors import run_alone

        fn = item_fn or jobs.process_item
        futs = {executor.submit(fn, t): t for t in todo}
        suspects = []

        def outcomes():
            for fut in as_completed(futs):
                # never yield inside the try: a Ctrl-C in the loop below closes this generator at its yield,
                # and `except BaseException` took the GeneratorExit for a lost worker and yielded again
                # ("generator ignored GeneratorExit", a traceback on stderr; seen once in the suite)
                try:
                    res = fut.result()
                except BrokenProcessPool:   # the local pool broke: this item may be innocent
                    suspects.append(futs[fut])
                    continue
                except KeyboardInterrupt:
                    raise
                except BaseException as e:  # a worker lost
                    res = {"status": "failed", "error": f"worker_lost: {type(e).__name__}: {e}"}
                yield futs[fut], res
            if suspects and own:             # a new pool for what is left (the sidecars)
                executor.shutdown(wait=False)
                ctrl_c.executor = executor_box[0] = jobs.make_executor(workers or None, None)
            for t in suspects:
                res, deaths = run_alone(fn, t)
                yield t, res if res is not None else {
                    "status": "failed", "error": f"worker_killed: processing this image ended its worker process "
                    f"{deaths} times when it ran alone (a crash in decoding it, or not enough memory)"}

        executor_box = [executor]
        for t, res in outcomes():
            executor = executor_box[0]
            res.pop("retry", None)
            rows[t.name].update(res)
            rows[t.name].pop("adopted", None)
            count["done" if res["status"] == "done" else "failed"] += 1
            bar.update(**count)
            if xmp is not None and res["status"] == "done":   # its sidecar now, not after the whole batch
                xmp_jobs[t.name] = batch_xmp.submit_sidecar(t, rows[t.name], options, out_dir, executor, xmp,
                                                            _settings())
        executor = executor_box[0]
        if xmp is not None:
            batch_xmp.batch_sidecars(tasks, rows, options, out_dir, executor, xmp, xmp_jobs, _settings())
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if own:        # the pool in use now (a new one when culprit isolation replaced a broken one)
            executor = ctrl_c.executor
        try:
            bar.close()
            if interrupted and own:
                _stop_now(executor)
            elif own and executor is not None:
                executor.shutdown()
        finally:
            ctrl_c.__exit__(None, None, None)
    if interrupted:
        for t in tasks:
            r = rows[t.name]
            if r["status"] != "pending":
                continue
            r["status"] = "stopped"
            if jobs.is_finished(t.out):  # written just before the stop, its answer not yet read
                with contextlib.suppress(OSError, ValueError):
                    with open(jobs.meta_path(t.out, ".json")) as f:
                        r.update(status="done", illuminant=json.load(f).get("illuminant"))
        for t in tasks:   # a worker ended mid-item leaves its lock file: gone once nobody holds the lock
            jobs.remove_stale_lock(t.out)
        if xmp is not None:   # every finished image gets its sidecar before the command exits
            with contextlib.suppress(KeyboardInterrupt):
                batch_xmp.finish_sidecars(tasks, rows, options, out_dir, xmp, xmp_jobs, _settings())
    with contextlib.suppress(OSError, KeyboardInterrupt):   # OUT_DIR/batch.json, flagged first (docs/confidence.md)
        try:
            batch_summary.write_cli_summary(tasks, rows, options, in_dir, out_dir, interrupted, force=force)
        except batch_summary.SummaryKept as e:    # a user's batch.json: kept and said, even with --quiet
            sys.stderr.write(f"warning: {term_safe(str(e))}\n")
    if interrupted:
        raise BatchInterrupted([rows[t.name] for t in tasks])
    return [rows[t.name] for t in tasks]


def _cmd_batch(args) -> int:
    args.format = args.format or "tiff"
    opts = _options(args, args.lighting)
    input_folder(args.in_dir)
    output_folder(args.out_dir)
    check_workers(args.workers, jobs.max_local_workers())
    files, ignored = scan_inputs(args.in_dir, args.recursive, args.out_dir)
    if not files:
        raise ServiceError(422, "empty_folder", f"no RAW/TIFF/PNG files in {args.in_dir!r}"
                           + (" or its subfolders" if args.recursive else "")
                           + ("; " + _ignored_text(ignored).strip().replace("\n", "; ") if ignored else ""))
    try:
        xmp = None if not (args.xmp or args.xmp_dir) else {"folder": args.xmp_dir or None, "name": args.xmp_name,
                                                            "overwrite": args.xmp_overwrite}
        info: dict = {}
        rows = run_batch(args.in_dir, args.out_dir, opts, args.workers, args.dask_scheduler, force=args.force,
                         quiet=args.quiet, recursive=args.recursive, xmp=xmp, info=info)
    except BatchInterrupted as e:
        _print_light_warnings(info.get("shared_light"))
        if threading.current_thread() is threading.main_thread():
            import signal

            signal.signal(signal.SIGINT, signal.SIG_IGN)  # stopped already: more Ctrl-C change nothing
        _summary(e.rows, sys.stdout, args.quiet)
        stopped = sum(r["status"] == "stopped" for r in e.rows)
        finished = sum(r["status"] in ("done", "skipped") for r in e.rows)
        cmd = " ".join(shlex.quote(a) for a in ["wandell"] + list(args.argv))
        sys.stderr.write(f"\ninterrupted: {finished} of {len(e.rows)} finished and kept, {stopped} stopped before "
                         f"they were written (nothing partial is kept).\nTo resume, run the same command again "
                         f"(finished outputs are skipped):\n  {cmd}\n")
        return 130
    _summary(rows, sys.stdout, args.quiet)
    _print_light_warnings(info.get("shared_light"))
    if (args.xmp or args.xmp_dir) and not args.quiet:
        written = [r["xmp"] for r in rows if r.get("xmp")]
        beside = sum(os.path.dirname(p) == os.path.dirname(os.path.abspath(os.path.join(args.in_dir, r["name"])))
                     for r, p in ((r, r["xmp"]) for r in rows if r.get("xmp")))
        kept = sum(bool(r.get("xmp_kept")) for r in rows)
        print(f"XMP sidecars: {len(written)} written ({beside} beside their RAW), {kept} kept as they were"
              + (" (--xmp-overwrite replaces them)" if kept else ""))
    if ignored:
        (sys.stderr if args.quiet else sys.stdout).write(_ignored_text(ignored))
    return 1 if any(r["status"] == "failed" for r in rows) else 0


def _print_light_warnings(light: dict | None) -> None:
    """``--lighting shared``: the shared light's warnings (its images' own lights disagree), on stderr."""
    if not light:
        return
    from .batch.store import shared_light_warnings

    for w in shared_light_warnings(light):
        sys.stderr.write(f"warning: {term_safe(w)}\n")


def _cmd_white_balance(args) -> int:
    input_file(args.file)
    output_file(args.out)
    args.format = format_for(args.out, args.format)
    opts = _options(args)
    max_pixels, est_pixels = _limits()
    task = jobs.ItemTask(src=args.file, out=os.path.abspath(args.out), name=os.path.basename(args.file),
                         options=opts, max_pixels=max_pixels, estimation_pixels=est_pixels, threads=None,
                         exactly_once=False)
    res = jobs.process_item(task)
    res["name"] = task.name
    if res["status"] == "done" and (args.xmp or args.xmp_dir):
        target = sidecars.sidecar_path(args.file, args.xmp_name)
        if args.xmp_dir:
            os.makedirs(args.xmp_dir, exist_ok=True)
            target = os.path.join(args.xmp_dir, os.path.basename(target))
        fallback = None if args.xmp_dir else os.path.dirname(os.path.abspath(args.out))
        sc = sidecars._sidecar_job(args.file, res["illuminant"], opts, target, fallback, args.xmp_overwrite, _settings())
        if sc.get("error"):
            res["status"] = "failed"
            res["error"] = f"xmp: {sc['error']}"
        else:
            if sc.get("xmp"):
                res["xmp"] = sc["xmp"]
                if not args.quiet:
                    print(f"XMP sidecar: {term_safe(sc['xmp'])} (Temperature {sc['temperature']:.0f} K, "
                          f"Tint {sc['tint']:+.0f})")
            res.update({k: sc[k] for k in ("dng", "dng_kept", "dng_error") if sc.get(k)})
            # a DNG copy not written is said even with --quiet (on stderr, as a batch's notes are)
            if sc.get("dng_error") or (not args.quiet and (sc.get("dng") or sc.get("dng_kept"))):
                print(term_safe(sidecars.dng_copy_message(sc)), file=sys.stderr if sc.get("dng_error") else sys.stdout)
            if sc.get("note"):
                res["note"] = sc["note"]
    _summary([res], sys.stdout, args.quiet)
    return 0 if res["status"] == "done" else 1


def sidecar_path(raw: str, name: str = "stem") -> str:
    """:func:`service.sidecars.sidecar_path` (importing it costs ``--help`` nothing)."""
    return sidecars.sidecar_path(raw, name)


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("wandell-recovery")
    except metadata.PackageNotFoundError:
        return "unknown (not installed)"


class _VersionAction(argparse.Action):
    """``--version``, looked up only when asked (``importlib.metadata`` costs
    about 0.06 s, paid by every command when the string was built up front)."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings=option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        print(f"wandell {_version()}")       # on stdout, as argparse's own version action
        parser.exit()


def _model_disk_cache() -> None:
    """Models read from disk instead of rebuilt in every command (issue 19:
    the light posterior's model took 0.5-4 s and 200 MB of a fresh
    process; :func:`recovery.bayes.disk_cache_dir`, ``WANDELL_MODEL_CACHE_DIR``).
    Through the environment, so that batch workers inherit it and a command
    that never needs the model does not import it."""
    os.environ.setdefault("WANDELL_MODEL_CACHE", "1")


def _cmd_batches(args) -> int:
    """``wandell batches``: the batches the server keeps under
    ``WANDELL_DATA_DIR`` (default ``~/.cache/wandell``), and their removal
    (the same as ``DELETE /v1/batches/{id}?remove=true`` of a settled batch)."""
    import datetime

    data_dir = os.environ.get("WANDELL_DATA_DIR") or jobs.default_data_dir()
    if not os.path.exists(os.path.join(data_dir, "jobs.sqlite")):
        print(f"no batches under {data_dir}")
        return 0
    store = jobs.JobStore(data_dir)
    ids = list(args.remove)
    if args.older_than is not None:
        if not args.older_than >= 0:
            raise ServiceError(422, "invalid_parameter", f"--older-than: a number of days >= 0, not {args.older_than}")
        ids += store.expired_batches(args.older_than * 86400.0)
    rc = 0
    for bid in dict.fromkeys(ids):
        if store.batch(bid) is None:
            print(f"error: not_found: no batch {bid!r} under {data_dir}", file=sys.stderr)
            rc = 1
            continue
        freed = store.delete_batch(bid)
        if freed is None:
            print(f"error: batch_running: {bid} is still queued or running: cancel it first "
                  f"(POST /v1/batches/{bid}/cancel)", file=sys.stderr)
            rc = 1
        else:
            print(f"removed {bid} ({freed / 1e6:.1f} MB)")
    if ids:
        return rc
    rows = store.summaries()
    print(f"{len(rows)} batches under {data_dir}, {sum(r['bytes'] for r in rows) / 1e6:.1f} MB")
    for r in rows:
        when = datetime.datetime.fromtimestamp(r["created"]).strftime("%Y-%m-%d %H:%M")
        c = r["counts"]
        print(f"{r['id']}  {when}  {r['status']:<9}  {c['done']}/{c['total']} done  {r['bytes'] / 1e6:9.1f} MB")
    return 0


def main(argv=None) -> int:
    ap = _ArgumentParser(prog="wandell", description="White balance and illuminant estimation of RAW "
                                 "files (Wandell 1985; Maloney & Wandell)")
    ap.add_argument("--version", action=_VersionAction, help="show the installed version and exit")
    sub = ap.add_subparsers(dest="command", required=True)
    b = sub.add_parser("batch", help="white-balance every RAW of IN_DIR into OUT_DIR (resumable)")
    b.add_argument("in_dir")
    b.add_argument("out_dir")
    _add_options(b, True)
    a = sub.add_parser("analyze", help="estimate the light of one file (JSON on stdout)")
    a.add_argument("file")
    _add_options(a, None)
    s = sub.add_parser("surfaces", help="surface reflectances at points, rectangles or a grid of one file, "
                                        "with their bands (JSON or CSV on stdout)")
    s.add_argument("file")
    _add_options(s, None)
    add_options(s, REGIONS, describe={"points": "JSON [[row, col], ...] in full-resolution pixels",
                                      "metamers": "also each surface's metamer set (at most 64 surfaces, about "
                                                  "0.1 s each)"})
    w = sub.add_parser("white-balance", help="one corrected image")
    w.add_argument("file")
    w.add_argument("out")
    _add_options(w, False)
    k = sub.add_parser("batches", help="list the server's stored batches (WANDELL_DATA_DIR) or remove them")
    k.add_argument("--remove", nargs="+", metavar="ID", default=[], help="remove these batches (files and all); "
                   "a batch still running is refused")
    k.add_argument("--older-than", type=float, metavar="DAYS", help="remove every finished or cancelled batch "
                   "that finished more than DAYS days ago")
    out, err = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _SafeStream(out), _SafeStream(err)  # also what libraries and warnings print
    try:
        args = ap.parse_args(argv)
        if getattr(args, "xmp_name", "stem") not in XMP_NAMES:   # a CLI-only option: no model checks it
            raise ServiceError(422, "invalid_parameter", f"--xmp-name {args.xmp_name!r} unknown; accepted: "
                               + ", ".join(XMP_NAMES))
        _model_disk_cache()
        args.argv = sys.argv[1:] if argv is None else list(argv)
        if args.command == "batch":
            return _cmd_batch(args)
        if args.command == "analyze":
            from .cli_one import cmd_analyze

            return cmd_analyze(args)
        if args.command == "batches":
            return _cmd_batches(args)
        if args.command == "surfaces":
            from .cli_one import cmd_surfaces

            return cmd_surfaces(args)
        return _cmd_white_balance(args)
    except KeyboardInterrupt:  # Ctrl-C outside a batch's items (or while printing): no traceback
        sys.stderr.write("\ninterrupted\n")
        return 130
    except ServiceError as e:
        print(f"error: {e.code}: {term_safe(e.detail)}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"error: {term_safe(e)}", file=sys.stderr)
        return 1
    finally:
        sys.stdout, sys.stderr = out, err


if __name__ == "__main__":
    sys.exit(main())
