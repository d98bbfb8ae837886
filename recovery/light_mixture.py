"""Two lights in one photograph: a light map from the learnt estimator's
evidence on overlapping regions, and the one-or-several decision.

Wandell (1985, 'A condition on spatial variation') analyses an image in
overlapping regions, the light constant within each and varying slowly
across the image. Here each region is read by the estimator that works on
real photographs, the learnt one (:mod:`recovery.learned`): the classical
estimates of a window of the analysis grid, corrected by the learnt model,
give that window's light in canonical log-chroma. Three things make a map
of them:

1. **The level: the whole image's estimate and the windows' mean.** A
   window sees a quarter of the scene, so its estimate is noisier than the
   whole image's; but where two lights mix, the whole image's estimate
   follows the light of its brightest surfaces (the bright-pixel reference
   it corrects), while the windows, each lit mostly by one light, average
   to the light over the frame. The map's level is a blend,
   ``(1 - level) uv0 + level m``, of the whole-image estimate ``uv0`` and
   the windows' precision-weighted mean ``m``, with the blend chosen by
   cross-validation; the windows give the variation about it: their
   estimates minus ``m``.
2. **Two lights lie on a line.** Where two lights mix, every window's light
   lies between them: in log-chroma, close to the segment joining them. The
   variation is projected on the windows' principal direction (weighted by
   each window's precision), which removes the noise across it.
3. **Shrunk where the evidence is weak, stretched where it is averaged.** A
   window averages the lights over its area, so the windows' spread is
   smaller than the light's; noise makes it larger. The variation is
   multiplied by a gain chosen by cross-validation on relit real
   photographs (:mod:`benchmarks.mixed_light`), and the field is smooth:
   bilinear between window centres, constant beyond the outer ones. The
   gain may rise with the evidence, ``max(gain, 1 - shrink / T)`` (a
   positive-part James-Stein factor: the variation is trusted more the
   further ``T``, below, is above what noise gives), ``shrink`` chosen by the
   same cross-validation (0: the fixed gain).

The decision: the windows' variation along the principal direction against
their own calibrated uncertainty (the learnt uncertainty law,
:func:`recovery.learned.variance_from_spread`),

.. math:: T = \\sum_w \\frac{(p_w - \\bar p)^2}{s^2_w}

where :math:`p_w` is window ``w``'s estimate projected on the principal
direction and :math:`s^2_w` its variance. Windows of one scene share much of
their evidence, so :math:`T` does not follow a chi-square law; its threshold
is chosen by cross-validation on relit photographs of benchmarks the model
did not see, scored on two-light and single-light photographs together.
A map is given only when :math:`T` passes it and the principal direction's
range across the frame exceeds :data:`MIN_RANGE_DEG`.

References
----------
Wandell (1985) [docs/references.md#seed-002], Fig. 1 and 'A condition on
spatial variation'. Gijsenij, Lu & Gevers (2012), Color constancy for
multiple light sources, IEEE TIP 21(2) (estimates on patches, combined).
Bianco & Schettini (2014), Adaptive color constancy using faces (local
estimates, smoothed). James & Stein (1961), Estimation with quadratic loss,
Proc. 4th Berkeley Symp. 1; Efron & Morris (1973), Stein's estimation rule
and its competitors, JASA 68(341) (the positive-part shrinkage factor). Hussain & Akbari (2018), Color constancy for uniform
and non-uniform illuminant using image texture (two-light benchmarks).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .learned import (REFERENCE, LearnedModel, _spread, rgb_to_uv, uv_to_rgb, variance_from_spread,
                      window_features)

__all__ = ["WINDOW", "STEP", "MixtureSettings", "DEFAULT_SETTINGS", "WindowEvidence", "window_slices", "window_evidence",
           "mixture_statistic", "field_parts", "compose_field", "light_field", "decide", "MIN_RANGE_DEG"]

#: Windows of this many analysis cells (of the 64 x 64 grid the learnt model
#: reads a whole image at) ...
WINDOW = 32
#: ... every this many cells: 3 x 3 windows, each overlapping its neighbours by half.
STEP = 16
#: A map only when the light it gives changes by more than this across the
#: frame (degrees): below it one light is within half of it everywhere, under
#: the learnt estimator's own median error on real photographs.
MIN_RANGE_DEG = 2.0
#: A window needs this many usable cells (of WINDOW**2) to count.
MIN_WINDOW_CELLS = 64


@dataclass(frozen=True)
class MixtureSettings:
    """What the light map and its decision depend on, chosen by
    cross-validation on relit development photographs
    (``python -m benchmarks.mixed_light``, inner leave-one-benchmark-out)."""

    threshold: float = 32.0     #: the decision's threshold on T (module docstring)
    gain: float = 0.5           #: multiplies the windows' variation (item 3 of the module docstring)
    project: bool = False       #: project the variation on the principal direction (two lights)
    level: float = 0.75         #: weight of the windows' mean in the map's level (item 1 of the module docstring)
    shrink: float = 24.0        #: the gain rises to ``1 - shrink / T`` where that is larger (item 3; 0: fixed)

    def gain_at(self, T: float) -> float:
        """The gain on the windows' variation for a scene whose windows
        disagree by ``T`` (:func:`mixture_statistic`): ``max(gain, 1 -
        shrink / T)``, the fixed ``gain`` when ``shrink`` is 0 (module
        docstring, item 3).

        Examples
        --------
        >>> MixtureSettings(gain=0.5, shrink=16.0).gain_at(64.0)
        0.75
        >>> MixtureSettings(gain=0.5, shrink=16.0).gain_at(20.0)
        0.5
        """
        if self.shrink <= 0 or not np.isfinite(T) or T <= 0:
            return float(self.gain)
        return float(max(self.gain, 1.0 - self.shrink / T))


#: The shipped settings (benchmarks.mixed_light prints how they were chosen).
DEFAULT_SETTINGS = MixtureSettings()


@dataclass
class WindowEvidence:
    """The learnt estimator on the overlapping windows of an analysis grid.

    Attributes
    ----------
    uv : (n, 2) each window's light, canonical log-chroma (NaN where unusable)
    var : (n,) its variance (log-chroma^2) from the learnt uncertainty law
    centres : (n, 2) window centres (row, col) in analysis cells
    valid : (n,) bool, windows with enough usable cells and surface variation
    shape : (rows, cols) of the analysis grid
    """

    uv: np.ndarray
    var: np.ndarray
    centres: np.ndarray
    valid: np.ndarray
    shape: tuple
    grid: tuple = field(default=(0, 0))


def _starts(n: int, size: int, step: int) -> list[int]:
    if n <= size:
        return [0]
    s = list(range(0, n - size + 1, step))
    if s[-1] != n - size:
        s.append(n - size)
    return s


def window_slices(shape, window: int = WINDOW, step: int = STEP) -> tuple[list[tuple[slice, slice]], tuple]:
    """The overlapping windows of an (h, w) analysis grid, row by row:
    ``(slices, (rows, cols))``, each window ``window`` cells on a side (less
    where the grid is smaller), every ``step`` cells, the last flush with
    the grid's edge."""
    h, w = shape[:2]
    rs, cs = _starts(h, window, step), _starts(w, window, step)
    return ([(slice(r, min(h, r + window)), slice(c, min(w, c + window))) for r in rs for c in cs],
            (len(rs), len(cs)))


