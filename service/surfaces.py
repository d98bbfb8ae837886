"""Reflectance spectra with error bars at points, rectangles or a grid of an
image under its estimated light (``/v1/surfaces``; :mod:`service.pipeline`
re-exports :func:`surfaces_at`; the estimator is :mod:`recovery.surface_prior`,
issue 31)."""

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


#: rows of the image summed at a time by :func:`box_sums_streamed`
BOX_STRIP_ROWS = 64


def box_sums_streamed(layers, h: int, w: int, r0, c0, r1, c1, strip: int = BOX_STRIP_ROWS) -> np.ndarray:
    """The sums of ``layers`` over the boxes rows ``r0..r1-1``, columns
    ``c0..c1-1``: what :func:`_box` gives from the summed-area table
    :func:`_box_sums`, with the table's values computed only at the boxes'
    corners, ``strip`` rows at a time. ``layers(a, b)`` returns rows
    ``a..b-1`` as ``(b - a, w, K)`` float64. The whole table of a 30 MP
    image (float64, three channels and the masks: some 1.5 GB with its
    temporaries) is never held: at most ``strip x (w + 1) x K`` of it (issue
    28: ``/v1/surfaces`` took 95 MiB per megapixel).

    The table's row ``r`` is the running sum over image rows ``< r`` of each
    row's cumulative sum along the columns; a corner ``(r, c)`` is read from
    it when the running sum reaches row ``r``."""
    r0, c0, r1, c1 = (np.asarray(v, np.intp) for v in (r0, c0, r1, c1))
    R = np.concatenate([r1, r0, r1, r0])
    C = np.concatenate([c1, c1, c0, c0])
    sign = np.repeat([1.0, -1.0, -1.0, 1.0], r0.size)
    vals = None
    acc = None
    for a in range(0, h, strip):
        b = min(h, a + strip)
        want = (R > a) & (R <= b)
        x = layers(a, b)
        if vals is None:
            vals = np.zeros((R.size, x.shape[2]))
            acc = np.zeros((w + 1, x.shape[2]))
        if not want.any():
            acc[1:] += np.cumsum(x.sum(axis=0), axis=0)
            continue
        cs = np.zeros((b - a, w + 1, x.shape[2]))
        np.cumsum(x, axis=1, out=cs[:, 1:])
        np.cumsum(cs, axis=0, out=cs)
        cs += acc
        k = np.flatnonzero(want)
        vals[k] = cs[R[k] - a - 1, C[k]]
        acc = cs[-1].copy()
    if vals is None:
        return np.zeros((r0.size, 0))
    return (sign[:, None] * vals).reshape(4, r0.size, -1).sum(axis=0)


#: What ``metamer_lower`` / ``metamer_upper`` / ``metamer_slack`` mean (the answer's ``metamers``).
METAMERS_DOC = ("metamer_lower / metamer_upper: at each wavelength the least and greatest reflectance of any "
                "reflectance in [0, 1] that gives the surface's response under the estimated light (the map's "
                "light at its pixel) and the nominal camera, within 2 standard deviations of the response's noise "
                "per channel, on the reflectance's scale (Finlayson & Morovic 2005, metamer sets; linear "
                "programmes). It assumes nothing about what surfaces are like: where it is narrow the data fix the "
                "reflectance, where it spans [0, 1] only the prior does. The light's and the camera's own "
                "uncertainty do not widen it (they widen reflectance_std). metamer_scale > 1: the response is that "
                "many times brighter than the brightest reflectance of its colour at this exposure (the scale is "
                "relative), and the range is that of its dimmest copy that fits, multiplied back. metamer_slack > "
                "0: no reflectance gives its colour under the light; the range is that of the tolerance grown "
                "(1 + slack)-fold")
#: What the range holds with ``metamer_model=measured`` (appended to :data:`METAMERS_DOC`).
METAMERS_MEASURED_DOC = ("metamer_model=measured: only reflectances like measured surfaces (Finlayson & Morovic "
                         "2005 bound metamer sets to a linear model of measured reflectances): a 5-term model of the "
                         "274 shipped measured reflectances, each wavelength allowed the 95th percentile of the residual "
                         "they leave outside it, within [0, 1]; about half as wide as the physical range, and it held "
                         "99 % or more of the true values of every reflectance set left out of the model "
                         "(docs/surfaces.md, benchmarks.metamers --model-cv); metamer_slack > 0 then says no such "
                         "reflectance gives the colour")


