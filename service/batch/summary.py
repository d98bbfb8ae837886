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


def write_cli_summary(tasks, rows: dict, options, in_dir: str, out_dir: str, interrupted: bool = False) -> str:
    """:func:`cli_summary` written to ``OUT_DIR/batch.json`` (whole or not at
    all: a temporary file renamed into place); returns its path."""
    from ..jsonsafe import clean
    from .items import atomic_write, write_text

    path = os.path.join(out_dir, SUMMARY)
    doc = clean(cli_summary(tasks, rows, options, in_dir, out_dir, interrupted))
    atomic_write(path, lambda p: write_text(p, json.dumps(doc, indent=1) + "\n"), durable=False)
    return path
