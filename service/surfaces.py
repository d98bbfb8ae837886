"""Reflectance spectra at points, rectangles or a grid of an image under
its estimated light (``/v1/surfaces``; :mod:`service.pipeline` re-exports
:func:`surfaces_at`)."""

from __future__ import annotations

import numpy as np

from recovery.api import surfaces_from_estimate

from .errors import ServiceError
from .estimation import EstimateRun


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
            raise ServiceError(422, "invalid_parameter", f"point ({r}, {c}) outside the {H}x{W} image")
        return min(int(r * sy), h - 1), min(int(c * sx), w - 1)

    kinds, wheres, rows, cols = [], [], [], []
    for r, c in points:
        a, b = to_est(r, c)
        kinds.append("point"), wheres.append([r, c]), rows.append((a, a + 1)), cols.append((b, b + 1))
    for r0, c0, r1, c1 in rects:
        if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
            raise ServiceError(422, "invalid_parameter", f"rectangle {[r0, c0, r1, c1]} must satisfy "
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
            raise ServiceError(422, "invalid_parameter", f"{kinds[k]} {wheres[k]} covers non-finite pixel values: "
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
