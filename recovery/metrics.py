"""The angle between two colours: the one error metric of the estimates."""

from __future__ import annotations

import numpy as np

__all__ = ["angular_error"]


def angular_error(a, b) -> np.ndarray:
    """Angle in degrees between vectors (last axis), computed as
    ``2 atan2(|a^ - b^|, |a^ + b^|)``, accurate for tiny angles."""
    a = np.asarray(a, float)
    b = np.asarray(b, float)
    an = a / np.linalg.norm(a, axis=-1, keepdims=True)
    bn = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(2 * np.arctan2(np.linalg.norm(an - bn, axis=-1), np.linalg.norm(an + bn, axis=-1)))
