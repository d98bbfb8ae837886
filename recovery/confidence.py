"""How far to trust a light estimate: a calibrated probability of a small
error and a flag on the estimates that are likely wrong.

The learnt estimator's 90 % region (:mod:`recovery.learned`) grows with
one number, the spread of the classical estimates about the answer; it is
calibrated for coverage, but as a *ranking* of the failures it is weak
(area under the ROC curve for errors above 6 degrees 0.68-0.77 on
benchmarks never seen; with this module's evidence and law 0.79-0.82,
``python -m benchmarks.real_photos``, docs/confidence.md). This module
adds the other evidence that an answer may be wrong, each read from the
image alone:

* ``log_spread``: the classical estimates' RMS distance from the answer
  (what the region uses);
* ``log_correction``: how far the learnt model moved the answer from its
  reference (bright pixels): a large correction is an extrapolation;
* ``log_input_distance``: the mean squared standardised distance of the
  model's inputs from the training photographs' mean (the model's own
  standardisation): how far outside its training the image lies;
* ``gamut_fraction``: the share of cells the colour matrix sends out of the
  canonical gamut;
* ``usable_fraction``: the share of analysis cells that could be used;
* ``patch_fraction``: the share of cells inside uniform patches;
* ``off_locus``, ``mired``: where the estimate sits among the physical
  lights (its distance off the Planckian locus, and the reciprocal colour
  temperature of the nearest locus point, in 100 mired): a light far off
  the locus, or at an end of it, is suspect;
* ``log_region_reference_spread``, ``log_region_gray_world_spread``: how
  much the bright-pixel and gray-world estimates of the four quadrants
  differ from the whole image's (a scene whose parts point at different
  lights: two lights, or evidence that depends on which surfaces happen to
  be in view). The learnt estimator run on each quadrant was tried too; it
  added nothing the inner cross-validation could see and cost four more
  feature extractions per estimate.

``P(error < 3 degrees)`` is a sum of boosted stumps (:func:`fit_stumps`:
200 Newton steps of the logistic loss, each a split of one input; a small
nonlinear law, deterministic) on these, fitted on the *out-of-fold*
predictions of the training procedure's inner leave-one-benchmark-out (each
benchmark predicted by a model that never saw it), so the probability is
calibrated for photographs of benchmarks never seen. A logistic regression
on the same inputs (:func:`fit_logistic`, the law before) and boosted trees
of depth 2 (:func:`fit_trees`, tried after) are kept as options: the
stumps ranked the failures better than the logistic law in the inner
cross-validation, and the trees' gain over the stumps did not clear the
bar set for a change (docs/confidence.md). ``low_confidence`` is ``confidence <
threshold``, the threshold chosen on the same out-of-fold predictions
(:func:`choose_threshold`). Both ship in
``recovery/data/learned_confidence.json``, built by ``python -m
benchmarks.train_illuminant --flag-only`` (the learnt model's own file left
as it is).

References
----------
Cox (1958), The regression analysis of binary sequences, JRSS B (logistic
regression). Friedman (2001), Greedy function approximation: a gradient
boosting machine, Annals of Statistics 29(5). Platt (1999), Probabilistic outputs for support vector
machines (calibrated probabilities from held-out scores). Fawcett (2006),
An introduction to ROC analysis, Pattern Recognition Letters 27.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

__all__ = ["INPUT_NAMES", "FlagModel", "confidence_inputs", "fit_logistic", "fit_stumps", "stump_score",
           "fit_trees", "tree_score",
           "choose_threshold", "auroc",
           "load_flag_model", "DEFAULT_FLAG_PATH", "quadrants", "region_estimates"]

DEFAULT_FLAG_PATH = Path(__file__).with_name("data") / "learned_confidence.json"

INPUT_NAMES = ("log_spread", "log_correction", "log_input_distance", "gamut_fraction",
               "usable_fraction", "patch_fraction", "off_locus", "mired", "log_region_reference_spread",
               "log_region_gray_world_spread")

#: Usable cells a quadrant needs for its estimates (as the whole image needs
#: for :func:`recovery.learned.features`).
MIN_REGION_CELLS = 16

#: Floor of the log-chroma distances before their logarithm (0.1 degree or so).
_FLOOR = 2e-3


def quadrants(shape) -> list[tuple[slice, slice]]:
    """The four quadrants of an analysis image of ``shape`` (h, w)."""
    h, w = shape[:2]
    return [(slice(a * h // 2, (a + 1) * h // 2), slice(b * w // 2, (b + 1) * w // 2)) for a in (0, 1) for b in (0, 1)]


def _region_rms(region, whole) -> np.ndarray:
    """(N,) RMS distance of the quadrants' (N, 4, 2) values from the whole
    image's (N, 2), over the quadrants that have one; NaN with fewer than two."""
    d2 = np.sum((np.asarray(region, float) - np.asarray(whole, float)[:, None, :]) ** 2, axis=-1)
    good = np.isfinite(d2)
    n = good.sum(axis=1)
    rms = np.sqrt(np.where(good, d2, 0.0).sum(axis=1) / np.maximum(n, 1))
    return np.where(n >= 2, rms, np.nan)


