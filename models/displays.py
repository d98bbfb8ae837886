"""Displays: spectral gun emissions, or primaries given as tristimulus values.

The guns :math:`G_j(\\lambda)` of Wandell (1985), eq. 2-4. A spectral display
(``Typical CRT Brainard 1997``, ``Apple Studio Display`` from
colour-science) gives :math:`\\Gamma` for any observer. A colourimetric
display (sRGB / Rec. 709) is defined only through its primaries' CIE 1931
XYZ, so its :math:`\\Gamma` exists for the CIE 1931 observer alone.

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 2-4; IEC 61966-2-1 (sRGB).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ._colour import cached, sd_to_array

__all__ = ["Display", "display", "display_names"]

_SPECTRAL = ("Typical CRT Brainard 1997", "Apple Studio Display")
_COLORIMETRIC = {"sRGB": "sRGB", "Rec. 709": "ITU-R BT.709", "Display P3": "Display P3"}


@dataclass(frozen=True)
class Display:
    """A display: either spectral guns ``(N, 3)`` on ``wavelengths`` or a
    3x3 matrix of the primaries' CIE 1931 XYZ (columns, white Y = 1)."""

    name: str
    guns: np.ndarray | None = None
    wavelengths: np.ndarray | None = None
    primaries_XYZ: np.ndarray | None = None
    encoding: str | None = None  # colour-science RGB colourspace for the transfer function

    @property
    def spectral(self) -> bool:
        return self.guns is not None


def display_names() -> list[str]:
    """Names :func:`display` accepts."""
    return list(_SPECTRAL) + list(_COLORIMETRIC)


def display(name: str = "sRGB", wavelengths=None) -> Display:
    """A :class:`Display` by name.

    Examples
    --------
    >>> display("Typical CRT Brainard 1997").guns.shape
    (31, 3)
    >>> display("sRGB").primaries_XYZ.shape
    (3, 3)
    """
    from .grid import DEFAULT_WAVELENGTHS

    if name in _SPECTRAL:
        wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
        return Display(name=name, guns=_spectral_guns(name, wl), wavelengths=wl)
    if name in _COLORIMETRIC:
        m, encoding = _colorimetric(name)
        return Display(name=name, primaries_XYZ=m, encoding=encoding)
    raise KeyError(f"unknown display {name!r}; accepted: {display_names()}")


@cached("models.displays._spectral_guns")
def _spectral_guns(name: str, wl) -> np.ndarray:
    import colour

    return np.clip(sd_to_array(colour.MSDS_DISPLAY_PRIMARIES[name], np.asarray(wl, float)), 0, None)


@cached("models.displays._colorimetric")
def _colorimetric(name: str) -> tuple[np.ndarray, str]:
    import colour

    cs = colour.RGB_COLOURSPACES[_COLORIMETRIC[name]]
    # Gamma^-1 is the colourspace's own XYZ -> RGB matrix (for sRGB the
    # IEC 61966-2-1 matrix, which is not the exact inverse of the rounded
    # RGB -> XYZ one), so synthesis agrees with colour-science's encoder.
    return np.linalg.inv(np.asarray(cs.matrix_XYZ_to_RGB, float)), cs.name
