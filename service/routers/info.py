"""``GET /health``, ``/v1/cameras``, ``/v1/models``."""

from __future__ import annotations

from fastapi import APIRouter, Depends

import models
from recovery.methods import METHODS

from ..schemas.responses import CameraList, Health, ModelsInfo
from ..settings import Settings, get_settings

router = APIRouter()


@router.get("/health", response_model=None, responses={200: {"model": Health}})
def health(settings: Settings = Depends(get_settings)) -> dict:
    """Liveness: the service is up and the numerical core imports;
    ``job_store`` says whether the batch store opened cleanly (``recovered``:
    a damaged one was moved aside at start-up, with where to, or a lost one
    rebuilt from the batch folders; ``unavailable``: it could not be opened,
    with why; ``read_only``: batches are only read); ``batch_runner`` whether batch items can
    run now (``degraded``: why not, e.g. no Dask worker, and since when; the
    top-level ``status`` is then ``degraded`` too, still HTTP 200)."""
    import recovery.api  # noqa: F401

    from .batches import runner_health, store_health

    runner, store = runner_health(), store_health()
    degraded = runner["status"] == "degraded" or store["status"] in ("unavailable", "read_only")
    return {"status": "degraded" if degraded else "ok", "version": "0.1.0",
            "max_upload_bytes": settings.max_upload_bytes, "max_pixels": settings.max_pixels,
            "job_store": store, "batch_runner": runner}


@router.get("/v1/cameras", response_model=None, responses={200: {"model": CameraList}})
def cameras() -> dict:
    """Cameras the service knows, and how it knows them."""
    measured = [{"name": n, "source": "measured", "channels": 3,
                 "matches": list(models.cameras.CAMERAS[n])} for n in models.camera_names()]
    return {
        "cameras": measured,
        "other_sources": {
            "matrix-derived": "any camera LibRaw has a colour matrix for (or a DNG ColorMatrix1): "
                              "sensitivities = CIE 1931 CMFs through the XYZ->camera matrix; approximate",
            "uploaded": "multipart field 'sensitivities': CSV with wavelength and one column per channel",
            "generic": "mean of the measured cameras, used with a warning when nothing else is known",
        },
    }


@router.get("/v1/models", response_model=None, responses={200: {"model": ModelsInfo}})
def linear_models() -> dict:
    """Linear models (bases) and their dimensions; estimation methods."""
    return {
        "surface_models": {"pca": "PCA through the origin of colour-science's reflectances (up to 31 terms)",
                           "fourier": "DC plus sine/cosine pairs (Wandell 1985, Fig. 4b)"},
        "light_models": {"daylight": "CIE daylight S0, S1, S2 (up to 3 terms; default for D(E) <= 3)",
                         "illuminant-pca": "PCA of colour-science's illuminants (default for D(E) > 3)"},
        "rules": ["D(S) < C (number of camera channels)", "D(E) <= D(S) + 1"],
        "defaults": {"D(S)": "C - 1", "D(E)": "D(S) + 1"},
        "methods": list(METHODS),
        "method_descriptions": {name: m.description for name, m in METHODS.items()},
        "method_words": {name: m.words for name, m in METHODS.items()},
        "wavelengths": models.DEFAULT_WAVELENGTHS.tolist(),
        "reflectance_sets": models.reflectance_set_names(),
        "illuminants": models.illuminant_names(),
        "displays": models.display_names(),
    }