def region_estimates(cells, ok) -> np.ndarray:
    """(4, 2, 2) the gray-world and bright-pixel (top 1 %) estimates'
    log-chroma on the four quadrants of an analysis image (``cells`` clipped
    at 1e-6, usable ``ok``, as :func:`recovery.learned.features` reads the
    whole image); NaN for a quadrant with fewer than
    :data:`MIN_REGION_CELLS` usable cells. Cheap (two statistics, no
    filters), so the confidence adds little to an estimate's cost."""
    from .estimators import bright_pixels, gray_world
    from .learned import rgb_to_uv

    img = np.clip(np.asarray(cells, float), 1e-6, None)
    out = np.full((4, 2, 2), np.nan)
    for q, sl in enumerate(quadrants(ok.shape)):
        px = img[sl][ok[sl]]
        if px.shape[0] >= MIN_REGION_CELLS:
            est = np.array([gray_world(px), bright_pixels(px, None, 0.01)])
            if np.all(np.isfinite(est) & (est > 0)):
                out[q] = rgb_to_uv(est)
    return out


def confidence_inputs(feats, uv, region, input_z2, gamut_fraction, usable_fraction, patch_fraction,
                      reference: int, locus_uv, locus_mired) -> np.ndarray:
    """(N, len(INPUT_NAMES)) the evidence for :class:`FlagModel`.

    Parameters
    ----------
    feats : (N, F, 2) the classical estimates' log-chroma (gray world first)
    uv : (N, 2) the learnt estimate (the first stage's)
    region : (N, 4, 2, 2) the quadrants' gray-world and bright-pixel
        estimates (:func:`region_estimates`; NaN where a quadrant had too
        few usable cells)
    input_z2 : (N,) mean squared standardised model input
    gamut_fraction, usable_fraction, patch_fraction : (N,)
    reference : index of the reference (bright-pixel) estimate in ``feats``
    locus_uv, locus_mired : the model's Planckian locus
        (:func:`recovery.learned.locus_coordinates`): where the estimate sits
        among physical lights (a light far off the locus is suspect)
    """
    from .learned import locus_coordinates

    f = np.asarray(feats, float)
    uv = np.asarray(uv, float)
    rg = np.asarray(region, float)
    spread = np.sqrt(np.mean(np.sum((f - uv[:, None, :]) ** 2, axis=-1), axis=-1))
    corr = np.linalg.norm(uv - f[:, reference], axis=-1)
    # fewer than two quadrants to compare: as spread out as the classical estimates are
    rr = _region_rms(rg[:, :, 1], f[:, reference])
    rr = np.where(np.isfinite(rr), rr, spread)
    rw = _region_rms(rg[:, :, 0], f[:, 0])
    rw = np.where(np.isfinite(rw), rw, spread)
    lc = locus_coordinates(uv, np.asarray(locus_uv, float), np.asarray(locus_mired, float))
    return np.stack([np.log(spread + _FLOOR), np.log(corr + _FLOOR),
                     np.log(np.asarray(input_z2, float) + 1e-3), np.asarray(gamut_fraction, float),
                     np.asarray(usable_fraction, float), np.asarray(patch_fraction, float),
                     np.abs(lc[:, 1]), lc[:, 0], np.log(rr + _FLOOR), np.log(rw + _FLOOR)], axis=1)


