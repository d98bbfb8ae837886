"""One light or a light map: decide from the scene's own evidence.

Two kinds of evidence, each able to say "the light varies":

1. **A chromaticity trend inside surfaces** (smooth light changes). Wandell
   (1985 [docs/references.md#seed-002], 'A condition on spatial variation') assumes
   the light varies slowly across the image while surfaces change abruptly;
   Land & McCann's retinex (1971) and Horn (1974) separate the two the same
   way: small steps between neighbouring pixels belong to the light, large
   ones to surface edges. In the centred log-ratio chromaticity ``u = H log
   rho`` (:func:`recovery.bayes.helmert`) shading cancels, and a light
   change is a shift of ``u`` (the diagonal model, Drew & Finlayson, seed
   ``003``). So under one light the differences of ``u`` between
   neighbouring pixels of one surface are pure noise with mean zero, and
   under a light that changes smoothly they have the mean ``g`` (the light's
   chromaticity gradient per pixel). :func:`chromaticity_trend` estimates
   ``g`` along rows and columns from the neighbour pairs whose difference is
   within ``kappa`` robust standard deviations of the noise (same surface),
   with a standard error that respects the telescoping of differences along
   a run of one surface (the sum over a run is ``u_end - u_start``: its
   variance is that of one difference, whatever the run's length). The
   trend decides when it is both significant (chi-square, ``p <
   10**TREND_LOG10_P``) and large enough to matter (the light's direction
   changes by more than ``TREND_MIN_EFFECT_DEG`` across the image).

2. **Regions that disagree about the light** (abrupt changes, e.g. sun and
   shade). The light posterior of :mod:`recovery.bayes` is computed in each
   region of a grid; its per-candidate likelihoods ``L_r(m)`` combine into
   the Bayes factor of "independent lights per region" against "one light
   for all":

   .. math:: \\log B = \\sum_r \\log \\sum_m \\pi_m e^{L_r(m)}
             - \\log \\sum_m \\pi_m e^{\\sum_r L_r(m)}

   with the candidates' prior ``pi``. Regions with few surfaces have flat
   likelihoods and so add no evidence either way (the false alarms of a
   plain comparison of region estimates came from them). The regions'
   likelihoods count each distinct colour once (``coarse`` clustering of
   :func:`recovery.bayes.estimate_bayes`): without it a noisy surface
   spreads over many chromaticity cells, each counted as a surface, and the
   likelihoods are too sharp (measured: a map chosen in most uniform
   scenes). A map is chosen when ``log B > LOG_BF_THRESHOLD`` (0: the map is
   more probable than one light at even prior odds).

References
----------
Wandell (1985) [docs/references.md#seed-002]: Fig. 1 and 'A condition on spatial
variation' (overlapping regions, light constant within a region, slowly
varying across the image). Land & McCann (1971), Lightness and retinex
theory, JOSA 61(1); Horn (1974), Determining lightness from an image, CGIP
3. Drew & Finlayson (2003) [docs/references.md#seed-003] (diagonal model of light change).
Kass & Raftery (1995), Bayes factors, JASA 90 (the scale of log B).
"""

from __future__ import annotations

import numpy as np

from .bayes import estimate_bayes, helmert, modulated_spectrum
from .errors import InputError
from .metrics import angular_error
from .regions import LightMap

__all__ = ["SPATIAL_MODES", "parse_spatial", "chromaticity_trend", "region_posteriors", "log_bayes_factor",
           "choose_light_model", "TREND_LOG10_P", "TREND_MIN_EFFECT_DEG", "LOG_BF_THRESHOLD"]

#: Accepted values of ``spatial``: booleans and their names pin the choice.
SPATIAL_MODES = ("auto", "map", "uniform")
#: The trend must be significant at p < 10**TREND_LOG10_P (chi-square) ...
TREND_LOG10_P = -6.0
#: ... and change the light's direction by more than this across the image:
#: below it one light is off by at most half of it anywhere, under the
#: default estimator's own median error on the development scenes.
TREND_MIN_EFFECT_DEG = 2.0
#: A map from region posteriors when log B exceeds this (even prior odds).
LOG_BF_THRESHOLD = 0.0


