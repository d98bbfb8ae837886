"""Plain JSON values with no NaN or Inf (DESIGN.md: never NaN in JSON)."""

from __future__ import annotations

import math

import numpy as np


def clean(obj):
    """Recursively convert numpy types to Python ones and non-finite floats
    to ``None``."""
    if isinstance(obj, dict):
        return {str(k): clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [clean(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return clean(obj.tolist())
    if isinstance(obj, (np.bool_, bool)):
        return bool(obj)
    if isinstance(obj, (np.integer,)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        return f if math.isfinite(f) else None
    return obj