def fit_logistic(x, y, weights=None, l2: float = 1e-3, iters: int = 100) -> np.ndarray:
    """Weighted logistic regression of ``y`` (0/1) on ``x`` (N, k) with a
    constant, the slopes penalised by ``l2 |b|^2`` (the weights summing to
    1): Newton's method from zero, a convex problem, so the result is
    unique and deterministic. Returns (k + 1,) ``[constant, slopes...]``."""
    x = np.asarray(x, float)
    X = np.c_[np.ones(len(x)), x]
    y = np.asarray(y, float)
    w = np.ones(len(y)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    P = l2 * np.diag(np.r_[0.0, np.ones(x.shape[1])])
    c = np.zeros(X.shape[1])
    for _ in range(iters):
        p = 1.0 / (1.0 + np.exp(-(X @ c)))
        g = X.T @ (w * (y - p)) - 2 * P @ c
        h = (X * (w * p * (1 - p))[:, None]).T @ X + 2 * P + 1e-12 * np.eye(X.shape[1])
        step = np.linalg.solve(h, g)
        c = c + step
        if np.abs(step).max() < 1e-10:
            break
    return c


def auroc(score, positive) -> float:
    """Area under the ROC curve of ``score`` for ``positive`` (ties count
    half): the probability that a positive scores above a negative
    (Mann-Whitney). NaN without both classes."""
    from scipy.stats import rankdata

    s = np.asarray(score, float)
    pos = np.asarray(positive, bool)
    n1, n0 = int(pos.sum()), int((~pos).sum())
    if n1 == 0 or n0 == 0:
        return float("nan")
    r = rankdata(s)
    return float((r[pos].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def choose_threshold(conf, failed, groups, max_flag: float = 0.15) -> tuple[float, dict]:
    """The flag threshold on the out-of-fold confidences ``conf``: the
    largest threshold whose flag rate is at most ``max_flag`` in every group
    (benchmark) — the most failures caught (``failed``: error above 6
    degrees) for a bounded share of photographs flagged. Returns the
    threshold and, per group, its flag and catch rates."""
    conf = np.asarray(conf, float)
    failed = np.asarray(failed, bool)
    groups = np.asarray(groups)
    names = sorted(set(groups.tolist()))
    cands = np.unique(np.round(conf, 4))
    best = float(cands.min()) if cands.size else 0.0
    for t in cands:
        if all(np.mean(conf[groups == g] < t) <= max_flag for g in names):
            best = float(t)
    rec = {g: {"flagged": float(np.mean(conf[groups == g] < best)),
               "caught": float(np.mean(conf[(groups == g) & failed] < best)) if np.any(failed[groups == g]) else None}
           for g in names}
    return best, rec


def _boosting_start(x, y, weights, bins: int):
    """What :func:`fit_stumps` and :func:`fit_trees` start from: the inputs
    and outcomes as floats, the weights rescaled to average 1, each input's
    ``bins - 1`` inner quantiles and every value's bin, and the constant
    log-odds of the weighted outcome rate."""
    x = np.asarray(x, float)
    y = np.asarray(y, float)
    w = np.ones(len(y)) if weights is None else np.asarray(weights, float)
    w = w / w.mean()
    edges = [np.unique(np.quantile(x[:, j], np.linspace(0.0, 1.0, bins + 1)[1:-1])) for j in range(x.shape[1])]
    b = np.stack([np.searchsorted(edges[j], x[:, j], side="right") for j in range(x.shape[1])], axis=1)
    p0 = float(np.clip(np.average(y, weights=w), 1e-3, 1 - 1e-3))
    return x, y, w, edges, b, float(np.log(p0 / (1 - p0)))


def fit_stumps(x, y, weights=None, rounds: int = 200, rate: float = 0.1, bins: int = 32,
               lam: float = 1.0) -> tuple[float, np.ndarray]:
    """Gradient-boosted stumps for the log-odds of ``y`` (0/1) on ``x`` (N, k):
    ``rounds`` Newton steps of the weighted logistic loss, each a split of
    one input at one of its ``bins - 1`` inner quantiles (the split of
    largest gain, the leaves' values ``-G / (H + lam)`` shrunk by ``rate``).
    Deterministic (no sampling; ties in gain go to the first input and
    split). The weights are rescaled to average 1, so ``lam`` is worth
    ``lam`` photographs of average weight.

    Returns ``(constant, stumps)``, ``stumps`` (rounds, 4): input index,
    threshold, value below it, value at or above it (:func:`stump_score`).

    References
    ----------
    Friedman (2001), Greedy function approximation: a gradient boosting
    machine, Annals of Statistics 29(5). Chen & Guestrin (2016), XGBoost,
    KDD (the Newton step and its ``lam``).
    """
    x, y, w, edges, b, c0 = _boosting_start(x, y, weights, bins)
    n, k = x.shape
    f = np.full(n, c0)
    out = np.zeros((rounds, 4))
    for r in range(rounds):
        p = 1.0 / (1.0 + np.exp(-f))
        g, h = w * (p - y), w * p * (1 - p)
        best = None
        for j in range(k):
            m = len(edges[j]) + 1
            if m < 2:
                continue
            G, H = np.bincount(b[:, j], g, m), np.bincount(b[:, j], h, m)
            gl, hl = np.cumsum(G)[:-1], np.cumsum(H)[:-1]
            gr, hr = G.sum() - gl, H.sum() - hl
            gain = gl ** 2 / (hl + lam) + gr ** 2 / (hr + lam)
            t = int(np.argmax(gain))
            if best is None or gain[t] > best[0]:
                best = (gain[t], j, t, -gl[t] / (hl[t] + lam), -gr[t] / (hr[t] + lam))
        if best is None:
            return c0, out[:r]
        _, j, t, vl, vr = best
        out[r] = (j, edges[j][t], rate * vl, rate * vr)
        f += np.where(b[:, j] <= t, rate * vl, rate * vr)
    return c0, out


def stump_score(x, constant: float, stumps) -> np.ndarray:
    """(N,) log-odds of :func:`fit_stumps`' model at inputs ``x`` (N, k)."""
    x = np.atleast_2d(np.asarray(x, float))
    st = np.asarray(stumps, float).reshape(-1, 4)
    v = np.where(x[:, st[:, 0].astype(int)] < st[:, 1], st[:, 2], st[:, 3])
    # summed in the stumps' order from the constant (a running sum: the same bits as adding one by one)
    return np.cumsum(np.c_[np.full(len(x), float(constant)), v], axis=1)[:, -1]



def _best_split(b, g, h, rows, edges, lam):
    """The split of largest gain among ``rows`` (bool mask) of the binned
    inputs ``b``: ``(gain over no split, input, bin, left value, right
    value)``, or None (no input has two bins)."""
    best = None
    G0, H0 = g[rows].sum(), h[rows].sum()
    for j in range(b.shape[1]):
        m = len(edges[j]) + 1
        if m < 2:
            continue
        G, H = np.bincount(b[rows, j], g[rows], m), np.bincount(b[rows, j], h[rows], m)
        gl, hl = np.cumsum(G)[:-1], np.cumsum(H)[:-1]
        gr, hr = G0 - gl, H0 - hl
        gain = gl ** 2 / (hl + lam) + gr ** 2 / (hr + lam) - G0 ** 2 / (H0 + lam)
        t = int(np.argmax(gain))
        if best is None or gain[t] > best[0]:
            best = (gain[t], j, t, -gl[t] / (hl[t] + lam), -gr[t] / (hr[t] + lam))
    return best


def fit_trees(x, y, weights=None, rounds: int = 100, rate: float = 0.1, bins: int = 32,
              lam: float = 1.0) -> tuple[float, np.ndarray]:
    """Gradient-boosted trees of depth 2 for the log-odds of ``y`` (0/1) on
    ``x`` (N, k): as :func:`fit_stumps` (the same binning at inner
    quantiles, Newton steps of the weighted logistic loss, leaves
    ``-G / (H + lam)`` shrunk by ``rate``), but each round splits the root
    and then each of its two halves on that half's own best split (a half
    whose best split gains nothing keeps one value), so one round can say
    "a large spread matters where few cells are usable". Deterministic.

    Returns ``(constant, trees)``, ``trees`` (rounds, 10): the root's input
    and threshold, the left half's input and threshold, the right half's,
    and the four leaves' values (left-left, left-right, right-left,
    right-right; "left" is below the threshold) (:func:`tree_score`). A half
    without a split has input 0, threshold 0 and its value in both leaves.

    References
    ----------
    Friedman (2001), Greedy function approximation: a gradient boosting
    machine, Annals of Statistics 29(5). Chen & Guestrin (2016), XGBoost,
    KDD (the Newton step, ``lam``, the gain of a split).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> x = rng.normal(size=(2000, 2))
    >>> y = (x[:, 0] > 0) ^ (x[:, 1] > 0)                 # no sum of single splits can say this
    >>> c, t = fit_trees(x, y, rounds=100)
    >>> c1, s1 = fit_stumps(x, y, rounds=100)
    >>> xt = rng.normal(size=(2000, 2)); yt = (xt[:, 0] > 0) ^ (xt[:, 1] > 0)      # new points
    >>> acc_trees = float(np.mean((tree_score(xt, c, t) > 0) == yt))          # 0.92 when written
    >>> acc_stumps = float(np.mean((stump_score(xt, c1, s1) > 0) == yt))      # 0.58: little better than chance
    >>> acc_trees > 0.85, acc_stumps < 0.65
    (True, True)
    """
    x, y, w, edges, b, c0 = _boosting_start(x, y, weights, bins)
    n, k = x.shape
    f = np.full(n, c0)
    out = np.zeros((rounds, 10))
    every = np.ones(n, bool)
    for r in range(rounds):
        p = 1.0 / (1.0 + np.exp(-f))
        g, h = w * (p - y), w * p * (1 - p)
        root = _best_split(b, g, h, every, edges, lam)
        if root is None:
            return c0, out[:r]
        _, j0, t0, vl, vr = root
        left = b[:, j0] <= t0
        row, leaves = [j0, edges[j0][t0]], []
        for half, v in ((left, vl), (~left, vr)):
            sub = _best_split(b, g, h, half, edges, lam) if half.sum() > 1 else None
            if sub is None or not sub[0] > 0:
                row += [0, 0.0]
                leaves += [v, v]
            else:
                row += [sub[1], edges[sub[1]][sub[2]]]
                leaves += [sub[3], sub[4]]
        out[r] = row + [rate * v for v in leaves]
        f += _tree_values(x, out[r:r + 1])[:, 0]
    return c0, out


def _tree_values(x, trees) -> np.ndarray:
    """(N, R) the value of each tree of :func:`fit_trees` at inputs ``x``."""
    t = np.asarray(trees, float).reshape(-1, 10)
    left = x[:, t[:, 0].astype(int)] < t[:, 1]
    ll = x[:, t[:, 2].astype(int)] < t[:, 3]
    rl = x[:, t[:, 4].astype(int)] < t[:, 5]
    return np.where(left, np.where(ll, t[:, 6], t[:, 7]), np.where(rl, t[:, 8], t[:, 9]))


def tree_score(x, constant: float, trees) -> np.ndarray:
    """(N,) log-odds of :func:`fit_trees`' model at inputs ``x`` (N, k)."""
    x = np.atleast_2d(np.asarray(x, float))
    v = _tree_values(x, trees)
    return np.cumsum(np.c_[np.full(len(x), float(constant)), v], axis=1)[:, -1]

@dataclass(frozen=True)
class FlagModel:
    """The calibrated confidence and the flag (see the module docstring).

    Attributes
    ----------
    names : the inputs (:data:`INPUT_NAMES`)
    mean, scale : (k,) their standardisation (the logistic law's)
    coef : (k + 1,) the logistic law of P(error < 3 deg) on the standardised
        inputs; with ``trees`` or ``stumps``, ``[constant]`` of the boosted law
    threshold : confidence below which an estimate is flagged
    peers : method -> P(error < 3 deg) of a classical estimator on the
        development photographs (the confidence a requested peer reports)
    info : what it was fitted on, and how
    stumps : (R, 4) boosted stumps (:func:`fit_stumps`) on the raw inputs, or
        None
    trees : (R, 10) boosted trees of depth 2 (:func:`fit_trees`) on the raw
        inputs, or None; with neither, the logistic law
    """

    names: tuple
    mean: np.ndarray
    scale: np.ndarray
    coef: np.ndarray
    threshold: float
    peers: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict, compare=False)
    stumps: np.ndarray | None = None
    trees: np.ndarray | None = None

    def confidence(self, x) -> np.ndarray:
        """(N,) P(error < 3 deg) for inputs (N, k) (:func:`confidence_inputs`)."""
        x = np.atleast_2d(np.asarray(x, float))
        if self.trees is not None:
            a = tree_score(x, float(self.coef[0]), self.trees)
        elif self.stumps is not None:
            a = stump_score(x, float(self.coef[0]), self.stumps)
        else:
            a = self.coef[0] + ((x - self.mean) / self.scale) @ self.coef[1:]
        return 1.0 / (1.0 + np.exp(-np.clip(a, -50.0, 50.0)))

    def to_json(self) -> str:
        d = {"names": list(self.names), "mean": list(map(float, self.mean)),
             "scale": list(map(float, self.scale)), "coef": list(map(float, self.coef)),
             "threshold": float(self.threshold), "peers": {k: float(v) for k, v in self.peers.items()},
             "info": self.info}
        if self.stumps is not None:
            d["stumps"] = [[int(j), float(t), float(lo), float(hi)] for j, t, lo, hi in np.asarray(self.stumps)]
        if self.trees is not None:
            d["trees"] = [[int(r[0]), float(r[1]), int(r[2]), float(r[3]), int(r[4]), float(r[5])]
                          + [float(v) for v in r[6:]] for r in np.asarray(self.trees)]
        return json.dumps(d, indent=1, sort_keys=True)

    @classmethod
    def from_json(cls, text: str) -> "FlagModel":
        d = json.loads(text)
        st, tr = d.get("stumps"), d.get("trees")
        return cls(tuple(d["names"]), np.asarray(d["mean"], float), np.asarray(d["scale"], float),
                   np.asarray(d["coef"], float), float(d["threshold"]), dict(d.get("peers", {})), d.get("info", {}),
                   None if st is None else np.asarray(st, float).reshape(-1, 4),
                   None if tr is None else np.asarray(tr, float).reshape(-1, 10))


def fit_flag_model(x, ok3, failed, groups, weights=None, l2: float = 1e-3, max_flag: float = 0.15,
                   peers=None, info=None, stumps: dict | None = None, trees: dict | None = None) -> FlagModel:
    """Fit :class:`FlagModel` on out-of-fold inputs ``x`` (N, k), outcomes
    ``ok3`` (error under 3 degrees) and ``failed`` (above 6), the threshold
    by :func:`choose_threshold` per group (benchmark): the logistic law
    (ridge ``l2``), or with ``trees`` (keyword arguments of
    :func:`fit_trees`) boosted trees of depth 2, or with ``stumps`` (of
    :func:`fit_stumps`) boosted stumps."""
    x = np.asarray(x, float)
    mean, scale = x.mean(axis=0), x.std(axis=0) + 1e-9
    st = tr = None
    if trees is not None:
        c0, tr = fit_trees(x, ok3, weights, **trees)
        coef = np.array([c0])
    elif stumps is not None:
        c0, st = fit_stumps(x, ok3, weights, **stumps)
        coef = np.array([c0])
    else:
        coef = fit_logistic((x - mean) / scale, ok3, weights, l2)
    fm = FlagModel(tuple(INPUT_NAMES), mean, scale, coef, 0.0, dict(peers or {}), dict(info or {}), st, tr)
    t, rec = choose_threshold(fm.confidence(x), failed, groups, max_flag)
    return FlagModel(fm.names, mean, scale, coef, t, fm.peers, {**fm.info, "threshold_choice": rec,
                                                                 "max_flag_rate": max_flag, "l2": l2}, st, tr)


@lru_cache(maxsize=4)
def load_flag_model(path: str | None = None) -> FlagModel | None:
    """The shipped flag model (None when the file is absent)."""
    p = Path(path) if path else DEFAULT_FLAG_PATH
    if not p.exists():
        return None
    return FlagModel.from_json(p.read_text())


#: The light posterior's rate of errors under 3 degrees on the development
#: photographs (``python -m benchmarks.posterior_real --write``).
POSTERIOR_RATE_PATH = Path(__file__).resolve().parent / "data" / "posterior_real_rate.json"


@lru_cache(maxsize=1)
def posterior_real_rate() -> dict | None:
    """The light posterior (:func:`recovery.bayes.estimate_bayes`) on real
    photographs: ``rate_under_3deg`` (each benchmark weighing the same),
    ``per_benchmark``, ``auroc_spread`` (how well its spread ranks its errors
    there: about 0.5, i.e. not at all) and ``claimed_confidence`` (what its
    spread-based confidence claims on them); None when the file is absent.

    Its spread-based confidence (:data:`recovery.bayes.CONFIDENCE_COEF`) is
    calibrated on synthetic scenes of flat measured surfaces, where it holds;
    on a real scene the product reports this measured rate instead, as it
    does for a classical peer (issue 27, item 4; ``docs/confidence.md``)."""
    if not POSTERIOR_RATE_PATH.exists():
        return None
    return json.loads(POSTERIOR_RATE_PATH.read_text())
