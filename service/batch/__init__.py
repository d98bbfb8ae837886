"""Batch jobs: a SQLite job store, the per-item function, a runner on a local
process pool or a Dask cluster, resume after a crash (issue 6).

No FastAPI here (options are validated by :mod:`service.options`, errors are
:class:`~service.errors.ServiceError`): the HTTP router
(:mod:`service.routers.batches`) and the CLI (:mod:`service.cli`) both drive
this package (:mod:`service.jobs`, its former name, re-exports it).

Every item is the white-balance pipeline of ``POST /v1/white-balance``
(:func:`service.pipeline.analyze` and :func:`service.pipeline.render_corrected`)
(Wandell 1985, Fig. 6 and eq. 22-25/36: estimate the light, then one 3x3
matrix per pixel from camera RGB to the display). In ``shared`` lighting
mode one light is made for all the images of the batch, and every image is
corrected with it: each image's own estimate (as per-image mode makes it)
combined by :func:`shared_light`, their confidence-weighted mean. (Pooling
the pixels into one stacked image, as before issue 19, made the light
depend on the number and layout of the images: N copies of one image moved
it 0.8 degrees.)

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

One concept a module: :mod:`~service.batch.options` (a batch's validated
options), :mod:`~service.batch.items` (one item, exactly once),
:mod:`~service.batch.executors` (local pool or Dask),
:mod:`~service.batch.store` (the SQLite job store),
:mod:`~service.batch.runner` (the runner) and :mod:`~service.batch.xmp` (the
XMP sidecars of a CLI batch). What each fault (a stop, a killed worker, a lost
scheduler, a full disk, a locked or lost store) does to the items:
``docs/reliability.md``. Nothing is imported here, so a
worker loading :mod:`~service.batch.items` loads no more than it needs.
"""
