"""The JSON answers of the REST API, as pydantic models (issue 29, item 4).

They describe what ``/v1/analyze``, ``/v1/white-balance`` (``response=json``),
``/v1/surfaces``, ``/v1/render`` (``response=json``) and ``/v1/batches``
answer, so ``/openapi.json`` and ``/docs`` show real fields instead of
``"string"``. The routers build their answers as plain dictionaries (the
numbers come from :mod:`service.report`) and declare these models as their
documented 200 answers; ``tests/test_response_models.py`` checks that every
key a real answer carries is declared here and validates the answers
against the models, so the description cannot drift from the service.

Open-ended parts (an estimator's ``diagnostics``, the render's ``tried``
rules) are typed as objects: each method reports its own keys (see the
docs/accuracy.md, "What the diagnostics mean", and ``GET /v1/models``).
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["AnalyzeResult", "WhiteBalanceResult", "SurfacesResult", "RenderReport", "BatchCreated",
           "BatchProgress", "BatchDeleted", "BatchSummary", "BatchList"]


class _Answer(BaseModel):
    # documentation models: an answer may carry a key added later; the test
    # (tests/test_response_models.py) fails when one is not declared here
    model_config = ConfigDict(extra="allow")


class Illuminant(_Answer):
    """The estimated light."""
    camera_rgb: list[float] = Field(description="the light as the camera sees it (unit length)")
    wb_multipliers: list[float] = Field(description="white-balance multipliers per channel (green = 1)")
    wavelengths: list[float] = Field(description="wavelengths of `spectrum`, nm")
    spectrum: list[float] = Field(description="relative spectral power of the light")
    cct: float | None = Field(description="correlated colour temperature, K (Ohno 2013); null far from the "
                                          "Planckian locus")
    duv: float | None = Field(description="distance from the Planckian locus in CIE 1960 uv (Ohno 2013)")
    xy: list[float] | None = Field(description="CIE 1931 chromaticity the CCT/Duv come from")
    chromaticity_basis: str = Field(description="where xy comes from: `DNG tags`, `LibRaw` (the file's colour "
                                                "matrices) or `spectrum`")
    temperature: float | None = Field(None, description="Camera Raw's Temperature (K; also the XMP sidecar's)")
    tint: float | None = Field(None, description="Camera Raw's Tint (about 3000 x Duv)")
    temperature_basis: str | None = Field(None, description="where Temperature/Tint come from")


class CameraInfo(_Answer):
    """The camera model the estimate used."""
    name: str
    source: str = Field(description="`measured`, `matrix-derived`, `uploaded` or `generic`")
    channels: int
    approximate: bool = Field(description="true when the sensitivities are derived from a colour matrix or "
                                          "generic")
    notes: list[str]


class ImageInfo(_Answer):
    """The decoded upload."""
    kind: str = Field(description="`raw`, `tiff` or `png`")
    width: int
    height: int
    make: str | None = None
    model: str | None = None
    encoding: dict[str, Any] | None = Field(None, description="what a TIFF/PNG's ICC profile or colour chunks "
                                                              "say (display-referred input)")


class AsShot(_Answer):
    """The camera's own (as-shot) white."""
    camera_rgb: list[float]
    angle_to_estimate_deg: float = Field(description="angle between the as-shot white and the estimate, degrees")
    temperature: float | None = Field(None, description="the as-shot white as Camera Raw's Temperature (K)")
    tint: float | None = Field(None, description="and Tint")
    xy: list[float] | None = Field(None, description="its CIE 1931 chromaticity")


class LightMap(_Answer):
    """The light at the centres of a light map (``spatial`` maps)."""
    centres_row_fraction: list[float]
    centres_col_fraction: list[float]
    camera_rgb: list[list[list[float]]] = Field(description="rows x columns x channels")


