"""The service's glue: decoded upload -> estimate -> JSON / corrected image.

Thin by design: every number comes from :mod:`recovery`; this module only
chooses resolutions, applies the one 3x3 matrix per pixel (Wandell 1985,
Fig. 6: for a fixed light camera RGB to display RGB is one matrix) in
chunks, and encodes.
"""

from __future__ import annotations

import io
import time
from dataclasses import dataclass, field

import numpy as np

from models import illuminant as get_illuminant
from recovery import Camera, IlluminantEstimate, angular_error, estimate_illuminant
from recovery.api import resolve_model, surfaces_from_estimate
from recovery.resolution import block_average
from recovery.synthesis import output_space, synthesis_matrix

from .errors import ApiError

#: Estimation runs on at most this many pixels (block-averaged; the
#: subspace method is unchanged by averaging because mixtures of surfaces
#: under one light stay in the same subspace, eq. 29).
ANALYSIS_PIXELS = 250_000


@dataclass
class EstimateRun:
    estimate: IlluminantEstimate
    camera: Camera
    camera_warnings: list
    timings_ms: dict = field(default_factory=dict)
    factor: int = 1


def run_estimate(decoded, camera: Camera, camera_warnings: list, *, method: str, options: dict,
                 analysis_pixels: int = ANALYSIS_PIXELS) -> EstimateRun:
    """Estimate the light on the (block-averaged) estimation image of an
    upload, saturated cells excluded."""
    t0 = time.perf_counter()
    img, mask, f = block_average(decoded.estimation, ~decoded.saturated, analysis_pixels)
    est = estimate_illuminant(img, camera, method, mask=mask, **options)
    t1 = time.perf_counter()
    return EstimateRun(est, camera, list(camera_warnings), {"estimate": (t1 - t0) * 1e3}, f)


def illuminant_json(est: IlluminantEstimate) -> dict:
    cct, duv = est.cct_duv()
    return {
        "camera_rgb": est.rgb.tolist(),
        "wb_multipliers": est.wb_multipliers.tolist(),
        "wavelengths": est.wavelengths.tolist(),
        "spectrum": est.spectrum.tolist(),
        "cct": cct,
        "duv": duv,
    }


def camera_json(camera: Camera) -> dict:
    return {"name": camera.name, "source": camera.source, "channels": camera.channels,
            "approximate": camera.source in ("matrix-derived", "generic"), "notes": list(camera.notes)}


def analysis_json(run: EstimateRun, decoded) -> dict:
    est = run.estimate
    out = {
        "illuminant": illuminant_json(est),
        "camera": camera_json(run.camera),
        "method": est.method,
        "diagnostics": dict(est.diagnostics, analysis_block_factor=run.factor),
        "warnings": run.camera_warnings + list(decoded.warnings) + list(est.warnings),
        "timings_ms": dict(run.timings_ms),
        "image": {"kind": decoded.kind, "width": decoded.full_shape[1], "height": decoded.full_shape[0],
                  "make": decoded.make, "model": decoded.model},
    }
    lm = est.light_map
    if lm is not None:  # the light at the map's centres, as fractions of the image height and width
        rr, cc = np.meshgrid(lm.centres_r, lm.centres_c, indexing="ij")
        rgb = run.camera.response(lm.spectra_at(rr.ravel(), cc.ravel()))
        rgb = rgb / np.linalg.norm(rgb, axis=1, keepdims=True)
        eh, ew = decoded.estimation.shape[:2]
        out["light_map"] = {"centres_row_fraction": ((lm.centres_r + 0.5) * run.factor / eh).tolist(),
                            "centres_col_fraction": ((lm.centres_c + 0.5) * run.factor / ew).tolist(),
                            "camera_rgb": rgb.reshape(rr.shape + (-1,)).tolist()}
    if decoded.as_shot_neutral is not None and np.all(np.isfinite(decoded.as_shot_neutral)):
        asn = np.asarray(decoded.as_shot_neutral, float)
        out["as_shot"] = {"camera_rgb": (asn / np.linalg.norm(asn)).tolist(),
                          "angle_to_estimate_deg": float(angular_error(asn, est.rgb))}
    return out


