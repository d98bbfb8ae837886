"""Service settings with embedded defaults (no file or server needed).

Every value can be overridden by an environment variable ``WANDELL_<NAME>``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache


@dataclass(frozen=True)
class Settings:
    host: str = "127.0.0.1"
    port: int = 8000
    max_upload_bytes: int = 200 * 1024 * 1024
    max_pixels: int = 120_000_000
    #: decode/estimate/encode jobs running at once (0 = one per CPU); the rest queue (service.workers)
    max_concurrent_work: int = 0
    #: RAW files are binned to at most this many pixels for estimation
    estimation_pixels: int = 1_000_000
    #: batch jobs (service.jobs): SQLite store, inputs and outputs live
    #: here; empty = the user cache dir ($XDG_CACHE_HOME or ~/.cache)/wandell
    data_dir: str = ""
    #: server-side root for folder batches; empty = folder mode refused
    batch_root: str = ""
    #: local pool workers (0 = one per core)
    batch_workers: int = 0
    max_batch_items: int = 1000
    max_concurrent_batches: int = 2
    #: Dask scheduler address (tcp://host:8786); empty = local process pool
    dask_scheduler: str = ""
    #: POST /v1/render refuses spectral data with more values (H x W x N) (413)
    max_render_values: int = 64_000_000
    #: POST /v1/surfaces answers at most this many points + rectangles + grid cells (413 too_many_regions)
    max_surface_regions: int = 10_000
    #: Host header names served besides the bound host, localhost and 127.0.0.1 (comma-separated; others: 400)
    allowed_hosts: str = ""
    #: origins (scheme://host:port) allowed to send POST/DELETE besides the page's own (comma-separated; others: 403)
    allowed_origins: str = ""
    #: seconds an idle connection is kept open (before and between requests)
    keep_alive_timeout: float = 5.0
    #: seconds a request body may go without sending a byte before it is cut off (408)
    body_timeout: float = 30.0
    #: seconds the uploaded inputs of a finished or cancelled batch are kept (results are kept)
    batch_input_retention: float = 24 * 3600.0


@lru_cache
def get_settings() -> Settings:
    """Settings from the environment, else the embedded defaults."""
    env = os.environ
    return Settings(
        host=env.get("WANDELL_HOST", Settings.host),
        port=int(env.get("WANDELL_PORT", Settings.port)),
        max_upload_bytes=int(env.get("WANDELL_MAX_UPLOAD_BYTES", Settings.max_upload_bytes)),
        max_pixels=int(env.get("WANDELL_MAX_PIXELS", Settings.max_pixels)),
        max_concurrent_work=int(env.get("WANDELL_MAX_CONCURRENT_WORK", Settings.max_concurrent_work)),
        estimation_pixels=int(env.get("WANDELL_ESTIMATION_PIXELS", Settings.estimation_pixels)),
        data_dir=env.get("WANDELL_DATA_DIR", Settings.data_dir),
        batch_root=env.get("WANDELL_BATCH_ROOT", Settings.batch_root),
        batch_workers=int(env.get("WANDELL_BATCH_WORKERS", Settings.batch_workers)),
        max_batch_items=int(env.get("WANDELL_MAX_BATCH_ITEMS", Settings.max_batch_items)),
        max_concurrent_batches=int(env.get("WANDELL_MAX_CONCURRENT_BATCHES", Settings.max_concurrent_batches)),
        dask_scheduler=env.get("WANDELL_DASK_SCHEDULER", Settings.dask_scheduler),
        max_render_values=int(env.get("WANDELL_MAX_RENDER_VALUES", Settings.max_render_values)),
        max_surface_regions=int(env.get("WANDELL_MAX_SURFACE_REGIONS", Settings.max_surface_regions)),
        allowed_hosts=env.get("WANDELL_ALLOWED_HOSTS", Settings.allowed_hosts),
        allowed_origins=env.get("WANDELL_ALLOWED_ORIGINS", Settings.allowed_origins),
        keep_alive_timeout=float(env.get("WANDELL_KEEP_ALIVE_TIMEOUT", Settings.keep_alive_timeout)),
        body_timeout=float(env.get("WANDELL_BODY_TIMEOUT", Settings.body_timeout)),
        batch_input_retention=float(env.get("WANDELL_BATCH_INPUT_RETENTION", Settings.batch_input_retention)),
    )
