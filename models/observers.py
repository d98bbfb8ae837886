"""Observers: colour matching functions and cone fundamentals as arrays.

The observer :math:`R'_k(\\lambda)` of the synthesis equations (Wandell 1985,
eq. 1-4) and of Fig. 6. Data from colour-science (``colour.MSDS_CMFS``).

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 1-4; Smith & Pokorny (1975) are
the cones Wandell used.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ._colour import cached, sd_to_array

__all__ = ["OBSERVERS", "observer", "observer_names"]

#: Short aliases accepted besides colour-science's own names.
OBSERVERS = {
    "CIE 1931 2 Degree Standard Observer": "CIE 1931 2 Degree Standard Observer",
    "CIE 1964 10 Degree Standard Observer": "CIE 1964 10 Degree Standard Observer",
    "Smith & Pokorny 1975 Normal Trichromats": "Smith & Pokorny 1975 Normal Trichromats",
    "Stockman & Sharpe 2 Degree Cone Fundamentals": "Stockman & Sharpe 2 Degree Cone Fundamentals",
    "Stockman & Sharpe 10 Degree Cone Fundamentals": "Stockman & Sharpe 10 Degree Cone Fundamentals",
    "XYZ": "CIE 1931 2 Degree Standard Observer",
    "CIE 1931": "CIE 1931 2 Degree Standard Observer",
    "CIE 1964": "CIE 1964 10 Degree Standard Observer",
    "cones": "Smith & Pokorny 1975 Normal Trichromats",
    "LMS": "Stockman & Sharpe 2 Degree Cone Fundamentals",
}


def observer_names() -> list[str]:
    """Names :func:`observer` accepts (aliases included)."""
    return list(OBSERVERS)


def observer(name: str = "CIE 1931 2 Degree Standard Observer", wavelengths=None) -> np.ndarray:
    """See :func:`_observer` (cached per grid; returns a read-only array)."""
    from .grid import DEFAULT_WAVELENGTHS

    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return _observer_cached(name, tuple(wl.tolist()))


@lru_cache(maxsize=128)
def _observer_cached(name, wl):
    out = _observer(name, np.asarray(wl))
    out.flags.writeable = False
    return out


@cached("models.observers._observer")
def _observer(name: str = "CIE 1931 2 Degree Standard Observer", wavelengths=None) -> np.ndarray:
    """Colour matching functions or cone fundamentals, ``(N, 3)``.

    Parameters
    ----------
    name : str
        One of :func:`observer_names`.
    wavelengths : array_like, optional
        Grid in nm; default 400-700 nm at 10 nm.

    Examples
    --------
    >>> observer("XYZ").shape
    (31, 3)
    """
    import colour

    if name not in OBSERVERS:
        raise KeyError(f"unknown observer {name!r}; accepted: {observer_names()}")
    return sd_to_array(colour.MSDS_CMFS[OBSERVERS[name]], wavelengths)
