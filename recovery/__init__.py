"""Analysis and synthesis of colour images on arrays (Wandell 1985;
Maloney & Wandell). Knows nothing of HTTP.

>>> from recovery import Camera, estimate_illuminant, analyze, render
"""

from .api import (DEFAULT_ANALYSIS_PIXELS, METHODS, QUALITY_PRESETS, AnalysisResult, IlluminantEstimate, analysis_pixels,
                  analyze, angular_error, estimate_illuminant, render, resolve_model)
from .camera import Camera
from .errors import InputError, InsufficientSurfaceVariation, ModelDimensionError, RecoveryError
from .spectral import SpectralRender, render_spectra

__all__ = ["Camera", "estimate_illuminant", "analyze", "render", "IlluminantEstimate",
           "AnalysisResult", "METHODS", "QUALITY_PRESETS", "DEFAULT_ANALYSIS_PIXELS", "analysis_pixels",
           "angular_error", "resolve_model", "RecoveryError",
           "ModelDimensionError", "InsufficientSurfaceVariation", "InputError", "render_spectra", "SpectralRender"]