def window_evidence(can: np.ndarray, ok: np.ndarray, model: LearnedModel, gamut_fraction: float = 0.0,
                    window: int = WINDOW, step: int = STEP) -> WindowEvidence:
    """Each overlapping window's light by the learnt model.

    The windows' classical estimates read the whole grid's filtered maps
    (:func:`recovery.learned.window_features`): a window's gray edges and
    gray pixels near its border see the image's neighbouring cells, not an
    extension of the window's own border, and the filtering is done once.

    Parameters
    ----------
    can : (h, w, 3) canonical-space analysis cells
        (:func:`recovery.learned.canonical_analysis`)
    ok : (h, w) usable cells
    model : the learnt model
    gamut_fraction : the whole image's out-of-gamut fraction (beyond the
        model's limit the reference estimate stands, as for the whole image)
    """
    h, w = ok.shape
    wins, grid = window_slices((h, w), window, step)
    n = len(wins)
    uv = np.full((n, 2), np.nan)
    var = np.full(n, np.nan)
    centres = np.array([((a.start + a.stop - 1) / 2.0, (b.start + b.stop - 1) / 2.0) for a, b in wins])
    valid = np.zeros(n, bool)
    enough = [k for k, sl in enumerate(wins) if int(ok[sl].sum()) >= MIN_WINDOW_CELLS]
    idx, feats = [], []
    if enough:
        # each window reads the whole grid's filtered maps (recovery.learned.window_features)
        f_all, v_all = window_features(can, ok, [wins[k] for k in enough])
        idx = [k for k, v in zip(enough, v_all) if v]
        feats = list(f_all[v_all])
    if idx:
        f = np.asarray(feats)
        gam = np.full(len(idx), float(gamut_fraction))
        u = model.predict(model.inputs(f), gam) + f[:, REFERENCE]
        uv[idx] = u
        var[idx] = variance_from_spread(_spread(f, u), model.sigma)
        valid[idx] = True
    return WindowEvidence(uv, var, centres, valid, (h, w), grid)


