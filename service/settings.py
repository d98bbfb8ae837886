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
    #: RAW files are binned to at most this many pixels for estimation
    estimation_pixels: int = 1_000_000


def _positive_int(env, name: str, default: int) -> int:
    """``WANDELL_<NAME>`` as a positive integer, or a ValueError naming it."""
    key = "WANDELL_" + name.upper()
    raw = env.get(key)
    if raw is None:
        return default
    try:
        value = int(raw)
    except ValueError:
        raise ValueError(f"{key}={raw!r} is not an integer") from None
    if value <= 0:
        raise ValueError(f"{key}={raw!r} must be positive")
    return value


@lru_cache
def get_settings() -> Settings:
    """Settings from the environment, else the embedded defaults."""
    env = os.environ
    return Settings(
        host=env.get("WANDELL_HOST", Settings.host),
        port=_positive_int(env, "port", Settings.port),
        max_upload_bytes=_positive_int(env, "max_upload_bytes", Settings.max_upload_bytes),
        max_pixels=_positive_int(env, "max_pixels", Settings.max_pixels),
        estimation_pixels=_positive_int(env, "estimation_pixels", Settings.estimation_pixels),
    )
