"""The XMP sidecars of a ``wandell batch --xmp`` run's finished images
(:func:`service.cli.run_batch`): each submitted as soon as its image is
finished, so a Ctrl-C leaves every finished image with its sidecar (those
the stop interrupted are made here, in the CLI's process:
:func:`finish_sidecars`). The sidecar itself is :func:`service.sidecars._sidecar_job`.
"""

from __future__ import annotations

import contextlib
import os


def _sidecars():
    from .. import sidecars   # here: the CLI's --help imports none of it

    return sidecars


def preload() -> None:
    """Load this module's and :mod:`service.sidecars`' code now. The CLI
    imports both lazily (its ``--help`` costs nothing); their first use is
    when the first image finishes, and a Ctrl-C landing in that import (the
    CLI's handler raises KeyboardInterrupt in the main thread) left the lazy
    module half-made, so the sidecars of the finished images, made after the
    stop, failed with an AttributeError: seen in a full test run under load."""
    _sidecars().sidecar_path        # an attribute access runs a lazy module's code


def sidecar_args(t, r, options, out_dir: str, xmp: dict, settings) -> tuple:
    """The arguments of :func:`service.sidecars._sidecar_job` for task ``t`` (row ``r``)."""
    rel_dir = os.path.dirname(t.name)
    target = (_sidecars().sidecar_path(os.path.join(xmp["folder"], t.name), xmp["name"]) if xmp.get("folder")
              else _sidecars().sidecar_path(t.src, xmp["name"]))
    fallback = None if xmp.get("folder") else os.path.join(out_dir, rel_dir)
    if xmp.get("folder"):
        os.makedirs(os.path.dirname(target), exist_ok=True)      # --xmp DIR: the relative tree kept
    return (t.src, r["illuminant"], options, target, fallback, bool(xmp.get("overwrite")), settings)


def submit_sidecar(t, r, options, out_dir: str, executor, xmp: dict, settings):
    """A finished image's sidecar, on the executor (or here when there is none)."""
    args = sidecar_args(t, r, options, out_dir, xmp, settings)
    if executor is None:            # every item already finished: no pool was started
        from concurrent.futures import Future

        f: Future = Future()
        try:
            f.set_result(_sidecars()._sidecar_job(*args))
        except Exception as e:  # noqa: BLE001 - reported below as a worker's would be
            f.set_exception(e)
        return f
    return executor.submit(_sidecars()._sidecar_job, *args)


def apply_sidecar(r: dict, res: dict) -> None:
    """A sidecar job's answer into the item's row: the sidecar, a kept one,
    a DNG's copy with the white balance inside (issue 30), and the notes."""
    if res.get("xmp"):
        r["xmp"] = res["xmp"]
    if res.get("kept"):
        r["xmp_kept"] = res["kept"]
    for key in ("dng", "dng_kept"):
        if res.get(key):
            r[key] = res[key]
    notes = [res.get("note"), res.get("dng_error")]
    if res.get("dng_kept"):
        notes.append(f"DNG copy {res['dng_kept']} exists: kept as it is (--xmp-overwrite replaces it)")
    if any(notes):
        r["note"] = "; ".join(n for n in (r.get("note"), *notes) if n)


def finish_sidecars(tasks, rows, options, out_dir: str, xmp: dict, xmp_jobs: dict, settings) -> None:
    """After a Ctrl-C (the pool ended): the sidecars that finished are
    recorded, and every finished image whose sidecar was not made (its job
    dropped with the pool) gets it here, in this process."""
    for t in tasks:
        r = rows[t.name]
        if r["status"] not in ("done", "skipped") or not r.get("illuminant") or r.get("xmp") or r.get("xmp_kept"):
            continue
        f = xmp_jobs.get(t.name)
        res = None
        if f is not None and f.done() and not f.cancelled():
            with contextlib.suppress(BaseException):
                res = f.result()
        if res is None:
            try:
                res = _sidecars()._sidecar_job(*sidecar_args(t, r, options, out_dir, xmp, settings))
            except Exception as e:  # noqa: BLE001 - the image is done; say why its sidecar is not
                res = {"xmp": None, "note": f"no XMP sidecar: {type(e).__name__}: {e}"}
        apply_sidecar(r, res)


def batch_sidecars(tasks, rows, options, out_dir: str, executor, xmp: dict, xmp_jobs: dict | None, settings) -> None:
    """The sidecars of a batch's finished items (:func:`service.cli.run_batch`'s ``xmp``):
    those already submitted (``xmp_jobs``, name -> future) and the others."""
    xmp_jobs = xmp_jobs if xmp_jobs is not None else {}
    for t in tasks:
        r = rows[t.name]
        if r["status"] not in ("done", "skipped") or not r.get("illuminant") or t.name in xmp_jobs:
            continue
        xmp_jobs[t.name] = submit_sidecar(t, r, options, out_dir, executor, xmp, settings)
    for t in tasks:
        f = xmp_jobs.get(t.name)
        if f is None:
            continue
        try:
            res = f.result()
        except Exception as e:  # noqa: BLE001 - a worker lost: the image is done, say why the sidecar is not
            res = {"xmp": None, "note": f"no XMP sidecar: {type(e).__name__}: {e}"}
        apply_sidecar(rows[t.name], res)


