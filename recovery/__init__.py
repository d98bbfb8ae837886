"""Analysis and synthesis of colour images on arrays (Wandell 1985;
Maloney & Wandell). Knows nothing of HTTP.

>>> from recovery import Camera, estimate_illuminant, analyze, render

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
