"""Service settings with embedded defaults (no file or server needed).

Every value can be overridden by an environment variable ``WANDELL_<NAME>``
(pydantic-settings: values are parsed and validated, counts and sizes at
least 1 or 0 where 0 means "automatic", time-outs positive and finite; a
malformed or out-of-range one stops the service, or the CLI, with a message
naming it: :func:`settings_problem`). Routers receive the settings with
``Depends(get_settings)``; the ASGI middlewares, the work limiter and the
CLI, which have no request dependencies, call :func:`get_settings`.

Analysis resolution is one setting, ``estimation_pixels``
(``WANDELL_ESTIMATION_PIXELS``): a RAW is binned to at most that many pixels,
the full resolution of the analysis (``quality=accurate``); the ``quality``
presets and the default estimate block-average that image further
(:func:`recovery.analysis_pixels`, :mod:`service.pipeline`).
"""

from __future__ import annotations

from functools import lru_cache

from pydantic import Field, ValidationError
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="WANDELL_", frozen=True, extra="ignore")

    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    max_upload_bytes: int = Field(200 * 1024 * 1024, ge=1)
    max_pixels: int = Field(120_000_000, ge=1)
    #: decode/estimate/encode jobs running at once (0 = one per CPU); the rest queue (service.workers)
    max_concurrent_work: int = Field(0, ge=0)
    #: the analysis resolution: RAW files are binned (2x2 CFA cells, then area-averaged) to at most
    #: this many pixels for estimation; quality=accurate analyses all of them
    estimation_pixels: int = Field(1_000_000, ge=1)
    #: batch jobs (service.jobs): SQLite store, inputs and outputs live
    #: here; empty = the user cache dir ($XDG_CACHE_HOME or ~/.cache)/wandell
    data_dir: str = ""
    #: server-side root for folder batches; empty = folder mode refused
    batch_root: str = ""
    #: local pool workers (0 = one per core)
    batch_workers: int = Field(0, ge=0)
    max_batch_items: int = Field(1000, ge=1)
    max_concurrent_batches: int = Field(2, ge=1)
    #: Dask scheduler address (tcp://host:8786); empty = local process pool
    dask_scheduler: str = ""
    #: POST /v1/render refuses spectral data with more values (H x W x N) (413)
    max_render_values: int = Field(64_000_000, ge=1)
    #: POST /v1/surfaces answers at most this many points + rectangles + grid cells (413 too_many_regions)
    max_surface_regions: int = Field(10_000, ge=1)
    #: method=maloney-wandell&spatial=true makes at most this many regions: the default region side grows to
    #: fit, an explicit region_size past it is a 413 too_many_regions (about 2 s per 1,000 regions, docs/limits.md);
    #: the light posterior's regions of an explicit region_size too (same 413)
    max_light_map_regions: int = Field(4096, ge=1)
    #: Host header names served besides the bound host, localhost and 127.0.0.1 (comma-separated; others: 400)
    allowed_hosts: str = ""
    #: origins (scheme://host:port) allowed to send POST/DELETE besides the page's own (comma-separated; others: 403)
    allowed_origins: str = ""
    #: seconds an idle connection is kept open (before and between requests)
    keep_alive_timeout: float = Field(5.0, gt=0, allow_inf_nan=False)
    #: seconds a request body may go without sending a byte before it is cut off (408)
    body_timeout: float = Field(30.0, gt=0, allow_inf_nan=False)
    #: seconds a whole request body may take, however it trickles (408 body_deadline; 0 = no limit)
    body_deadline: float = Field(600.0, ge=0, allow_inf_nan=False)
    #: seconds each piece (<= 1 MiB) of an answer may wait for the client to take it; then the answer is
    #: given up, its temporary file removed and the connection closed (0 = no limit)
    send_timeout: float = Field(60.0, ge=0, allow_inf_nan=False)
    #: open connections at once; more are answered 503 too_many_connections and closed at once
    #: (0 = from the process's file-descriptor limit: (RLIMIT_NOFILE - 100) / 2)
    max_connections: int = Field(0, ge=0)
    #: seconds the uploaded inputs of a finished or cancelled batch are kept (results are kept; negative: for ever)
    batch_input_retention: float = Field(24 * 3600.0, allow_inf_nan=False)
    #: seconds a finished or cancelled batch is kept with its results before it is deleted (negative: for ever)
    batch_result_retention: float = Field(7 * 24 * 3600.0, allow_inf_nan=False)


@lru_cache
def get_settings() -> Settings:
    """Settings from the environment (``WANDELL_*``), else the embedded
    defaults; read once per process (``get_settings.cache_clear()`` re-reads)."""
    return Settings()


def settings_problem(exc: ValidationError) -> str:
    """One line per invalid ``WANDELL_*`` variable: its name, the value given
    and what is accepted (what ``python -m service`` and ``wandell`` print
    before exiting with status 2)."""
    lines = []
    for err in exc.errors():
        name = "WANDELL_" + "_".join(str(p) for p in err.get("loc", ())).upper()
        lines.append(f"invalid setting {name}={err.get('input')!r}: {err.get('msg')}")
    return "\n".join(lines) or str(exc)


def settings_or_exit(prog: str) -> Settings:
    """:func:`get_settings`, or, when a ``WANDELL_*`` variable is invalid, one
    line per variable on stderr (``prog: invalid setting ...``,
    :func:`settings_problem`) and exit status 2, without a traceback: what
    ``python -m service`` and ``wandell`` do at start."""
    try:
        return get_settings()
    except ValidationError as e:
        import sys

        sys.stderr.write("".join(f"{prog}: {line}\n" for line in settings_problem(e).splitlines()))
        raise SystemExit(2) from None
