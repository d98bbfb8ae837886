"""The service's one pipeline: upload -> decode -> camera -> estimate ->
correction matrix -> apply -> encode, and the JSON of each step.

The REST routers (:mod:`service.routers.analysis`, :mod:`service.routers.web`),
the batch worker (:mod:`service.jobs`) and the CLI (:mod:`service.cli`) all
go through :func:`analyze` (decode + choose the camera + estimate) and
:func:`write_corrected` (matrix, apply, encode to a file). Thin by design:
every number comes from :mod:`recovery` (the camera from
:mod:`recovery.cameras`, the matrix with its exposure rule from
:func:`recovery.synthesis.correction_matrix`); this module chooses
resolutions, applies the one 3x3 matrix per pixel (Wandell 1985, Fig. 6: for
a fixed light camera RGB to display RGB is one matrix) in chunks, and
encodes. Its errors are :class:`~service.errors.ServiceError`; recovery
errors pass through (the edges map them, :func:`service.errors.service_error`).

The steps live in one module per concern, and every name is importable from
here as before (issue 29 split the 979 lines): :mod:`service.opening`
(decode, choose the camera, prefetch the demosaic, :func:`analyze`),
:mod:`service.estimation` (:class:`EstimateRun`, the estimate at the
analysis resolution, the generic-camera cross-check, the literal method's
failure tests, a picked white), :mod:`service.report` (the light's xy,
CCT/Duv, Temperature/Tint and the JSON answers), :mod:`service.rendering`
(the correction matrix, DefaultCrop, the corrected image whole or in
strips, the output's metadata), :mod:`service.image_files` (TIFF, PNG and
JPEG files) and :mod:`service.surfaces` (reflectances at points, rectangles
or a grid). Patch a name in the module that defines it.

Analysis resolution, the one rule: a RAW is binned to 2x2 CFA cells and
area-averaged to at most ``WANDELL_ESTIMATION_PIXELS`` (default 1 megapixel,
:attr:`service.settings.Settings.estimation_pixels`): that is the full
analysis resolution. The estimate then runs on that image block-averaged to
:func:`recovery.analysis_pixels` of the ``quality`` preset: 4096 pixels for
``fast``, 65536 for ``balanced``, all of it for ``accurate``, and
:data:`recovery.DEFAULT_ANALYSIS_PIXELS` (250,000) when no quality is given.
"""

from __future__ import annotations

from recovery import estimate_illuminant  # noqa: F401 (re-exported)
from recovery.synthesis import correction_matrix as _recovery_correction_matrix, display_curve  # noqa: F401

from .correction import (CHUNK_PIXELS, Correction, _encoding_lut, _highlight_code, apply_matrix_inplace,  # noqa: F401
                         chunk_rows)
from .estimation import (AS_SHOT_WARN_DEG, LITERAL_FIT_TOLERANCE, LITERAL_NULL_RATIO, NEUTRAL_LOW_SIGNAL,  # noqa: F401
                         VISIBLE_WB_ERROR_DEG, EstimateRun, generic_cross_check, method_failure, neutral_white,
                         run_estimate, run_with_white, with_neutral)
from .image_files import _SparseFile, _tiff_kwargs, _with_meta, encode_image, tiff_head  # noqa: F401
from .opening import (_full_linear_u16, analyze, analyze_file, decode, drain_prefetch, open_image,  # noqa: F401
                      prefetch_full_linear)
from .options import FORMATS, MEDIA_TYPES, Format  # noqa: F401
from .rendering import (NOT_A_RAW, STRIP_ENCODERS, _estimation_image, correction_matrix, crop_bounds,  # noqa: F401
                        default_crop, dng_possible, exposure_gain, output_meta, render_corrected, render_encoded,
                        render_full, white_balanced_dng, write_corrected, xmp_sidecar)
from .report import (MATRIX_COLORIMETRY, _temperature_tint_xy, analysis_json, camera_json, confidence_json, estimate_summary,  # noqa: F401
                     illuminant_json, light_cct_duv, light_map_json, light_xy, lights_json, profile_of,
                     rendering_choice, rendering_json, temperature_tint)
from .surfaces import BOX_STRIP_ROWS, _box, _box_sums, box_sums_streamed, surfaces_at  # noqa: F401
