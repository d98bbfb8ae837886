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

from ._colour import cached, sd_to_array
from .grid import DEFAULT_WAVELENGTHS, resample_box

__all__ = [
    "illuminant",
    "illuminant_names",
    "illuminants",
    "daylight_basis",
    "daylight",
    "blackbody",
    "DAYLIGHT_CCT_RANGE",
    "BLACKBODY_RANGE",
    "temperature_of",
]

#: CCT (K) the CIE daylight series is defined for (CIE 015:2018, 4000-25000 K):
#: ``D<cct>`` names outside it are refused.
DAYLIGHT_CCT_RANGE = (4000.0, 25000.0)
#: Temperatures (K) ``BB<K>`` names may take: below 1000 K Planck's law
#: underflows on the visible grid (a black light), above 25000 K it is as
#: blue as daylight's own upper end.
BLACKBODY_RANGE = (1000.0, 25000.0)


def light_to_array(sd, wavelengths=None) -> np.ndarray:
    """A light (or a light basis) on ``wavelengths``: interpolated where the
    grid is at least as fine as the data, box-averaged where it is coarser
    (:func:`models.grid.resample_box`: narrow lines keep their energy)."""
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    src = np.asarray(sd.wavelengths, float)
    if wl.size > 1 and float(np.min(np.diff(wl))) > float(np.min(np.diff(src))) * 1.01:
        return resample_box(src, np.asarray(sd.values, float), wl)
    return sd_to_array(sd, wl)


@cached("models.illuminants.illuminant_names")
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


@cached("models.illuminants._illuminant")
def _illuminant(name: str, wavelengths=None, normalise: bool = True) -> np.ndarray:
    """One illuminant's relative spectral power, ``(N,)``.

    Besides colour-science's names, ``"D<cct>"`` with any CCT in 4000-25000 K
    (:data:`DAYLIGHT_CCT_RANGE`; e.g. ``"D93"``, ``"D5000"``) gives the CIE
    daylight at that CCT, and ``"BB<K>"`` with 1000-25000 K
    (:data:`BLACKBODY_RANGE`; e.g. ``"BB3200"``) a blackbody; other
    temperatures, or temperatures not in ASCII digits, are a ``KeyError``
    naming the range (:func:`temperature_of`).

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
    elif (kind_t := temperature_of(name)) is not None:
        kind, t = kind_t
        spd = blackbody(t, wavelengths) if kind == "BB" else daylight(t * 1.4388 / 1.4380, wavelengths)
    else:
        raise KeyError(f"unknown illuminant {name!r}; accepted: {illuminant_names()} or D<cct> "
                       f"({DAYLIGHT_CCT_RANGE[0]:.0f}..{DAYLIGHT_CCT_RANGE[1]:.0f} K), BB<K> "
                       f"({BLACKBODY_RANGE[0]:.0f}..{BLACKBODY_RANGE[1]:.0f} K)")
    if normalise:
        m = spd.mean()
        spd = spd / m if m > 0 else spd
    return spd


def _ascii_number(text: str, decimals: bool) -> float | None:
    """``text`` as a number if it is ASCII digits (one ``.`` when
    ``decimals``) of at most 8 characters, else ``None`` (no Unicode digits
    such as ``"²"``, no exponent, no sign)."""
    if not text or len(text) > 8 or not text.isascii():
        return None
    body = text.replace(".", "", 1) if decimals else text
    if not body or not body.isdigit():
        return None
    return float(text)


def temperature_of(name: str) -> tuple[str, float] | None:
    """``("D", cct)`` for ``D<cct>`` (a 2-3 digit value is hundreds of
    kelvin: ``D93`` is 9300 K), ``("BB", kelvin)`` for ``BB<K>``; ``None`` when
    the name names no temperature (the rest is not all digits: ``D65x``). A temperature outside
    :data:`DAYLIGHT_CCT_RANGE` / :data:`BLACKBODY_RANGE`, or written with
    anything but ASCII digits, is a ``KeyError`` naming the range.

    >>> temperature_of("D93"), temperature_of("BB3200"), temperature_of("A")
    (('D', 9300.0), ('BB', 3200.0), None)
    """
    if not isinstance(name, str):
        return None
    if name.startswith("BB") and name[2:].replace(".", "", 1).isdigit():    # digits, Unicode ones too ("²")
        lo, hi = BLACKBODY_RANGE
        t = _ascii_number(name[2:], decimals=True)
        if t is None or not lo <= t <= hi:
            raise KeyError(f"illuminant {name[:40]!r}: BB<K> takes a blackbody temperature of {lo:.0f}..{hi:.0f} K "
                           "in ASCII digits (e.g. BB3200)")
        return "BB", t
    if name.startswith("D") and name[1:].isdigit():
        lo, hi = DAYLIGHT_CCT_RANGE
        t = _ascii_number(name[1:], decimals=False)
        if t is not None and t < 1000:
            t *= 100
        if t is None or not lo <= t <= hi:
            raise KeyError(f"illuminant {name[:40]!r}: D<cct> takes a daylight CCT of {lo:.0f}..{hi:.0f} K in ASCII "
                           f"digits (D5000), or hundreds of K in 2-3 digits (D93 = 9300 K)")
        return "D", t
    return None


def illuminants(names=None, wavelengths=None, normalise: bool = True) -> np.ndarray:
    """Several illuminants stacked as rows, ``(M, N)``."""
    names = illuminant_names() if names is None else list(names)
    return np.stack([illuminant(n, wavelengths, normalise) for n in names])


@cached("models.illuminants.daylight_basis")
def daylight_basis(wavelengths=None) -> np.ndarray:
    """The CIE daylight components S0, S1, S2 as columns, ``(N, 3)``.

    Judd, MacAdam & Wyszecki's principal components of daylight, the light
    model Wandell (1985) cites; from
    ``colour.colorimetry.SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES``.
    """
    from colour.colorimetry import SDS_BASIS_FUNCTIONS_CIE_ILLUMINANT_D_SERIES as B

    return np.stack([light_to_array(B[k], wavelengths) for k in ("S0", "S1", "S2")], 1)


@cached("models.illuminants.daylight")
def daylight(cct: float, wavelengths=None) -> np.ndarray:
    """CIE daylight of correlated colour temperature ``cct`` (K), ``(N,)``,
    from colour-science's ``CCT_to_xy_CIE_D`` and ``sd_CIE_illuminant_D_series``."""
    import colour

    xy = colour.temperature.CCT_to_xy_CIE_D(cct)
    return light_to_array(colour.sd_CIE_illuminant_D_series(xy), wavelengths)


@cached("models.illuminants.blackbody")
def blackbody(temperature: float, wavelengths=None) -> np.ndarray:
    """Planckian radiator at ``temperature`` K, ``(N,)`` (colour-science's
    ``planck_law``), unnormalised."""
    import colour

    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return np.asarray(colour.colorimetry.planck_law(wl * 1e-9, temperature), float)