class Lights(_Answer):
    """How many lights the photograph has, as decided from the image
    (``spatial=auto``; docs/mixed_light.md)."""
    found: int = Field(description="1 (one light) or 2 (several: a light map is given and used)")
    decision: str = Field(description="`one light` or `light map`")
    reason: str = Field(description="why, in words, with the evidence's figures")
    held: str | None = Field(None, description="with several lights: which light `illuminant` is")


class Rendering(_Answer):
    """How the corrected image is (or would be) rendered."""
    rendering: str = Field(description="`dng-matrix` (the DNG specification's pipeline) or `spectral` "
                                       "(Wandell 1985)")
    color_source: str
    exposure: dict[str, Any] | None = Field(None, description="`rule` (auto or user) and `ev`")
    tone: str | None = None
    curve: str | None = Field(None, description="`libraw`: LibRaw's BT.709 tone as a display shows it")
    white_xy: list[float] | None = None
    temperature: float | None = None
    tint: float | None = None
    calibration_weight: float | None = None
    forward_matrix: bool | list | None = None
    baseline_exposure: float | None = None
    target_white_xy: list[float] | None = None
    crop: list[int] | None = None
    notes: list[str] | None = None


class AnalyzeResult(_Answer):
    """``POST /v1/analyze``: the light of one image."""
    illuminant: Illuminant
    camera: CameraInfo
    method: str = Field(description="the method that ran (or `neutral-surface`)")
    diagnostics: dict[str, Any] = Field(description="the method's own figures (docs/accuracy.md: what the "
                                                    "diagnostics mean)")
    warnings: list[str]
    timings_ms: dict[str, float]
    image: ImageInfo
    rendering: Rendering
    as_shot: AsShot | None = Field(None, description="absent when the file has no as-shot white")
    lights: Lights | None = Field(None, description="one light or several, and why")
    light_map: LightMap | None = None
    method_failed: dict[str, Any] | None = Field(None, description="the literal method's own tests that failed")
    neutral: dict[str, Any] | None = Field(None, description="where a picked white (`neutral`) came from")


class WhiteBalanceResult(AnalyzeResult):
    """``POST /v1/white-balance`` with ``response=json``: the estimate and
    the correction, without the image."""
    correction_matrix: list[list[float]] = Field(description="camera RGB (1.0 = saturation) -> linear display RGB")


class Surface(_Answer):
    kind: str = Field(description="`point`, `rect` or `grid`")
    where: list[int]
    reflectance: list[float] = Field(description="the estimate: the posterior mean under the prior over measured "
                                                 "surfaces, or eq. 36 when a surface model is named")
    warnings: list[str]
    reflectance_std: list[float] | None = Field(None, description="the band per wavelength: the posterior "
                                                                  "standard deviation times a factor calibrated on "
                                                                  "reflectance sets left out, so that reflectance "
                                                                  "+- 1.645 std is a 90 % band; null for eq. 36")
    expected_rmse: float | None = Field(None, description="one number for the surface: the RMS error the model "
                                                          "expects (the calibrated band's RMS); null for eq. 36")


class SurfacesResult(_Answer):
    """``POST /v1/surfaces`` (``format=json``)."""
    wavelengths: list[float]
    surfaces: list[Surface]
    surface_estimator: str = Field(description="`prior` (issue 31: a prior over measured surfaces, with bands) or "
                                               "`pinv` (eq. 36, when a surface model is named)")
    band: str = Field(description="what reflectance_std and expected_rmse mean")
    surface_model: str
    reflectance_scale_convention: str
    diagnostics: dict[str, Any]
    illuminant: Illuminant
    method: str
    camera: CameraInfo
    warnings: list[str]