def parse_spatial(value) -> str:
    """``spatial`` option -> ``"auto"``, ``"map"`` or ``"uniform"``.

    Accepts ``True``/``False``, ``"auto"``, ``"map"``, ``"uniform"`` and the
    strings ``"true"``/``"false"`` (any case, as a form field sends them).

    >>> parse_spatial(True), parse_spatial("false"), parse_spatial("auto")
    ('map', 'uniform', 'auto')
    """
    if value is True or value is False or isinstance(value, np.bool_):
        return "map" if value else "uniform"
    if isinstance(value, str):
        v = value.strip().lower()
        alias = {"true": "map", "1": "map", "yes": "map", "on": "map",
                 "false": "uniform", "0": "uniform", "no": "uniform", "off": "uniform"}
        v = alias.get(v, v)
        if v in SPATIAL_MODES:
            return v
    raise InputError(f"spatial must be auto, true (a light map), false (one light), map or uniform; "
                     f"not {value!r}")


def chi2_logsf(x: float, dof: int) -> float:
    """``scipy.stats.chi2.logsf(x, dof)``, bit for bit, from
    ``scipy.special`` alone: scipy.stats took 0.4-1 s to import in every
    fresh process that reached it (the command line's light posterior,
    issue 19). The same formulas as scipy's generic ``logsf``: 0 at and
    below 0, ``log(sf)`` above the median, ``log1p(-cdf)`` up to it
    (``tests/test_spatial.py`` compares the two)."""
    from scipy import special

    x = float(x)
    if x != x:
        return float("nan")
    if x <= 0.0:
        return 0.0
    if x == float("inf"):
        return float("-inf")
    with np.errstate(divide="ignore"):
        if x > 2 * special.gammaincinv(dof / 2, 0.5):
            return float(np.log(special.chdtrc(dof, x)))
        return float(np.log1p(-special.chdtr(dof, x)))


def chromaticity_trend(image: np.ndarray, mask: np.ndarray | None = None, *, dark_fraction: float = 0.02,
                       kappa: float = 4.0, reference_rgb=None, min_pairs: int = 64) -> dict:
    """The light's chromaticity gradient from within-surface differences.

    Parameters
    ----------
    image : (H, W, C) linear camera data
    mask : (H, W) usable pixels (default all finite)
    dark_fraction : pixels with a channel at or below this fraction of the
        brightest value are left out (their log is noise)
    kappa : neighbour pairs with every component of ``|du|`` below ``kappa``
        robust standard deviations count as one surface
    reference_rgb : the light the effect size is measured from (default
        neutral)

    Returns
    -------
    dict of plain numbers: ``gradient_row``, ``gradient_col`` (per pixel,
    in ``u`` units) and their standard errors ``se_row``, ``se_col``, ``chi2``, ``dof``, ``log10_p``, ``effect_deg`` (largest
    change of the light's direction between opposite corners),
    ``pairs``, ``runs``, ``noise`` (robust sd of ``du``), ``defined``.
    """
    img = np.asarray(image, dtype=np.float64)
    h, w, C = img.shape
    Hm = helmert(C)
    ok = np.all(np.isfinite(img), axis=2)
    if mask is not None:
        ok &= np.asarray(mask, bool)
    vals = img[ok]
    top = float(vals.max()) if vals.size else 0.0
    out = {"defined": False, "chi2": 0.0, "dof": 2 * (C - 1), "log10_p": 0.0, "effect_deg": 0.0,
           "pairs": 0, "runs": 0}
    if not top > 0:
        out["reason"] = "no positive pixels"
        return out
    with np.errstate(invalid="ignore"):
        ok &= np.all(img > dark_fraction * top, axis=2)
    u = np.log(np.where(ok[..., None], img, 1.0)) @ Hm.T               # (H, W, C-1)
    grads, ses, chi2, pairs, runs, noise = [], [], 0.0, 0, 0, []
    for ax in (0, 1):
        grads.append(np.zeros(C - 1))
        ses.append(np.full(C - 1, np.inf))
        if img.shape[ax] < 2:
            continue
        d = np.diff(u, axis=ax)
        pv = (ok[1:] & ok[:-1]) if ax == 0 else (ok[:, 1:] & ok[:, :-1])
        if pv.sum() < min_pairs:
            continue
        # robust noise of a difference; at least 0.1 % (log units), so an
        # image with repeated pixels (upsampled) does not make every
        # difference an edge
        sig = np.maximum(np.median(np.abs(d[pv]), axis=0) / 0.6745, 1e-3)
        same = pv & np.all(np.abs(d) < kappa * sig, axis=-1)
        n = int(same.sum())
        if n < min_pairs:
            continue
        prev = np.zeros_like(same)
        if ax == 0:
            prev[1:] = same[:-1]
        else:
            prev[:, 1:] = same[:, :-1]
        nr = int((same & ~prev).sum())
        g = d[same].mean(axis=0)
        se = sig * np.sqrt(nr) / n
        chi2 += float(np.sum((g / se) ** 2))
        grads[ax], ses[ax] = g, se
        pairs += n
        runs += nr
        noise.append(sig)
    if pairs == 0:
        out["reason"] = f"fewer than {min_pairs} neighbouring pixel pairs of one surface"
        return out
    dof = 2 * (C - 1)
    ref = np.ones(C) if reference_rgb is None else np.abs(np.asarray(reference_rgb, float))
    ref = np.where(ref > 0, ref, 1e-12)
    eff = 0.0
    for sgn in (1.0, -1.0):
        delta = grads[0] * (h - 1) + sgn * grads[1] * (w - 1)
        other = ref * np.exp(Hm.T @ delta)
        eff = max(eff, float(angular_error(ref, other)))
    logp = float(chi2_logsf(chi2, dof) / np.log(10))
    out.update(defined=True, gradient_row=[float(x) for x in grads[0]], gradient_col=[float(x) for x in grads[1]],
               se_row=[float(x) if np.isfinite(x) else None for x in ses[0]],
               se_col=[float(x) if np.isfinite(x) else None for x in ses[1]],
               chi2=chi2, dof=dof, log10_p=logp if np.isfinite(logp) else -300.0, effect_deg=eff,
               pairs=pairs, runs=runs, noise=float(np.mean([np.mean(s) for s in noise])))
    return out