def _principal(uv: np.ndarray, wts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean and unit principal direction of points ``uv``."""
    m = (wts[:, None] * uv).sum(axis=0) / wts.sum()
    d = uv - m
    S = (wts[:, None, None] * d[:, :, None] * d[:, None, :]).sum(axis=0)
    vals, vecs = np.linalg.eigh(S)
    return m, vecs[:, -1]


def mixture_statistic(ev: WindowEvidence) -> float:
    """:math:`T` of the module docstring (0 with fewer than two usable windows)."""
    v = ev.valid
    if v.sum() < 2:
        return 0.0
    uv, s2 = ev.uv[v], ev.var[v]
    m, d = _principal(uv, 1.0 / s2)
    p = (uv - m) @ d
    pbar = float((p / s2).sum() / (1.0 / s2).sum())
    return float(((p - pbar) ** 2 / s2).sum())


def field_parts(uv0: np.ndarray, ev: WindowEvidence,
                settings: MixtureSettings = DEFAULT_SETTINGS) -> tuple[np.ndarray, np.ndarray]:
    """The two parts of :func:`light_field`: its level (2,), the whole
    image's ``uv0`` blended with the windows' precision-weighted mean, and
    the windows' variation about their mean (n, 2; projected on their
    principal direction when ``settings.project``; zero where a window is
    unusable), before the gain. With fewer than two usable windows the
    level is ``uv0`` and the variation zero."""
    uv0 = np.asarray(uv0, float)
    v = ev.valid
    dev = np.zeros((v.size, 2))
    if v.sum() < 2:
        return uv0, dev
    uv, s2 = ev.uv[v], ev.var[v]
    m, d = _principal(uv, 1.0 / s2)
    level = (1.0 - settings.level) * uv0 + settings.level * m
    dv = uv - m
    if settings.project:
        dv = (dv @ d)[:, None] * d[None, :]
    dev[v] = dv
    return level, dev


def compose_field(level: np.ndarray, dev: np.ndarray, ev: WindowEvidence, gain: float) -> np.ndarray:
    """(gr, gc, 2) ``level + gain * dev`` at the window centres (the level
    alone where a window is unusable)."""
    gr, gc = ev.grid
    out = np.tile(np.asarray(level, float), (gr * gc, 1))
    out[ev.valid] += gain * dev[ev.valid]
    return out.reshape(gr, gc, 2)


def light_field(uv0: np.ndarray, ev: WindowEvidence, settings: MixtureSettings = DEFAULT_SETTINGS,
                T: float | None = None) -> np.ndarray:
    """(gr, gc, 2) the light at the window centres (canonical log-chroma):
    the level (the whole image's ``uv0`` blended with the windows'
    precision-weighted mean, ``settings.level``) plus the windows' variation
    about their mean, projected on their principal direction and multiplied
    by the gain ``settings.gain_at(T)`` (module docstring; :func:`field_parts`;
    ``T`` is computed when not given and the gain depends on it). Unusable
    windows get the level."""
    if ev.valid.sum() < 2:
        gr, gc = ev.grid
        return np.tile(np.asarray(uv0, float), (gr * gc, 1)).reshape(gr, gc, 2)
    level, dev = field_parts(uv0, ev, settings)
    if settings.shrink > 0 and T is None:
        T = mixture_statistic(ev)
    return compose_field(level, dev, ev, settings.gain_at(T if T is not None else 0.0))


def field_range_deg(field_uv: np.ndarray, K: np.ndarray) -> float:
    """Largest angle (degrees, camera RGB) between two lights of a field
    (every pair at once, by the stable half-angle formula of
    :func:`recovery.learned._angle`)."""
    f = field_uv.reshape(-1, 2)
    cam = np.linalg.solve(K, uv_to_rgb(f).T).T
    u = cam / np.linalg.norm(cam, axis=1, keepdims=True)
    d = np.linalg.norm(u[:, None, :] - u[None, :, :], axis=-1)
    s = np.linalg.norm(u[:, None, :] + u[None, :, :], axis=-1)
    return float(np.degrees(2 * np.arctan2(d, s)).max()) if len(u) > 1 else 0.0


def decide(ev: WindowEvidence, uv0: np.ndarray, K: np.ndarray,
           settings: MixtureSettings = DEFAULT_SETTINGS) -> tuple[np.ndarray | None, dict]:
    """One light or a map.

    Returns
    -------
    (field or None, evidence) : the (gr, gc, 2) field of :func:`light_field`
    when the map is chosen; the evidence holds ``T``, its threshold, the
    field's range across the frame and the reason, in words.
    """
    T = mixture_statistic(ev)
    fld = light_field(uv0, ev, settings, T)
    rng = field_range_deg(fld, K) if ev.valid.sum() >= 2 else 0.0
    nv = int(ev.valid.sum())
    evidence = {"mixture_T": T, "mixture_threshold": settings.threshold, "map_range_deg": rng,
                "map_range_threshold_deg": MIN_RANGE_DEG, "windows_used": nv, "windows": int(ev.valid.size),
                "window_cells": WINDOW, "gain": settings.gain_at(T), "gain_shrink": settings.shrink,
                "level_windows_weight": settings.level}
    if nv < 2:
        evidence["reason"] = (f"one light: only {nv} of {ev.valid.size} windows have enough surfaces to read "
                              "a light from, so a change of light across the frame cannot be seen")
        return None, evidence
    if T > settings.threshold and rng > MIN_RANGE_DEG:
        evidence["reason"] = (f"several lights: the {nv} overlapping windows disagree about the light along one "
                              f"direction far beyond their own uncertainty (T = {T:.1f} > {settings.threshold:g}), "
                              f"and the light changes by {rng:.1f} degrees across the frame")
        return fld, evidence
    if T <= settings.threshold:
        evidence["reason"] = (f"one light: the {nv} overlapping windows agree about the light within their own "
                              f"uncertainty (T = {T:.1f}, a map needs > {settings.threshold:g})")
    else:
        evidence["reason"] = (f"one light: the windows disagree (T = {T:.1f}) but the light they give changes by "
                              f"only {rng:.1f} degrees across the frame (a map needs > {MIN_RANGE_DEG:g})")
    return None, evidence