def surfaces_at(decoded, run: EstimateRun, points, rects, grid, options: dict, metamers: bool = False,
                metamer_model: str = "physical") -> dict:
    """Reflectance spectra at full-resolution pixel points, rectangle means,
    or a coarse grid: the prior's posterior mean with a band per wavelength
    and an expected RMS error (:mod:`recovery.surface_prior`), or eq. 36 with
    a C-term surface model when the request names a surface model.

    The cost is bounded whatever the rectangles: a rectangle's mean camera
    RGB comes from a summed-area table of the estimation image (built once,
    four look-ups per rectangle), and a rectangle's reflectance is the
    estimate of its mean RGB (for eq. 36, linear in the camera RGB, that is
    also the mean of its pixels' reflectances; the prior's mixture posterior
    is not linear: there it is the estimate of the surface the rectangle's
    pixels average to). All entries are then solved in one
    vectorised step.

    ``metamers``: also each entry's metamer set, the least and greatest
    reflectance at each wavelength of any physical reflectance giving its
    response (:meth:`recovery.api.AnalysisResult.metamers_from_responses`;
    at most :data:`recovery.api.METAMER_POINTS` entries, checked by the
    caller); ``metamer_model``: ``physical`` (any reflectance in [0, 1]) or
    ``measured`` (:func:`recovery.api.measured_surface_model`)."""
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
        saturated = np.asarray(decoded.saturated, bool)
        C = img.shape[2]

        def layers(a, b):
            """Rows a..b-1: the RGB with non-finite pixels as 0, a non-finite flag, the saturation flag."""
            x = np.empty((b - a, w, C + 2))
            part = img[a:b]
            finite = np.all(np.isfinite(part), axis=2)
            x[..., :C] = np.where(finite[..., None], part, 0.0)
            x[..., C] = ~finite
            x[..., C + 1] = saturated[a:b]
            return x

        sums = box_sums_streamed(layers, h, w, r0, c0, r1, c1)
        n = ((r1 - r0) * (c1 - c0)).astype(float)
        rho = sums[:, :C] / n[:, None]
        bad = sums[:, C] > 0
        if bad.any():
            k = int(np.argmax(bad))
            raise ServiceError(422, "invalid_parameter", f"{kinds[k]} {wheres[k]} covers non-finite pixel values: "
                           "no reflectance there")
        sat = sums[:, C + 1] > 0
        # the light at each entry's centre (one light: the same everywhere)
        rows_c, cols_c = (r0 + r1 - 1) / 2.0, (c0 + c1 - 1) / 2.0
        if res.surface_estimator == "prior":
            # a rectangle: the estimate of its mean RGB (the mixture posterior is not linear in it)
            pe = res.estimates_from_responses(rho, rows_c, cols_c)
            refl, stds, ermse = pe.mean, pe.std, pe.expected_rmse
        else:
            L = res._lighting(rows_c, cols_c)
            weights = np.einsum("pjk,pk->pj", np.linalg.pinv(L), rho) * res.reflectance_scale
            refl = weights @ res.surface_model.basis.T
            stds, ermse = [None] * len(kinds), [None] * len(kinds)
        mr = res.metamers_from_responses(rho, rows_c, cols_c, metamer_model) if metamers else None
        fit = res.illuminant.diagnostics.get("subspace_fit_ratio")
        for i, (kind, where, r, s_, sd, er) in enumerate(zip(kinds, wheres, refl, sat, stds, ermse)):
            warns = []
            if np.any(r < -0.02):
                warns.append(f"non-physical: reflectance below 0 (min {r.min():.3f})")
            if np.any(r > 1.02):
                warns.append(f"non-physical: reflectance above 1 (max {r.max():.3f}); the scale is relative")
            if s_:
                warns.append("saturated pixels: the estimate is clipped")
            if fit is not None and fit > 0.1:
                warns.append("poor subspace fit for the scene (see diagnostics)")
            entry = {"kind": kind, "where": where, "reflectance": r.tolist(), "warnings": warns,
                     "reflectance_std": None if sd is None else sd.tolist(),
                     "expected_rmse": None if er is None else float(er)}
            if mr is not None:
                entry.update(metamer_lower=mr.lower[i].tolist(), metamer_upper=mr.upper[i].tolist(),
                             metamer_slack=float(mr.slack[i]), metamer_scale=float(mr.scale[i]))
                if mr.slack[i] > 0:
                    which = "no reflectance like measured surfaces" if metamer_model == "measured" else "no reflectance"
                    warns.append(f"{which} gives this colour under the estimated light (the tolerance had "
                                 f"to grow {1 + mr.slack[i]:.3g}-fold): the light or the camera is wrong here"
                                 + (", or the surface is unlike the measured ones" if metamer_model == "measured"
                                    else ""))
                elif mr.scale[i] > 1:
                    warns.append(f"brighter than a perfect white of its colour at the surfaces' exposure (x"
                                 f"{mr.scale[i]:.3g}; the reflectance scale is relative): the metamer range is "
                                 "that of the brightest reflectances of this colour, on this scale")
            entries.append(entry)
    return {"wavelengths": run.camera.wavelengths.tolist(), "surfaces": entries,
            "surface_estimator": res.surface_estimator,
            "band": ("reflectance_std: the posterior standard deviation per wavelength times a factor "
                     "calibrated, per wavelength and per kind of camera (measured, matrix-derived, generic) and "
                     "light, on reflectance sets left out (benchmarks.surfaces, docs/surfaces.md): reflectance "
                     "+- 1.645 reflectance_std is a 90 % band (diagnostics.surface_band_calibration names the "
                     "factors used); expected_rmse: the RMS of that band, the error the model expects for the "
                     "surface"
                     if res.surface_estimator == "prior" else
                     "none: the literal method (eq. 36, pseudo-inverse in the surface model) has no band"),
            **({"metamers": METAMERS_DOC + ("; " + METAMERS_MEASURED_DOC if metamer_model == "measured" else "")}
               if metamers else {}),
            "surface_model": res.diagnostics.get("surface_model"),
            "reflectance_scale_convention": res.diagnostics.get("reflectance_scale_convention"),
            "diagnostics": res.diagnostics}


