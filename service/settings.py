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
    #: POST /v1/render refuses spectral data with more values (H x W x N) (413)
    max_render_values: int = 64_000_000


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
        max_render_values=int(env.get("WANDELL_MAX_RENDER_VALUES", Settings.max_render_values)),
    )
