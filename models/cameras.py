"""Measured camera spectral sensitivities shipped with colour-science.

The sensor functions :math:`R_k(\\lambda)` of Wandell (1985), eq. 12, for
the analysis side (Fig. 6: camera sensors analyse).

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 12 and Fig. 6.
colour-science: ``colour.MSDS_CAMERA_SENSITIVITIES`` (NPL measurements of
the Nikon 5100 and Sigma SD Merrill) and the rawtoaces Canon EOS 5D Mark II
data in ``colour/characterisation/datasets/rawtoaces``.
"""

from __future__ import annotations

import os

import numpy as np

from ._colour import cached, sd_to_array
from .grid import DEFAULT_WAVELENGTHS

__all__ = ["CAMERAS", "camera_names", "camera_sensitivities", "canonical_camera_name"]

#: Canonical name -> aliases (lower case) used to match RAW make/model.
CAMERAS = {
    "Nikon 5100 (NPL)": ("nikon d5100", "nikon 5100", "d5100"),
    "Sigma SDMerill (NPL)": ("sigma sd merrill", "sigma sdmerill", "sd merrill", "sigma sd1 merrill"),
    "Canon EOS 5D Mark II": ("canon eos 5d mark ii", "eos 5d mark ii", "canon 5d mark ii"),
}


def camera_names() -> list[str]:
    """Canonical names of the measured cameras."""
    return list(CAMERAS)


def canonical_camera_name(name: str) -> str | None:
    """Map a name or a RAW ``make model`` string to a canonical camera name,
    or ``None`` if it is not one of the measured cameras."""
    if name in CAMERAS:
        return name
    low = " ".join(name.lower().replace("-", " ").split())
    for canon, aliases in CAMERAS.items():
        if low == canon.lower() or any(low == a or low.endswith(a) for a in aliases):
            return canon
    return None


@cached("models.cameras.camera_sensitivities")
def camera_sensitivities(name: str, wavelengths=None) -> np.ndarray:
    """Spectral sensitivities ``(N, 3)`` (columns R, G, B) with the measured
    balance between channels, scaled together so the largest value on the
    default grid (400-700 nm at 10 nm) is 1; the same gain is used on every
    grid. Served from the shipped colour cache (:func:`models._colour.cached`)
    for the measured cameras on the default grid: importing colour-science
    for them cost a fresh ``wandell white-balance`` about 1.2 s (issue 19).

    Examples
    --------
    >>> camera_sensitivities("Nikon 5100 (NPL)").shape
    (31, 3)
    """
    import colour

    canon = canonical_camera_name(name)
    if canon is None:
        raise KeyError(f"unknown camera {name!r}; accepted: {camera_names()}")
    if canon == "Canon EOS 5D Mark II":
        from colour.characterisation.aces_it import ROOT_RESOURCES_RAWTOACES
        from colour.io import read_sds_from_csv_file

        path = os.path.join(ROOT_RESOURCES_RAWTOACES, "CANON_EOS_5DMark_II_RGB_Sensitivities.csv")
        msds = colour.colorimetry.sds_and_msds_to_msds(list(read_sds_from_csv_file(path).values()))
    else:
        msds = colour.MSDS_CAMERA_SENSITIVITIES[canon]
    arr = np.clip(sd_to_array(msds, wavelengths), 0.0, None)
    # one gain for all channels, taken on one reference grid: the measured
    # balance between channels is what a real RAW file records, and the
    # camera is the same on every sampling grid
    ref = np.clip(sd_to_array(msds, DEFAULT_WAVELENGTHS), 0.0, None).max()
    return arr / ref