def regions_of(regions, max_regions: int) -> tuple[list, list, tuple | None]:
    """The points, rectangles and grid of ``regions`` (a
    :class:`service.schemas.options.Regions`), within the limits a request
    and ``wandell surfaces`` share: at least one region (422
    ``invalid_parameter``), at most ``max_regions`` points, rectangles and
    grid cells together (``WANDELL_MAX_SURFACE_REGIONS``) and, with
    ``metamers``, at most :data:`recovery.api.METAMER_POINTS` (413
    ``too_many_regions``)."""
    from recovery.api import METAMER_POINTS

    pts, rcs, grd = regions.points or [], regions.rects or [], regions.grid
    if not (pts or rcs or grd):
        raise ServiceError(422, "invalid_parameter", "give at least one of points, rects or grid")
    n_regions = len(pts) + len(rcs) + (grd[0] * grd[1] if grd else 0)
    if n_regions > max_regions:
        raise ServiceError(413, "too_many_regions", f"{n_regions} points, rectangles and grid cells; at most "
                           f"{max_regions} per request (WANDELL_MAX_SURFACE_REGIONS)")
    if regions.metamers and n_regions > METAMER_POINTS:
        raise ServiceError(413, "too_many_regions", f"metamers=true for {n_regions} points, rectangles and grid "
                           f"cells; at most {METAMER_POINTS} per request with metamers (two linear programmes per "
                           "wavelength each)")
    return pts, rcs, grd


def surfaces_answer(decoded, run: EstimateRun, regions, where, options: dict) -> dict:
    """The whole answer of ``POST /v1/surfaces`` and ``wandell surfaces``:
    :func:`surfaces_at` at ``where`` (the points, rectangles and grid
    :func:`regions_of` gave for ``regions``, checked before the file was
    read), the light, method, camera, warnings, the lights found and the
    light map."""
    from .report import camera_json, illuminant_json, light_map_json, lights_json, profile_of

    pts, rcs, grd = where
    res = surfaces_at(decoded, run, pts, rcs, grd, options, metamers=regions.metamers,
                      metamer_model=regions.metamer_model)
    res["illuminant"] = illuminant_json(run.estimate, profile_of(decoded), run.camera)
    res["method"] = run.estimate.method
    res["camera"] = camera_json(run.camera)
    res["warnings"] = run.camera_warnings + list(decoded.warnings) + list(run.estimate.warnings)
    res["lights"] = lights_json(run.estimate, "light_map gives the light across the frame, and each "
                                              "surface is estimated under the map's light at its pixel")
    light_map = light_map_json(run, decoded)
    if light_map is not None:   # found 2 always comes with the map it used (probe round 4)
        res["light_map"] = light_map
    return res


def surfaces_csv(res: dict) -> str:
    """``format=csv``: a row per surface (kind, where, warnings, the
    reflectance at each wavelength), then its band: ``expected_rmse`` and
    the standard deviation at each wavelength (``std <nm>``; empty for eq. 36);
    with ``metamers=true`` then ``metamer_slack``, ``metamer_scale`` and the
    metamer set's least and greatest reflectance at each wavelength (``min
    <nm>``, ``max <nm>``)."""
    import csv
    import io

    buf = io.StringIO()
    w = csv.writer(buf)
    wl = [f"{x:g}" for x in res["wavelengths"]]
    metamers = "metamers" in res
    w.writerow(["kind", "where", "warnings"] + wl + ["expected_rmse"] + [f"std {x}" for x in wl]
               + (["metamer_slack", "metamer_scale"] + [f"min {x}" for x in wl] + [f"max {x}" for x in wl]
                  if metamers else []))
    for s in res["surfaces"]:
        std, rmse = s.get("reflectance_std"), s.get("expected_rmse")
        w.writerow([s["kind"], " ".join(map(str, s["where"])), "; ".join(s["warnings"])]
                   + [f"{v:.6g}" for v in s["reflectance"]] + ["" if rmse is None else f"{rmse:.6g}"]
                   + ([f"{v:.6g}" for v in std] if std is not None else [""] * len(wl))
                   + ([f"{s['metamer_slack']:.6g}", f"{s['metamer_scale']:.6g}"] + [f"{v:.6g}" for v in s["metamer_lower"]]
                      + [f"{v:.6g}" for v in s["metamer_upper"]] if metamers else []))
    return buf.getvalue()
