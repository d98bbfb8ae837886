"""Surface reflectance sets shipped with colour-science, as arrays.

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 6 and 11 and Fig. 5 (surfaces as
weighted sums of basis functions, fitted to a set of measured surfaces).
"""

from __future__ import annotations

import numpy as np

from ._colour import cached, sd_to_array

__all__ = ["REFLECTANCE_SETS", "reflectance_set", "reflectance_set_names"]

#: Set name -> description of where colour-science keeps it.
REFLECTANCE_SETS = {
    "colorchecker": "ColorChecker, BabelColor average (colour.SDS_COLOURCHECKERS)",
    "colorchecker-ohta": "ColorChecker, N. Ohta (colour.SDS_COLOURCHECKERS)",
    "rawtoaces-190": "190 training patches of rawtoaces (read_training_data_rawtoaces_v1)",
    "tcs": "CIE test colour samples, CIE 1995 (colour.quality.SDS_TCS)",
    "vs": "CQS test samples, NIST CQS 9.0 (colour.quality.SDS_VS)",
}


def reflectance_set_names() -> list[str]:
    """Names :func:`reflectance_set` accepts, plus ``"all"``."""
    return list(REFLECTANCE_SETS) + ["all"]


@cached("models.reflectances._load")
def _load(name: str, wavelengths) -> tuple[np.ndarray, list[str]]:
    import colour

    if name == "colorchecker":
        sds = colour.SDS_COLOURCHECKERS["BabelColor Average"]
    elif name == "colorchecker-ohta":
        sds = colour.SDS_COLOURCHECKERS["ColorChecker N Ohta"]
    elif name == "tcs":
        sds = colour.quality.SDS_TCS["CIE 1995"]
    elif name == "vs":
        sds = colour.quality.SDS_VS["NIST CQS 9.0"]
    elif name == "rawtoaces-190":
        msds = colour.characterisation.read_training_data_rawtoaces_v1()
        return sd_to_array(msds, wavelengths).T, [f"rawtoaces {label}" for label in msds.labels]
    else:
        raise KeyError(f"unknown reflectance set {name!r}; accepted: {reflectance_set_names()}")
    names = list(sds)
    return np.stack([sd_to_array(sds[k], wavelengths) for k in names]), [f"{name} {k}" for k in names]


def reflectance_set(name: str = "all", wavelengths=None, return_names: bool = False):
    """Reflectances of a set as rows, ``(M, N)``, in [0, 1].

    ``"all"`` stacks every set of :data:`REFLECTANCE_SETS`.

    Examples
    --------
    >>> reflectance_set("colorchecker").shape
    (24, 31)
    """
    if name == "all":
        parts = [_load(n, wavelengths) for n in REFLECTANCE_SETS]
        data = np.concatenate([p[0] for p in parts])
        names = [s for p in parts for s in p[1]]
    else:
        data, names = _load(name, wavelengths)
    data = np.clip(data, 0.0, None)
    return (data, names) if return_names else data