def correction_matrix(run: EstimateRun, target: str, output: str, surface_model: str | None = None
                      ) -> tuple[np.ndarray, dict]:
    """Camera RGB (1.0 = saturation) -> linear display values.

    ``M = Gamma^{-1} Lambda'_{E'} Lambda_E^{-1}`` (eq. 23 and 36 with a
    surface model of as many terms as sensors), scaled so that the
    brightest neutral the sensor records unclipped (the light's own camera
    RGB with its largest channel at saturation) renders with luminance 1:
    a fixed exposure, no auto-brightening. The surface model has C terms
    of ``surface_model`` (default PCA of the shipped reflectances).
    """
    cam, est = run.camera, run.estimate
    try:
        space = output_space(output, cam.wavelengths)
    except (ValueError, KeyError) as e:
        raise ApiError(422, "invalid_parameter", f"output: {e}") from None
    try:
        tgt = est.spectrum if target in ("estimate", "as-seen") else get_illuminant(target, cam.wavelengths)
    except KeyError as e:
        raise ApiError(422, "invalid_parameter", f"target: {e.args[0]}") from None
    S = resolve_model(surface_model, "surface", cam.channels, cam.wavelengths).basis
    M, cond = synthesis_matrix(cam.sensitivities, cam.wavelengths, est.spectrum, tgt, S, space)
    white = est.rgb / np.max(est.rgb)
    y = (M @ white)
    lum = float(y[1]) if space.Gamma is None else float((space.Gamma @ y)[1])
    if not (np.isfinite(lum) and lum > 0):
        raise ApiError(422, "unrenderable", "the estimated light renders white with no luminance")
    return M / lum, {"lighting_condition": cond, "encoding": space.encoding}


def _encoding_lut(encoding: str | None, bits: int) -> np.ndarray:
    """16-bit linear code -> encoded ``bits``-bit code, through
    colour-science's ``cctf_encoding`` of the colourspace."""
    import colour

    x = np.arange(65536) / 65535.0
    y = x if encoding is None else np.asarray(colour.RGB_COLOURSPACES[encoding].cctf_encoding(x), float)
    top = 65535.0 if bits == 16 else 255.0
    return np.rint(np.clip(y, 0, 1) * top).astype(np.uint16 if bits == 16 else np.uint8)


def apply_matrix_inplace(rgb16: np.ndarray, M: np.ndarray, encoding: str | None, bits: int,
                         rows_per_chunk: int = 256, threads: int | None = None) -> np.ndarray:
    """Apply ``M`` to a uint16 (H, W, 3) image whose 65535 is saturation and
    encode it, chunk by chunk on a few threads.

    OpenCV's ``transform`` applies the 3x3 matrix per pixel and saturates
    to [0, 65535] (Wandell's first gamut option: clip per pixel); a 65536-
    entry table then applies the transfer function. The 16-bit linear
    intermediate costs at most 13 codes of a 16-bit sRGB output in the
    deepest shadows (the sRGB toe has slope 12.92), nothing in 8-bit output.
    uint16 output reuses the input buffer (memory stays at one image).
    """
    import os
    from concurrent.futures import ThreadPoolExecutor

    import cv2

    lut = _encoding_lut(encoding, bits)
    out = rgb16 if bits == 16 else np.empty(rgb16.shape, np.uint8)
    Mt = np.asarray(M, np.float32)

    def work(r):
        lin = cv2.transform(rgb16[r:r + rows_per_chunk], Mt)
        np.take(lut, lin, out=out[r:r + rows_per_chunk])

    n = threads or min(4, os.cpu_count() or 1)
    with ThreadPoolExecutor(n) as pool:
        list(pool.map(work, range(0, rgb16.shape[0], rows_per_chunk)))
    return out


FORMATS = {"png": "image/png", "tiff": "image/tiff", "jpeg": "image/jpeg"}