class RenderReport(_Answer):
    """``POST /v1/render`` with ``response=json`` (also the ``X-Render-Report``
    header): the sampling rule used and its error against the full calculation."""
    strategy: str
    n: int | None = None
    options: dict[str, Any]
    nodes_nm: list[float]
    bands_read: int
    bands_total: int
    layout: str
    represent_light: bool | None = None
    light: dict[str, Any]
    error: dict[str, Any] | None = Field(None, description="CIEDE2000 mean/p95/max on a pixel sample against the "
                                                           "full calculation")
    bound: dict[str, Any] | None = None
    why: str | None = None
    tried: list[dict[str, Any]] | None = None
    output: str
    adapt: bool
    white_xyz: list[float]
    diagnostics: dict[str, Any]
    timings_ms: dict[str, float]
    warnings: list[str]


class BatchCounts(_Answer):
    done: int
    failed: int
    pending: int
    running: int | None = None
    cancelled: int | None = None
    total: int | None = None


class BatchCreated(_Answer):
    """``POST /v1/batches`` (202): the new batch."""
    id: str
    status: str
    counts: BatchCounts
    lighting: str
    url: str = Field(description="the progress document")
    runner_error: str | None = Field(None, description="accepted, but no item can run now, and why (no Dask "
                                                       "scheduler or worker, a full disk): docs/reliability.md")
    registration: str | None = Field(None, description="deferred: the job store was busy; the batch is kept on "
                                                       "disk and registered as soon as the store is free")


class BatchItem(_Answer):
    index: int
    name: str = Field(description="unique within the batch (`a (2).dng`)")
    status: str = Field(description="`pending`, `running`, `done`, `failed` or `cancelled`")
    output: str | None = None
    url: str | None = Field(None, description="the result's download, once done")
    error: str | None = None
    illuminant: dict[str, Any] | None = Field(None, description="camera_rgb, wb_multipliers, cct, duv, method, "
                                                                "camera, warnings, confidence, low_confidence")


class BatchProgress(_Answer):
    """``GET /v1/batches/{id}`` (and a cancelling ``DELETE``): progress."""
    id: str
    status: str = Field(description="`queued`, `running`, `done` or `cancelled`")
    settled: bool = Field(description="the batch is over and every count final")
    lighting: str | None
    options: dict[str, Any]
    counts: BatchCounts
    rate_per_minute: float | None
    time_left_s: float | None
    elapsed_s: float
    rate: float | None
    eta_s: float | None
    created: float
    items: list[BatchItem]
    phase: str | None = None
    shared_light: dict[str, Any] | None = None
    shared_light_error: str | None = None
    runner_error: str | None = Field(None, description="why no item runs now (`executor_unavailable`, "
                                                       "`waiting_for_workers`, `insufficient_storage`); "
                                                       "time_left_s is then null")
    runner_error_since: float | None = Field(None, description="since when (epoch seconds) runner_error holds")
    warnings: list[str] | None = Field(None, description="the batch's own warnings: a shared light over images "
                                                         "that were not all under one light, with its confidence")
    registration: str | None = Field(None, description="deferred: made while the job store was busy, not yet "
                                                       "registered (every item pending)")
    low_confidence: list[str] | None = Field(None, description="the items whose light estimate is flagged "
                                                               "low-confidence (listed first in `items`)")
    deleted: bool | None = Field(None, description="false: a DELETE of an unfinished batch cancels it; "
                                                   "DELETE again once settled to remove it")


class BatchDeleted(_Answer):
    """``DELETE /v1/batches/{id}`` of a settled batch: it is gone, files and all."""
    id: str
    deleted: bool
    freed_bytes: int = Field(description="bytes of inputs and results removed")


class BatchSummary(_Answer):
    id: str
    status: str
    created: float
    finished: float | None = None
    counts: BatchCounts
    bytes: int = Field(description="disk space of its inputs and results")
    url: str


class BatchList(_Answer):
    """``GET /v1/batches``: every batch the service keeps, newest first."""
    batches: list[BatchSummary]
    bytes: int = Field(description="their disk space together")
    result_retention_s: float = Field(description="WANDELL_BATCH_RESULT_RETENTION")
    input_retention_s: float = Field(description="WANDELL_BATCH_INPUT_RETENTION")
