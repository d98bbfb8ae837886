"""The ``wandell`` command's checks of its path arguments, before any work
(moved out of :mod:`service.cli`, which is at its line limit).

A missing FILE or IN_DIR, a folder given as FILE, a file given as IN_DIR, or
an output name whose extension the command cannot write are usage errors
(exit 2) in words, raised as :class:`~service.errors.ServiceError`, not a
Python traceback or an errno. Only :mod:`os` is imported: ``wandell --help``
stays light.
"""

from __future__ import annotations

import os

from .errors import ServiceError

#: Output file extensions and the formats they mean (white-balance OUT).
EXTENSION_FORMATS = {".tif": ("tiff",), ".tiff": ("tiff",), ".png": ("png", "png16"), ".jpg": ("jpeg", "jpg"),
                     ".jpeg": ("jpeg", "jpg")}


def format_for(out: str, given: str | None) -> str:
    """The output format of ``white-balance OUT``: from OUT's extension;
    ``--format`` must agree with it (png16 is the 16-bit choice for .png);
    a name without an extension needs ``--format``."""
    ext = os.path.splitext(out)[1].lower()
    if not ext:
        if given is None:
            raise ServiceError(422, "invalid_parameter", f"{out!r} has no extension: name it .tif, .png or "
                               ".jpg, or give --format")
        return given
    if ext not in EXTENSION_FORMATS:
        raise ServiceError(422, "invalid_parameter", f"cannot write {ext!r} files: name the output .tif/.tiff "
                           "(16-bit TIFF), .png (8-bit; --format png16 for 16-bit) or .jpg/.jpeg")
    allowed = EXTENSION_FORMATS[ext]
    if given is not None and given not in allowed:
        raise ServiceError(422, "format_mismatch", f"--format {given} disagrees with the output name {out!r} "
                           f"({ext} is {' or '.join(allowed)}): change one of them")
    return given or allowed[0]


def input_file(path: str) -> str:
    """The FILE argument of ``analyze`` and ``white-balance``: a missing
    file, a folder or an unreadable file is a usage error."""
    if os.path.isdir(path):
        raise ServiceError(422, "not_a_file", f"{path!r} is a folder; give one file, or use 'wandell batch "
                           f"{path} OUT_DIR' for every RAW in it")
    if not os.path.exists(path):
        raise ServiceError(422, "file_not_found", f"{path!r} does not exist (current folder {os.getcwd()!r})")
    if not os.access(path, os.R_OK):
        raise ServiceError(422, "file_not_readable", f"{path!r} cannot be read (permission denied)")
    return path


def input_folder(path: str) -> str:
    """The IN_DIR argument of ``batch``: a file there is named as a file
    (with the command for one file, ``wandell white-balance``), not as a
    folder that does not exist (probe round 4); a missing path says so."""
    if os.path.isfile(path) or (os.path.exists(path) and not os.path.isdir(path)):
        raise ServiceError(422, "not_a_folder", f"input folder {path!r} is a file, not a folder; give the folder "
                           f"that holds the RAWs, or use 'wandell white-balance {path} OUT' for this one file")
    if not os.path.isdir(path):
        raise ServiceError(422, "folder_not_found", f"input folder {path!r} does not exist "
                           f"(current folder {os.getcwd()!r})")
    return path


#: The suffix of the DNG copy ``--xmp`` writes beside a RAW (:func:`service.sidecars.dng_copy_path`).
DNG_COPY_SUFFIX = ".wandell.dng"


def dng_copy_name(stem: str) -> str:
    """The DNG copy's name for a RAW named ``stem`` + extension:
    ``stem.wandell.dng``, the stem cut (on a character boundary) so the
    name fits the length a batch's outputs are cut to
    (:data:`service.batch.store.DISK_NAME_BYTES` - 12 bytes, room for its
    temporary within NAME_MAX; probe round 9b: a 255-byte RAW's copy was
    "File name too long"), the suffix kept.

    >>> dng_copy_name("IMG_0001")
    'IMG_0001.wandell.dng'
    >>> n = dng_copy_name("a" + "é" * 127); len(n.encode()), n.endswith(".wandell.dng")
    (187, True)
    """
    from .batch.store import DISK_NAME_BYTES

    room = DISK_NAME_BYTES - 12 - len(DNG_COPY_SUFFIX)
    return stem.encode("utf-8")[:room].decode("utf-8", "ignore") + DNG_COPY_SUFFIX


def dng_copies(names, raw_suffixes) -> set:
    """The names among ``names`` (one folder's entries) that are the DNG
    copies ``--xmp`` writes beside a RAW, ``IMG_0001.wandell.dng`` beside
    ``IMG_0001.dng`` or ``IMG_0001.nef``: a rerun of ``wandell batch IN OUT
    --xmp`` took them as new photographs (an output and a copy of the copy
    each time). They are left out silently, as the sidecars are (the
    output of a RAW processed here, not a photograph the batch skipped). A
    ``.wandell.dng`` whose original is not in the folder is not one of them
    (it is processed).

    >>> sorted(dng_copies(["a.dng", "a.wandell.dng", "b.wandell.dng", "c.NEF", "c.wandell.dng"], (".dng", ".nef")))
    ['a.wandell.dng', 'c.wandell.dng']

    A long RAW's copy has its cut name (:func:`dng_copy_name`).
    """
    copies = {dng_copy_name(os.path.splitext(n)[0]) for n in names if n.lower().endswith(raw_suffixes)}
    return {n for n in names if n in copies}