def encode_image(img: np.ndarray, fmt: str, path: str | None = None) -> bytes | None:
    """PNG (8-bit or 16-bit), 16-bit TIFF or 8-bit JPEG of an RGB image, as
    bytes, or written to ``path`` (TIFF straight from the array, no copy)."""
    if fmt == "tiff":
        import tifffile

        if path is not None:
            tifffile.imwrite(path, img, photometric="rgb")
            return None
        buf = io.BytesIO()
        tifffile.imwrite(buf, img, photometric="rgb")
        return buf.getvalue()
    import cv2

    bgr = np.ascontiguousarray(img[..., ::-1])
    ok, enc = cv2.imencode(".png" if fmt == "png" else ".jpg", bgr,
                           [cv2.IMWRITE_JPEG_QUALITY, 95] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ApiError(422, "encode_failed", f"could not encode {fmt}")
    if path is not None:
        enc.tofile(path)
        return None
    return enc.tobytes()


def _box_sums(a: np.ndarray) -> np.ndarray:
    """Summed-area table of ``a`` (H, W[, C]) with a zero first row and
    column: the sum over rows r0..r1-1, columns c0..c1-1 is
    ``S[r1, c1] - S[r0, c1] - S[r1, c0] + S[r0, c0]``."""
    S = np.zeros((a.shape[0] + 1, a.shape[1] + 1) + a.shape[2:], np.float64)
    np.cumsum(a, axis=0, dtype=np.float64, out=S[1:, 1:])
    np.cumsum(S[1:, 1:], axis=1, out=S[1:, 1:])
    return S


def _box(S: np.ndarray, r0, c0, r1, c1) -> np.ndarray:
    return S[r1, c1] - S[r0, c1] - S[r1, c0] + S[r0, c0]


def surfaces_at(decoded, run: EstimateRun, points, rects, grid, options: dict) -> dict:
    """Reflectance spectra (eq. 36 with a C-term surface model) at full-
    resolution pixel points, rectangle means, or a coarse grid.

    The cost is bounded whatever the rectangles: a rectangle's mean camera
    RGB comes from a summed-area table of the estimation image (built once,
    four look-ups per rectangle), and for one light eq. 36 is linear in the
    camera RGB (sigma = L^+ rho), so the reflectance of the mean RGB is the
    mean of the pixels' reflectances. All entries are then solved in one
    vectorised step."""
    img = decoded.estimation
    h, w = img.shape[:2]
    H, W = decoded.full_shape
    sy, sx = h / H, w / W
    # the light estimated once (run.estimate) serves the surfaces too
    res = surfaces_from_estimate(img, run.camera, run.estimate, synthesis_basis=options.get("surface_basis"))

    def to_est(r, c):
        if not (0 <= r < H and 0 <= c < W):
            raise ApiError(422, "invalid_parameter", f"point ({r}, {c}) outside the {H}x{W} image")
        return min(int(r * sy), h - 1), min(int(c * sx), w - 1)

    kinds, wheres, rows, cols = [], [], [], []
    for r, c in points:
        a, b = to_est(r, c)
        kinds.append("point"), wheres.append([r, c]), rows.append((a, a + 1)), cols.append((b, b + 1))
    for r0, c0, r1, c1 in rects:
        if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
            raise ApiError(422, "invalid_parameter", f"rectangle {[r0, c0, r1, c1]} must satisfy "
                           f"0 <= r0 < r1 <= {H} and 0 <= c0 < c1 <= {W}")
        a0, b0 = to_est(r0, c0)
        a1, b1 = to_est(r1 - 1, c1 - 1)
        kinds.append("rect"), wheres.append([r0, c0, r1, c1]), rows.append((a0, a1 + 1)), cols.append((b0, b1 + 1))
    if grid:
        gr, gc = grid
        for i in range(gr):
            for j in range(gc):
                r = int((i + 0.5) * H / gr)
                c = int((j + 0.5) * W / gc)
                a, b = to_est(r, c)
                kinds.append("grid"), wheres.append([r, c]), rows.append((a, a + 1)), cols.append((b, b + 1))
    entries = []
    if kinds:
        r0, r1 = np.asarray(rows, np.intp).T
        c0, c1 = np.asarray(cols, np.intp).T
        finite = np.all(np.isfinite(img), axis=2)
        data = np.where(finite[..., None], img, 0.0)
        n = ((r1 - r0) * (c1 - c0)).astype(float)
        rho = _box(_box_sums(data), r0, c0, r1, c1) / n[:, None]
        bad = _box(_box_sums(~finite), r0, c0, r1, c1) > 0
        if bad.any():
            k = int(np.argmax(bad))
            raise ApiError(422, "invalid_parameter", f"{kinds[k]} {wheres[k]} covers non-finite pixel values: "
                           "no reflectance there")
        sat = _box(_box_sums(np.asarray(decoded.saturated, bool)), r0, c0, r1, c1) > 0
        # the light at each entry's centre (one light: the same everywhere)
        L = res._lighting((r0 + r1 - 1) / 2.0, (c0 + c1 - 1) / 2.0)
        weights = np.einsum("pjk,pk->pj", np.linalg.pinv(L), rho) * res.reflectance_scale
        refl = weights @ res.surface_model.basis.T
        fit = res.illuminant.diagnostics.get("subspace_fit_ratio")
        for kind, where, r, s_ in zip(kinds, wheres, refl, sat):
            warns = []
            if np.any(r < -0.02):
                warns.append(f"non-physical: reflectance below 0 (min {r.min():.3f})")
            if np.any(r > 1.02):
                warns.append(f"non-physical: reflectance above 1 (max {r.max():.3f}); the scale is relative")
            if s_:
                warns.append("saturated pixels: the estimate is clipped")
            if fit is not None and fit > 0.1:
                warns.append("poor subspace fit for the scene (see diagnostics)")
            entries.append({"kind": kind, "where": where, "reflectance": r.tolist(), "warnings": warns})
    return {"wavelengths": run.camera.wavelengths.tolist(), "surfaces": entries,
            "surface_model": res.diagnostics.get("surface_model"),
            "reflectance_scale_convention": res.diagnostics.get("reflectance_scale_convention"),
            "diagnostics": res.diagnostics}
