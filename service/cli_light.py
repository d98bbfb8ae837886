"""``wandell batch --lighting shared``: one light from all of a folder's
images (moved out of :mod:`service.cli`, which is at its line limit).

Each image's light evidence is estimated on the pool; an image whose
estimation kills its worker (a decoder crash, the OOM killer) breaks the
pool for the images in flight with it, which are then estimated again one at
a time, each alone (:func:`service.batch.executors.run_alone`): only the
culprit fails, as ``worker_killed``, and the light is made from the others,
as the server's runner does (:class:`service.batch.runner.BatchRunner`).
"""

from __future__ import annotations

import functools
import json
import os

from .errors import ServiceError


def shared_light_of(tasks, options, out_dir, executor, rows, count, force: bool = False,
                    sample_fn=None) -> dict | None:
    """One light from all input images (finished ones included, so a resumed
    run corrects with the same light), kept in ``OUT_DIR/.wandell``."""
    path = os.path.join(out_dir, ".wandell", "shared-light.json")
    key = {"inputs": [t.name for t in tasks], "options": json.loads(options.to_json())}
    if os.path.exists(path) and not force:
        with open(path) as f:
            saved = json.load(f)
        if saved.get("key") == key:
            return saved["light"]
    from concurrent.futures.process import BrokenProcessPool

    from .batch.executors import run_alone

    fn = sample_fn or _jobs().estimation_sample
    futs = [(t, executor.submit(fn, t)) for t in tasks]
    samples = []
    for t, f in futs:
        try:
            s = f.result()
        except BrokenProcessPool:   # an image killed the pool's worker: each in flight again, alone
            s, deaths = run_alone(fn, t)
            s = s or {"status": "failed", "error": f"worker_killed: estimating this image's light ended its "
                      f"worker process {deaths} times when it ran alone"}
        if s["status"] != "ok":
            if rows[t.name]["status"] == "pending":
                rows[t.name].update(status="failed", error=s["error"])
                count["failed"] += 1
            continue
        samples.append(s)
    if not samples:
        return None
    cam = samples[0]["camera"].name
    if any(s["camera"].name != cam for s in samples):
        raise ServiceError(422, "camera_mismatch", "shared lighting pools images of one camera; this folder "
                           f"mixes {sorted({s['camera'].name for s in samples})}")
    if getattr(executor, "broken", None):
        light = run_alone(functools.partial(_jobs().shared_light, options=options), samples)[0]
    else:
        light = executor.submit(_jobs().shared_light, samples, options).result()
    os.makedirs(os.path.dirname(path), exist_ok=True)
    _jobs().atomic_write(path, lambda p: _jobs().write_text(p, json.dumps({"key": key, "light": light})))
    return light


def _jobs():
    from . import jobs

    return jobs
