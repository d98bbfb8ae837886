"""Private helpers turning colour-science spectral objects into arrays."""

from __future__ import annotations

import numpy as np

from .grid import DEFAULT_WAVELENGTHS, resample


def sd_to_array(sd, wavelengths=None) -> np.ndarray:
    """A colour ``SpectralDistribution`` or ``MultiSpectralDistributions``
    as a float64 array on ``wavelengths`` (``(N,)`` or ``(N, K)``)."""
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return resample(np.asarray(sd.wavelengths, float), np.asarray(sd.values, float), wl)
