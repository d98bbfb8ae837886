"""Analysis and synthesis of colour images on arrays (Wandell 1985;
Maloney & Wandell). Knows nothing of HTTP.

Where to start
--------------
* :func:`estimate_illuminant` (image, camera) -> :class:`IlluminantEstimate`:
  the light as the camera sees it (``rgb``, ``wb_multipliers``), its
  ``spectrum``, ``diagnostics["confidence"]`` (the probability of an error
  under 3 degrees) and, when the light varies over the frame, ``light_map``
  (:class:`recovery.regions.LightMap`).
* :func:`analyze` (image, camera) -> :class:`AnalysisResult`: the light and
  the surfaces; ``reflectance(points)`` and ``surface_estimates(points)``
  (mean, ``std`` per wavelength: mean +- 1.645 std is a 90 % band, and
  ``expected_rmse``) at ``(row, col)`` pixels of the image given.
* :func:`render` (image, camera, estimate, target) -> the image under another
  light; :class:`Camera` (``Camera.named``, or its sensitivities) says how
  the camera responds.
* Errors are :class:`RecoveryError` subclasses (``ValueError``): bad input
  (:class:`InputError`), too little surface variation, a model too large.

To read a camera file into these arrays, ``service.loader.load`` (the
README's Python section). ``docs/surfaces.md`` and ``docs/mixed_light.md``
say how good the bands and the light map are.

>>> import numpy as np
>>> from recovery import Camera, analyze
>>> cam = Camera.named("Nikon 5100 (NPL)")
>>> img = np.random.default_rng(0).uniform(0.1, 1, (8, 8, 3))   # linear camera RGB
>>> res = analyze(img, cam, method="gray-world")
>>> res.illuminant.rgb.shape, res.surface_estimates([(0, 0)]).std.shape
((3,), (1, 31))

The names are loaded on first use (PEP 562): importing ``recovery.methods``
(the method and preset tables, plain data) does not import numpy, so the
CLI's ``--help`` can list the methods and stay light.
"""

from __future__ import annotations

import importlib

#: public name -> the submodule that defines it
_EXPORTS = {
    **dict.fromkeys(("DEFAULT_ANALYSIS_PIXELS", "METHODS", "QUALITY_PRESETS", "AnalysisResult",
                     "IlluminantEstimate", "analysis_pixels", "analyze", "angular_error", "estimate_illuminant",
                     "render", "resolve_model"), ".api"),
    "Camera": ".camera",
    **dict.fromkeys(("InputError", "InsufficientSurfaceVariation", "ModelDimensionError", "RecoveryError"),
                    ".errors"),
    **dict.fromkeys(("SpectralRender", "render_spectra"), ".spectral"),
}

__all__ = ["Camera", "estimate_illuminant", "analyze", "render", "IlluminantEstimate",
           "AnalysisResult", "METHODS", "QUALITY_PRESETS", "DEFAULT_ANALYSIS_PIXELS", "analysis_pixels",
           "angular_error", "resolve_model", "RecoveryError",
           "ModelDimensionError", "InsufficientSurfaceVariation", "InputError", "render_spectra", "SpectralRender"]


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(_EXPORTS[name], __name__), name)
        globals()[name] = value
        return value
    try:       # a submodule (recovery.api, ...) reached as an attribute
        return importlib.import_module(f"{__name__}.{name}")
    except ModuleNotFoundError as e:
        if e.name != f"{__name__}.{name}":
            raise
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None


def __dir__():
    return sorted(set(globals()) | set(__all__))
