"""Former name of :mod:`service.batch` (batch jobs: options, items, executors, the SQLite
store, the runner), kept for the callers that import it: every name of the modules it was
split into, re-exported.
"""

from __future__ import annotations

from .batch.executors import (  # noqa: F401
    DaskExecutor, LocalExecutor, _dask_call, _sigint_ignored, default_data_dir, default_workers,
    make_executor, max_local_workers,
)
from .batch.items import (  # noqa: F401
    ItemCancelled, ItemTask, RAW_SUFFIXES, SHARED_SPREAD_WARN_DEG, THREAD_ENV, _PARTS, _TEMPORARY,
    _check_cancel, _clean, _error_text, _estimate_from_json, _estimate_json, _exit_on_term, _item_lock,
    _open, _pool_worker_init, atomic_write, open_under, read_source, remove_stale_lock, estimation_sample, is_finished, is_temporary, limit_threads,
    meta_path, pool_images, process_item, remove_stale_temporaries, shared_light, write_text,
)
from .batch.options import (  # noqa: F401
    BatchOptions, LIGHTING, batch_options,
)
from .batch.runner import (  # noqa: F401
    BatchRunner, RunnerConfig, folder_sources, scan_folder,
)
from .batch.store import (  # noqa: F401
    BUSY_TIMEOUT_S, DISK_NAME_BYTES, JOURNAL, JobStore, MANIFEST, MAX_ATTEMPTS, MAX_NAME_BYTES, _INDEX_TEXT, _SCHEMA, _read_sidecar,
    clip_name, safe_name, unique,
)