def _grid_bounds(n: int, parts: int) -> np.ndarray:
    return np.linspace(0, n, max(1, min(parts, n)) + 1).round().astype(int)


def region_posteriors(image: np.ndarray, mask: np.ndarray | None, camera, grid=(2, 2), **bayes_options):
    """The light posterior (:func:`recovery.bayes.estimate_bayes`) in each
    region of a ``grid`` of non-overlapping regions (Wandell's Fig. 1
    without the overlap), each distinct colour counted once.

    Returns a list of dicts: ``slice``, ``centre`` (row, col), ``rgb``,
    ``spectrum`` (None after a fallback), ``diagnostics`` (with the
    per-candidate log-likelihoods).
    """
    img = np.asarray(image)
    h, w = img.shape[:2]
    rb, cb = _grid_bounds(h, grid[0]), _grid_bounds(w, grid[1])
    opts = {"coarse": 2.0, "keep_likelihood": True}
    opts.update(bayes_options)
    out = []
    for i in range(rb.size - 1):
        for j in range(cb.size - 1):
            sl = (slice(rb[i], rb[i + 1]), slice(cb[j], cb[j + 1]))
            rgb, spd, d = estimate_bayes(img[sl], None if mask is None else mask[sl], camera, **opts)
            out.append({"slice": sl, "centre": ((rb[i] + rb[i + 1] - 1) / 2.0, (cb[j] + cb[j + 1] - 1) / 2.0),
                        "grid_index": (i, j), "rgb": rgb, "spectrum": spd, "diagnostics": d})
    return out


def _region_loglik(d: dict) -> np.ndarray | None:
    Lc = d.get("log_likelihood_chroma")
    if d.get("method") != "bayes" or Lc is None:
        return None
    L = np.array(Lc, float)
    fin = np.isfinite(L)
    if not fin.any():
        return None
    L[~fin] = L[fin].min()                   # C > 3: lights not evaluated are the least likely
    Ll = d.get("log_likelihood_lightness")
    if Ll is not None:
        Ll = np.asarray(Ll, float)
        fl = np.isfinite(Ll)
        if fl.any():                         # lightness only for the most probable lights; the rest at the floor
            L = L + np.where(fl, Ll, Ll[fl].min())
    return L


