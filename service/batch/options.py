"""The options of a batch: :func:`batch_options` validates them into a
:class:`~service.schemas.options.BatchOptions` (declared in :mod:`service.schemas.fields`).
"""

from __future__ import annotations

from ..errors import ServiceError
from ..options import check_camera_name
from ..schemas.options import LIGHTING, BatchOptions  # noqa: F401 (the options model, named here too)


def batch_options(**kw) -> BatchOptions:
    """Validated :class:`BatchOptions` (declared in :mod:`service.schemas.options`,
    with the checks of the white-balance endpoint, and a camera name checked
    now since the batch runs later); :class:`~service.errors.ServiceError`
    (422) naming the bad option and what is accepted. ``None`` and ``""``
    mean the default."""
    kw = {k: v for k, v in kw.items() if v is not None and v != ""}
    unknown = set(kw) - set(BatchOptions.model_fields)
    if unknown:
        raise ServiceError(422, "invalid_parameter", f"unknown options {sorted(unknown)}")
    opts = BatchOptions(**kw)
    check_camera_name(opts.camera)
    return opts