def _through_a_file(path: str) -> str | None:
    """The nearest existing path above ``path`` (itself included) when it is
    not a folder (so nothing can be made at ``path``), else None."""
    p = os.path.abspath(path)
    while not os.path.exists(p):
        parent = os.path.dirname(p)
        if parent == p:
            return None
        p = parent
    return None if os.path.isdir(p) else p


def output_folder(path: str) -> str:
    """The OUT_DIR argument of ``batch``: an existing file, or a path through
    one, is a usage error in words (was Python's ``[Errno 17] File exists``,
    exit 1: probe round 7)."""
    blocker = _through_a_file(path)
    if blocker is not None:
        raise ServiceError(422, "not_a_folder", f"output folder {path!r} cannot be made: {blocker!r} is a file, "
                           "not a folder; give a folder (it is made if missing)")
    return path


def output_file(path: str) -> str:
    """The OUT argument of ``white-balance``: an existing folder, or a path
    through a file, is a usage error in words (was ``IsADirectoryError:
    [Errno 21]`` as a failed file: probe round 7)."""
    if os.path.isdir(path):
        raise ServiceError(422, "not_a_file", f"output {path!r} is a folder; name the file to write, e.g. "
                           f"{os.path.join(path, 'IMG_0001.tif')!r}")
    blocker = _through_a_file(os.path.dirname(os.path.abspath(path)))
    if blocker is not None:
        raise ServiceError(422, "not_a_folder", f"output {path!r} cannot be written: {blocker!r} is a file, "
                           "not a folder")
    if os.path.isfile(path) and not os.stat(path).st_mode & 0o222:
        # the output is written beside and renamed over: a file made read-only was replaced (round 7)
        raise ServiceError(422, "output_read_only", f"output {path!r} exists and is read-only; it is kept: "
                           "make it writable (chmod u+w) or remove it to replace it, or name another output")
    return path


def kept_output(out: str, finished: bool, force: bool, src: str | None = None) -> str | None:
    """Why ``wandell batch`` keeps the file at an output's path instead of
    writing over it (the item then fails with these words), or ``None``.

    An output is written beside and renamed over, which ignores the file's
    mode and whose file it was: ``batch --force`` replaced an output the user
    had made read-only, and any run replaced a file of the user's own that
    had an output's name (no record of ours in ``.wandell``), both without a
    word (probe round 8). A read-only file is kept even with ``--force`` (as
    ``cp`` would not write it); a file not written by a batch is replaced only
    with ``--force``; a finished output of ours, with ``--force``. An output
    that is the item's input ``src`` (``wandell batch IN IN --format dng``)
    says so first (``output_is_input``, as the item itself would)."""
    if not os.path.lexists(out):
        return None
    try:
        same = src is not None and os.path.samefile(src, out)
    except OSError:
        same = False
    if same:
        return (f"output_is_input: the result of {os.path.basename(src)!r} would be written over the file itself "
                f"({out}); the original is only ever read: choose another output folder or format")
    why = keep_reason(out, finished, force)
    if why == "folder":
        return f"output_exists: {out!r} is a folder; it is kept: move it or choose another output folder"
    if why == "read_only":
        return (f"output_read_only: {out!r} exists and is read-only; it is kept: make it writable (chmod u+w) "
                "or remove it, then run again")
    if why == "not_ours":
        return (f"output_exists: {out!r} exists and was not written by a batch (no record in .wandell); it is "
                "kept: move it, choose another output folder, or --force to replace it")
    return None


def keep_reason(path: str, ours: bool, force: bool) -> str | None:
    """The rule a batch's outputs and its summary share for a file already
    at their path: ``"folder"`` and ``"read_only"`` are kept even with
    ``--force``, ``"not_ours"`` (a file no batch wrote) unless ``--force``;
    ``None``: nothing there, or ours to replace."""
    if not os.path.lexists(path):
        return None
    if os.path.isdir(path) and not os.path.islink(path):
        return "folder"
    if os.path.isfile(path) and not os.stat(path).st_mode & 0o222:
        return "read_only"
    if not ours and not force:
        return "not_ours"
    return None


def own_outputs(folder: str, names) -> set:
    """The names among ``names`` (``folder``'s entries) that are outputs a
    batch wrote there: each has its record ``.wandell/NAME.json`` beside it
    (:func:`service.batch.items.meta_path`). ``wandell batch DIR DIR`` puts
    the outputs beside the RAWs, and a rerun took them for new photographs
    (an 8-bit PNG failed, a 16-bit one was corrected again into ``NAME
    (2).png``: probe round 7); they are left out silently, as the sidecars
    are, and so is the batch's summary ``batch.json`` there. A file of the
    same kind without a record is a photograph."""
    records = os.path.join(folder, ".wandell")
    if not os.path.isdir(records):
        return set()
    return {n for n in names if n == "batch.json" or os.path.isfile(os.path.join(records, n + ".json"))}


def check_workers(workers: int, limit: int) -> int:
    """``--workers``: 0 (one per core) up to ``limit``
    (:func:`service.batch.executors.max_local_workers`); every worker is a
    process started at once, so 100,000 was 100,000 processes (probe round
    7), and a negative count was taken silently."""
    if not 0 <= workers <= limit:
        raise ServiceError(422, "invalid_parameter", f"--workers {workers}: give 0 (one per core) or a number of "
                           f"worker processes in 0..{limit} (at most 4 per core)")
    return workers