def log_bayes_factor(regions: list) -> tuple[float, int]:
    """``log B`` of independent lights per region against one light
    (module docstring), from :func:`region_posteriors`; regions that fell
    back carry no likelihood and are left out. Returns ``(log B, regions
    used)``; ``(0.0, n)`` with fewer than two usable regions."""
    Ls, lp = [], None
    for r in regions:
        L = _region_loglik(r["diagnostics"])
        if L is not None:
            Ls.append(L)
            lp = np.asarray(r["diagnostics"]["log_prior"], float)
    if len(Ls) < 2:
        return 0.0, len(Ls)
    from scipy.special import logsumexp

    Ls = np.asarray(Ls)
    lbf = float(sum(logsumexp(lp + L) for L in Ls) - logsumexp(lp + Ls.sum(axis=0)))
    return (lbf if np.isfinite(lbf) else 0.0), len(Ls)


def _trend_map(shape, trend: dict, camera, rgb, spectrum, centroid, points: int = 5) -> LightMap:
    """A light map from the chromaticity gradient: the light at ``p`` is the
    global light shifted by ``g . (p - centroid)`` in ``u`` (diagonal
    model), its spectrum the global one smoothly modulated to that
    response; centres span the image so bilinear interpolation is exact
    for the linear field."""
    h, w = shape[:2]
    C = camera.channels
    Hm = helmert(C)
    cr = np.linspace(0, h - 1, min(points, h))
    cc = np.linspace(0, w - 1, min(points, w))
    g_r, g_c = np.asarray(trend["gradient_row"]), np.asarray(trend["gradient_col"])
    base = camera.response(spectrum)
    spectra = np.empty((cr.size, cc.size, spectrum.size))
    for a, r in enumerate(cr):
        for b, c in enumerate(cc):
            tgt = base * np.exp(Hm.T @ (g_r * (r - centroid[0]) + g_c * (c - centroid[1])))
            s = modulated_spectrum(spectrum, camera, tgt)
            spectra[a, b] = s / (s.mean() or 1.0)
    n = spectrum.size
    return LightMap(cr, cc, spectra, np.ones((cr.size, cc.size), bool), np.full((cr.size, cc.size), np.nan),
                    np.full((cr.size, cc.size), np.nan), np.eye(n))


def _region_map(regions: list, grid_shape, spectrum) -> LightMap:
    gr, gc = grid_shape
    cr = np.array([regions[i * gc]["centre"][0] for i in range(gr)])
    cc = np.array([regions[j]["centre"][1] for j in range(gc)])
    spectra = np.empty((gr, gc, spectrum.size))
    used = np.zeros((gr, gc), bool)
    for r in regions:
        i, j = r["grid_index"]
        s = r["spectrum"]
        ok = s is not None and r["diagnostics"].get("method") == "bayes"
        spectra[i, j] = (np.asarray(s, float) / (np.mean(s) or 1.0)) if ok else spectrum
        used[i, j] = ok
    return LightMap(cr, cc, spectra, used, np.full((gr, gc), np.nan), np.full((gr, gc), np.nan),
                    np.eye(spectrum.size))


