"""Spectral data and linear models, as plain arrays on a wavelength grid.

Knows nothing of images or HTTP. Data come from colour-science; nothing is
typed in by hand.
"""

from .bases import (LinearModel, daylight_model, fourier_basis, fourier_model,
                    illuminant_pca_model, normalised_rmse, pca_model, surface_pca_model)
from .cameras import camera_names, camera_sensitivities, canonical_camera_name
from .displays import Display, display, display_names
from .grid import DEFAULT_WAVELENGTHS, resample, wavelength_grid, wavelength_step
from .illuminants import (blackbody, daylight, daylight_basis, illuminant, illuminant_names,
                          illuminants)
from .observers import observer, observer_names
from .reflectances import reflectance_set, reflectance_set_names

__all__ = [
    "LinearModel", "daylight_model", "fourier_basis", "fourier_model", "illuminant_pca_model",
    "normalised_rmse", "pca_model", "surface_pca_model", "camera_names", "camera_sensitivities",
    "canonical_camera_name", "Display", "display", "display_names", "DEFAULT_WAVELENGTHS",
    "resample", "wavelength_grid", "wavelength_step", "blackbody", "daylight", "daylight_basis",
    "illuminant", "illuminant_names", "illuminants", "observer", "observer_names",
    "reflectance_set", "reflectance_set_names",
]
