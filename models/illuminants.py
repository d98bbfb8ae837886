"""Illuminants: colour-science's spectral power distributions and the CIE
daylight basis, as arrays.

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 5 and 10 (lights as weighted sums
of basis functions) and section "Principal Components Analysis" (Judd,
MacAdam & Wyszecki 1964: the daylight components S0, S1, S2).
CIE 015:2018, daylight series.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from ._colour import sd_to_array
from .grid import DEFAULT_WAVELENGTHS, resample_box

__all__ = [
    "illuminant",
    "illuminant_names",
    "illuminants",
    "daylight_basis",
    "daylight",
    "blackbody",
]


def light_to_array(sd, wavelengths=None) -> np.ndarray:
    """A light (or a light basis) on ``wavelengths``: interpolated where the
    grid is at least as fine as the data, box-averaged where it is coarser
    (:func:`models.grid.resample_box`: narrow lines keep their energy)."""
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    src = np.asarray(sd.wavelengths, float)
    if wl.size > 1 and float(np.min(np.diff(wl))) > float(np.min(np.diff(src))) * 1.01:
        return resample_box(src, np.asarray(sd.values, float), wl)
    return sd_to_array(sd, wl)


def illuminant_names(kind: str = "all") -> list[str]:
    """Names of colour-science's illuminants (``colour.SDS_ILLUMINANTS``).

    Parameters
    ----------
    kind : {"all", "fluorescent", "non-fluorescent"}
        ``fluorescent`` are the FL series (spiky); LED and HP lights are
        listed under ``non-fluorescent``.
    """
    import colour

    names = [n for n in colour.SDS_ILLUMINANTS if not n.startswith("ISO 7589 Sensitometric")]
    if kind == "fluorescent":
        return [n for n in names if n.startswith("FL")]
    if kind == "non-fluorescent":
        return [n for n in names if not n.startswith("FL")]
    if kind != "all":
        raise ValueError(f"kind must be all, fluorescent or non-fluorescent, not {kind!r}")
    return names


def illuminant(name: str, wavelengths=None, normalise: bool = True) -> np.ndarray:
    """See :func:`_illuminant` (cached per grid; returns a new array)."""
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return _illuminant_cached(name, tuple(wl.tolist()), bool(normalise)).copy()


@lru_cache(maxsize=512)
def _illuminant_cached(name, wl, normalise):
    return _illuminant(name, np.asarray(wl), normalise)


def _illuminant(name: str, wavelengths=None, normalise: bool = True) -> np.ndarray:
    """One illuminant's relative spectral power, ``(N,)``.

    Besides colour-science's names, ``"D<cct>"`` with any CCT in 4000-25000 K
    (e.g. ``"D93"``, ``"D5000"``) gives the CIE daylight at that CCT, and
    ``"BB<cct>"`` (e.g. ``"BB3200"``) a blackbody.

    On a grid coarser than the data the spectrum is resampled with
    :func:`models.grid.resample_box` (each value is the mean over its
    interval), so narrow emission lines keep their energy.

    Parameters
    ----------
    normalise : bool
        Scale so the mean over the grid is 1 (unit relative power).

    Examples
    --------
    >>> round(float(illuminant("D65").mean()), 6)
    1.0
    """
    import colour

    if name in colour.SDS_ILLUMINANTS:
        spd = light_to_array(colour.SDS_ILLUMINANTS[name], wavelengths)
    elif name.startswith("BB") and name[2:].replace(".", "", 1).isdigit():
        spd = blackbody(float(name[2:]), wavelengths)
    elif name.startswith("D") and name[1:].isdigit():
        cct = float(name[1:])
        cct = cct * 100 if cct < 1000 else cct
        spd = daylight(cct * 1.4388 / 1.4380, wavelengths)
    else:
        raise KeyError(f"unknown illuminant {name!r}; accepted: {illuminant_names()} or D<cct>, BB<cct>")
    if normalise:
        m = spd.mean()
        spd = spd / m if m > 0 else spd
    return spd


def illuminants(names=None, wavelengths=None, normalise: bool = True) -> np.ndarray:
    """Several illuminants stacked as rows, ``(M, N)``."""
    names = illuminant_names() if names is None else list(names)
    return np.stack([illuminant(n, wavelengths, normalise) for n in names])


def daylight_basis(wavelengths=None) -> np.ndarray:
    """The CIE daylight components S0, S1, S2 as columns, ``(N, 3)``.

    Judd, MacAdam & Wyszecki's principal components of daylight, the light
    model Wandell (1985) cites; from
    ``colour.colorimetry.SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES``.
    """
    from colour.colorimetry import SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES as B

    return np.stack([light_to_array(B[k], wavelengths) for k in ("S0", "S1", "S2")], 1)


def daylight(cct: float, wavelengths=None) -> np.ndarray:
    """CIE daylight of correlated colour temperature ``cct`` (K), ``(N,)``,
    from colour-science's ``CCT_to_xy_CIE_D`` and ``sd_CIE_illuminant_D_series``."""
    import colour

    xy = colour.temperature.CCT_to_xy_CIE_D(cct)
    return light_to_array(colour.sd_CIE_illuminant_D_series(xy), wavelengths)


def blackbody(temperature: float, wavelengths=None) -> np.ndarray:
    """Planckian radiator at ``temperature`` K, ``(N,)`` (colour-science's
    ``planck_law``), unnormalised."""
    import colour

    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return np.asarray(colour.colorimetry.planck_law(wl * 1e-9, temperature), float)