def choose_light_model(image: np.ndarray, mask: np.ndarray | None, camera, rgb, spectrum, *,
                       mode: str = "auto", grid=(2, 2), max_pixels: int | None = 262144
                       ) -> tuple[LightMap | None, dict]:
    """One light or a light map for an image whose single light is ``rgb``,
    ``spectrum`` (the default estimator's answer).

    Parameters
    ----------
    mode : ``"auto"`` (decide), ``"map"`` (always a map: from the trend when
        it is significant, else from the regions)
    grid : regions of the Bayes-factor test and of the region map
    max_pixels : the tests run on the image block-averaged to at most this
        many pixels (:func:`recovery.resolution.block_average`: a mean over a
        block of one surface keeps its chromaticity and a linear trend); the
        map's centres are in the caller's pixels

    Returns
    -------
    (LightMap or None, diagnostics) where the diagnostics hold the decision
    (``light_model``: ``"one light"`` or ``"light map"``), its reason and
    the evidence: the trend's statistic and thresholds, ``log B`` and its
    threshold, and a per-region summary (distinct colours, posterior spread,
    angle to the single light).
    """
    from .resolution import block_average

    img, mask, f = block_average(np.asarray(image), mask, max_pixels)
    img = np.asarray(img, dtype=np.float64)
    h, w = img.shape[:2]
    trend = chromaticity_trend(img, mask, reference_rgb=rgb)
    regions = region_posteriors(img, mask, camera, grid)
    lbf, used = log_bayes_factor(regions)
    summary = [{"centre": [float((x + 0.5) * f - 0.5) for x in r["centre"]],
                "distinct_colours": float(r["diagnostics"].get("distinct_colours") or 0.0),
                "posterior_spread_deg": r["diagnostics"].get("posterior_spread_deg"),
                "angle_to_one_light_deg": float(angular_error(r["rgb"], rgb)) if r["spectrum"] is not None else None,
                "estimator": r["diagnostics"].get("method")} for r in regions]
    trend_says = bool(trend["defined"] and trend["log10_p"] < TREND_LOG10_P
                      and trend["effect_deg"] > TREND_MIN_EFFECT_DEG)
    regions_say = bool(used >= 2 and lbf > LOG_BF_THRESHOLD)
    evidence = {
        "trend_chi2": trend["chi2"], "trend_dof": trend["dof"], "trend_log10_p": trend["log10_p"],
        "trend_log10_p_threshold": TREND_LOG10_P, "trend_effect_deg": trend["effect_deg"],
        "trend_effect_threshold_deg": TREND_MIN_EFFECT_DEG, "trend_pairs": trend["pairs"],
        "log_bayes_factor": lbf, "log_bayes_factor_threshold": LOG_BF_THRESHOLD,
        "regions_grid": [int(grid[0]), int(grid[1])], "regions_used": used, "regions": summary,
        "trend_says_map": trend_says, "regions_say_map": regions_say, "test_block_factor": int(f),
    }
    if trend.get("reason"):
        evidence["trend_note"] = trend["reason"]
    ok = np.ones(img.shape[:2], bool) if mask is None else np.asarray(mask, bool)
    rr, cc = np.nonzero(ok)
    centroid = (float(rr.mean()), float(cc.mean())) if rr.size else ((h - 1) / 2.0, (w - 1) / 2.0)
    lm = None
    if mode == "map" or trend_says or regions_say:
        if trend_says or (mode == "map" and not regions_say and trend["defined"]
                          and trend["log10_p"] < TREND_LOG10_P):
            lm = _trend_map(img.shape, trend, camera, rgb, spectrum, centroid)
            how = "a smooth chromaticity trend inside surfaces"
        else:
            lm = _region_map(regions, (len(set(r["grid_index"][0] for r in regions)),
                                       len(set(r["grid_index"][1] for r in regions))), spectrum)
            how = "the regions' light posteriors"
        why = ("requested" if mode == "map" and not (trend_says or regions_say) else
               ("the light varies: " + "; ".join(
                   ([f"chromaticity trend p = 10^{trend['log10_p']:.0f}, {trend['effect_deg']:.1f} deg across "
                     "the image"] if trend_says else [])
                   + ([f"regions disagree, log B = {lbf:.1f} > {LOG_BF_THRESHOLD:g}"] if regions_say else []))))
        evidence.update(light_model="light map", light_model_reason=f"{why}; map from {how}")
        if f > 1:  # block centres back to the caller's pixels
            lm.centres_r = (lm.centres_r + 0.5) * f - 0.5
            lm.centres_c = (lm.centres_c + 0.5) * f - 0.5
    else:
        evidence.update(light_model="one light", light_model_reason=(
            f"no evidence the light varies: trend p = 10^{trend['log10_p']:.1f} over "
            f"{trend['effect_deg']:.1f} deg (map needs p < 10^{TREND_LOG10_P:g} and > {TREND_MIN_EFFECT_DEG:g} "
            f"deg), regions log B = {lbf:.1f} (map needs > {LOG_BF_THRESHOLD:g})"))
    return lm, evidence
