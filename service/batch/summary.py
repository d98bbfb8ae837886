"""A batch's summary for its user: ``batch.json`` in a CLI batch's output
folder and in an API batch's zip (issue 27, item 4: the photographs whose
light is likely wrong come first).

Every item's name, status, output file, light (camera RGB, CCT, confidence,
``low_confidence``) or error; the items whose estimate is flagged low
confidence first (each keeps its ``index``, its place in the batch), the
rest in their order; ``low_confidence`` names them. What the confidence
means and how the flag is set: ``docs/confidence.md``.

Not the server's own manifest of a batch (also named ``batch.json``, in its
folder under the data directory, written before any estimate exists and in
upload order: what a restart rebuilds the batch from).
"""

from __future__ import annotations

import json
import os

#: The name of the summary file.
SUMMARY = "batch.json"

#: The light's fields a summary keeps (those of ``GET /v1/batches/{id}``).
LIGHT_FIELDS = ("camera_rgb", "wb_multipliers", "cct", "duv", "method", "camera", "warnings", "confidence",
                "low_confidence")


def flagged(item: dict) -> bool:
    """Whether ``item``'s light is flagged low confidence."""
    return bool((item.get("illuminant") or {}).get("low_confidence"))


def flagged_first(items: list[dict]) -> list[dict]:
    """``items`` with the flagged ones first, each group in its order (a
    stable sort)."""
    return sorted(items, key=lambda it: not flagged(it))


def cli_summary(tasks, rows: dict, options, in_dir: str, out_dir: str, interrupted: bool = False) -> dict:
    """The summary of a ``wandell batch`` run: ``tasks`` (its
    :class:`~service.batch.items.ItemTask` list, in order) and ``rows`` (name
    -> the row :func:`service.cli.run_batch` made: status, illuminant,
    error, seconds, note, xmp)."""
    items = []
    for i, t in enumerate(tasks):
        r = rows[t.name]
        it = {"index": i, "name": t.name, "status": r["status"],
              "output": os.path.relpath(t.out, out_dir) if r["status"] in ("done", "skipped") else None}
        if r.get("illuminant"):
            it["illuminant"] = {k: r["illuminant"].get(k) for k in LIGHT_FIELDS if k in r["illuminant"]}
        for k in ("error", "note", "seconds", "xmp"):
            if r.get(k) is not None:
                it[k] = r[k]
        items.append(it)
    items = flagged_first(items)
    counts = {s: sum(it["status"] == s for it in items) for s in ("done", "skipped", "failed", "stopped")}
    return {"input_folder": os.path.abspath(in_dir), "output_folder": os.path.abspath(out_dir),
            "interrupted": interrupted, "options": json.loads(options.to_json()),
            "counts": dict(counts, total=len(items)),
            "low_confidence": [it["name"] for it in items if flagged(it)], "items": items}


#: The keys every summary :func:`cli_summary` writes has: a ``batch.json`` without them is not ours.
SUMMARY_KEYS = ("input_folder", "output_folder", "interrupted", "options", "counts", "low_confidence", "items")

#: A ``batch.json`` larger than this is not read to see whether it is a summary (a batch of the
#: largest size, 1000s of items, writes a few MB).
MAX_SUMMARY_BYTES = 256 << 20


class SummaryKept(Exception):
    """``OUT_DIR/batch.json`` is a file a batch did not write, or read-only:
    it is kept and the summary is not written (the message says why and
    what to do)."""


def is_cli_summary(path: str) -> bool:
    """Whether the file at ``path`` is a summary a ``wandell batch`` wrote
    (a JSON object with every key of :data:`SUMMARY_KEYS`)."""
    try:
        if os.path.getsize(path) > MAX_SUMMARY_BYTES:
            return False
        with open(path, "rb") as f:
            doc = json.loads(f.read())
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and all(k in doc for k in SUMMARY_KEYS)


def kept_summary(path: str, force: bool) -> str | None:
    """Why ``OUT_DIR/batch.json`` is kept instead of replaced by the
    summary, or ``None``: the rule of the outputs
    (:func:`service.cli_paths.kept_output`): a folder or a read-only file is
    kept even with ``--force``, a file no batch wrote unless ``--force``;
    a summary of an earlier run is replaced. It replaced a user's
    ``batch.json`` without a word (probe round 8b)."""
    from ..cli_paths import keep_reason

    why = keep_reason(path, force or (os.path.isfile(path) and is_cli_summary(path)), force)
    if why == "folder":
        return f"{path!r} is a folder; it is kept and the batch's summary is not written"
    if why == "read_only":
        return (f"{path!r} exists and is read-only; it is kept and the batch's summary is not written: make it "
                "writable or remove it, then run again")
    if why == "not_ours":
        return (f"{path!r} exists and was not written by a batch; it is kept and the batch's summary is not "
                "written: move it, or --force to replace it")
    return None


def write_cli_summary(tasks, rows: dict, options, in_dir: str, out_dir: str, interrupted: bool = False,
                      force: bool = False) -> str:
    """:func:`cli_summary` written to ``OUT_DIR/batch.json`` (whole or not at
    all: a temporary file renamed into place); returns its path. Raises
    :class:`SummaryKept` when a file there must be kept (:func:`kept_summary`)."""
    from ..jsonsafe import clean
    from .items import atomic_write, write_text

    path = os.path.join(out_dir, SUMMARY)
    kept = kept_summary(path, force)
    if kept is not None:
        raise SummaryKept(kept)
    doc = clean(cli_summary(tasks, rows, options, in_dir, out_dir, interrupted))
    atomic_write(path, lambda p: write_text(p, json.dumps(doc, indent=1) + "\n"), durable=False)
    return path
