"""How the confidence's law and evidence were chosen (issue 27, item 4;
docs/confidence.md, "Choosing the model"): variants of
:mod:`recovery.confidence` scored by the inner cross-validation only, the
left-out benchmark's figures printed beside them.

For each outer fold (one benchmark left out), the training procedure of
:mod:`benchmarks.train_illuminant` runs on the other two, giving their
inner out-of-fold estimates (each benchmark predicted by an estimator that
never saw it) and the confidence's ten inputs; the outer estimator
predicts the left-out benchmark. Each variant (further evidence, another
law) is then scored on the inner out-of-fold predictions alone:

* inner leave-one-benchmark-out: the law fitted on one training benchmark,
  the area under the ROC curve (errors above 6 degrees) on the other;
* inner leave-one-camera-out: fitted on all their cameras but one, scored
  on that camera's images, the AUROC per benchmark;

and, beside them (not used for the choice), fitted on all inner
out-of-fold predictions and applied to the left-out benchmark: its AUROC,
and the catch and flag rates at the threshold
:func:`recovery.confidence.choose_threshold` picks on the inner
predictions (15 % per benchmark, as shipped). An image the estimator
cannot read (a fallback) counts as confidence 0.

Evidence beyond the ten inputs, each computed with the estimator that made
the prediction: ``dist`` each classical estimate's log distance from the
answer (19); ``z`` the model's standardised input vector (36); ``knn`` the
log mean distance to the 10 nearest of 1,500 of that estimator's training
photographs in its input space; ``win`` (``--windows``: nine feature
extractions per image) the 3 x 3 windows' learnt estimates
(:mod:`recovery.light_mixture`'s windows): RMS and largest distance from
the answer, their spread, the share of valid windows; ``lev`` and ``ens``
(``--leverage``) the estimator's own predictive uncertainty: the log
leverage ``phi(x)^T (Phi^T U Phi + 2 lambda I)^-1 phi(x)`` of the image in
the estimator's expanded input space (``U`` the last reweighting step's
weights of :func:`recovery.learned.fit_robust_ridge`, rebuilt from its
training images, ``lambda`` :data:`LEVERAGE_RIDGE`), and the log spread of
the predictions of refits leaving out each training camera and of
bootstrap refits (:func:`leverage_evidence`); ``hd``, ``hd2``, ``hdv``
(``--histogram``) the disagreement of a second, differently built
estimator with the learnt answer: a ridge regression from luminance-weighted
log-chroma histograms of the cells and of their edges
(:func:`log_chroma_histogram`, :func:`fit_histogram_ridge`) to the light,
fitted within the same folds (:func:`histogram_evidence`); ``fd``, ``fw``
(``--ffcc``) the same with the convolutional histogram estimator of
:mod:`recovery.chroma_histogram` (Barron & Tsai 2017) and its posterior's
width (:func:`ffcc_evidence`); ``bd``, ``bw`` (``--bayes``) the light
posterior's (:func:`recovery.bayes.estimate_bayes`, the camera derived from
its colour matrix as for a RAW upload; it learns nothing from the
photographs, so one run serves every fold) disagreement with the learnt
answer and its own width: its posterior spread, entropy and confidence
(:func:`bayes_evidence`). ``--paired`` prints each variant's inner gain
over the shipped stumps with a paired bootstrap of the images scored
(:func:`paired_bootstrap`); ``--quick --third K`` scores one of three
disjoint thirds of the images (a measure of how the gains move with them).

Usage::

    python -m benchmarks.flag_variants [--windows] [--leverage] [--histogram] [--ffcc] [--bayes [--bayes-cache F]] [--paired] [--only NAMES] [--quick [--third K]]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from recovery import confidence as C
from recovery import learned as L

from . import train_illuminant as T
from .realdata import REAL_DIR, load_real, usable_mask

_FLOOR = 2e-3


def window_features(rs) -> np.ndarray:
    """(N, 9, F, 2) the classical estimates of each image's 3 x 3 windows
    (NaN where a window is unusable), as :func:`recovery.light_mixture.window_evidence` reads them."""
    from recovery.light_mixture import MIN_WINDOW_CELLS, window_slices

    out = np.full((len(rs.truth), 9, len(L.FEATURE_NAMES), 2), np.nan)
    for i, (img, cam) in enumerate(zip(rs.images, rs.camera)):
        can, ok, _, _ = L.canonical_analysis(img, usable_mask(img), rs.matrices[cam], L.BRADFORD)
        for k, sl in enumerate(window_slices(ok.shape)[0][:9]):
            if int(ok[sl].sum()) >= MIN_WINDOW_CELLS:
                try:
                    out[i, k] = L.features(can[sl], ok[sl])
                except L.InsufficientSurfaceVariation:
                    pass
    return out


#: the ridge at which the leverage and the ensemble are computed (the shipped
#: model averages the coefficients of fits at 0.03, 0.1, 1 and 10; 0.1 is
#: :func:`recovery.learned.fit_robust_ridge`'s default, set before any figure)
LEVERAGE_RIDGE = 0.1
#: bootstrap replicates of the ensemble
BOOTSTRAPS = 8


def training_system(model, feats, tuv, dataset, camera, train_rows, settings=T.SETTINGS, ridge=LEVERAGE_RIDGE):
    """The weighted least-squares system of ``model``'s last IRLS step,
    rebuilt as :func:`benchmarks.train_illuminant.fit_model` fitted it on
    images ``train_rows`` (with their augmented copies): ``Z`` (M, P) the
    expanded inputs, ``u`` (M,) the weights ``w / r`` at the model's
    residuals ``r`` (:func:`recovery.learned.fit_robust_ridge`), ``y`` (M, 2)
    the targets, ``A = Z^T U Z + 2 ridge I`` (the constant not penalised),
    and each row's camera (copies too)."""
    f, t = feats[train_rows], tuv[train_rows]
    fa, ta = T.augment(f, t, np.random.default_rng(settings["augment_seed"]), settings)
    allf, allt = np.concatenate([f, fa]), np.concatenate([t, ta])
    w = np.tile(T.balance_weights(dataset[train_rows], camera[train_rows]), 2)
    w = w / w.sum()
    pw, pb = L.random_expansion(len(model.mean), int(model.expansion[0]), int(model.expansion[1]))
    Z = L.expand(model.inputs(allf), model.mean, model.scale, pw, pb)
    y = allt - allf[:, L.REFERENCE]
    r = np.sqrt(((Z @ model.coef - y) ** 2).sum(axis=1) + settings["delta"] ** 2)
    u = w / r
    P = 2.0 * ridge * np.diag(np.r_[np.ones(Z.shape[1] - 1), 0.0])
    A = (Z * u[:, None]).T @ Z + P
    return {"Z": Z, "u": u, "y": y, "A": A, "P": P, "cam": np.tile(camera[train_rows], 2),
            "img": np.tile(np.arange(len(train_rows)), 2)}


def leverage_evidence(model, feats, rows, uv, system) -> dict:
    """``lev``: log of the leverage ``phi(x)^T A^-1 phi(x)`` of images ``rows``
    in ``model``'s expanded input space (its predictive variance up to the
    noise scale); ``ens``: log RMS spread of the predictions of ridge refits
    (the last IRLS step's weights kept) leaving out each training camera,
    (four random folds of its images where it has one camera), and of
    :data:`BOOTSTRAPS` Poisson-bootstrap refits of the training
    images, about the full refit's; ``lev1``, ``lev10`` the leverage at
    ridges 1 and 10."""
    pw, pb = L.random_expansion(len(model.mean), int(model.expansion[0]), int(model.expansion[1]))
    phi = L.expand(model.inputs(feats[rows]), model.mean, model.scale, pw, pb)
    Z, u, y, A, P = (system[k] for k in ("Z", "u", "y", "A", "P"))
    Lc = np.linalg.cholesky(A)
    v = np.linalg.solve(Lc, phi.T)
    lev = (v ** 2).sum(0)
    Zu = Z * u[:, None]
    b = Zu.T @ y
    full = phi @ np.linalg.solve(A, b)
    loco = []
    cams = system["cam"]
    if len(set(cams.tolist())) < 2:      # one camera (Cube+ alone): four random folds of its images instead
        cams = np.random.default_rng(0).integers(0, 4, system["img"].max() + 1)[system["img"]]
    for c in sorted(set(cams.tolist())):
        m = cams == c
        Am = A - Zu[m].T @ Z[m]
        loco.append(phi @ np.linalg.solve(Am, b - Zu[m].T @ y[m]))
    rng = np.random.default_rng(0)
    boot = []
    for _ in range(BOOTSTRAPS):
        k = rng.poisson(1.0, system["img"].max() + 1)[system["img"]].astype(float)
        Zk = Zu * k[:, None]
        boot.append(phi @ np.linalg.solve(Zk.T @ Z + P, Zk.T @ y))

    def spread(preds):
        return np.sqrt(np.mean([((p - full) ** 2).sum(1) for p in preds], axis=0))

    ZUZ = A - P
    other = {}
    for r in (1.0, 10.0):        # the leverage at the grid's larger ridges (a larger floor under the training's spread)
        Pr = P * (r / LEVERAGE_RIDGE)
        other[f"lev{r:g}"] = np.log((np.linalg.solve(np.linalg.cholesky(ZUZ + Pr), phi.T) ** 2).sum(0))[:, None]
    return {"lev": np.log(lev)[:, None], **other,
            "ens": np.stack([np.log(spread(loco) + 1e-6), np.log(spread(boot) + 1e-6)], axis=1)}


#: The log-chroma histogram estimator (``--histogram``): bins per axis and
#: the range of ``(u, v) = (log g/r, log g/b)`` in the canonical space (the
#: 1st-99th percentiles of the development cells' u, -1.3 to 0.5, and v,
#: -0.7 to 2.8, a little widened; a value beyond it counts in the last bin),
#: and the ridges its fit chooses among. Set before any figure.
HIST_BINS = 16
HIST_RANGE = ((-1.4, 0.7), (-0.8, 3.0))
HIST_RIDGES = (1e-4, 1e-3, 1e-2, 1e-1)


def _bin(x, lo, hi, bins):
    return np.clip(np.floor((x - lo) / (hi - lo) * bins).astype(np.int64), 0, bins - 1)


def log_chroma_histogram(cells, ok, bins=HIST_BINS, limits=HIST_RANGE) -> np.ndarray:
    """(2 * bins * bins,) the square roots of two normalised 2-D histograms
    of log-chroma ``(log g/r, log g/b)`` (Barron 2015; Barron & Tsai 2017):
    of the usable cells with positive channels, each weighing its luminance
    ``r + g + b``, and of their edge image
    (:func:`recovery.chroma_histogram.edge_image`), each edge weighing its
    size; ``bins`` equal bins per axis over ``limits``, a value beyond them
    counted in the last bin. Square roots: each histogram has unit norm
    (the Hellinger embedding). A histogram with no weight is zero."""
    from recovery.chroma_histogram import _log_chroma, edge_image

    c = np.asarray(cells, float)
    good = np.asarray(ok, bool) & np.all(c > 0, axis=-1)
    e, eok = edge_image(c, good)
    eok &= np.all(e > 1e-9, axis=-1)
    out = []
    for x in (c[good], e[eok]):
        h = np.zeros(bins * bins)
        if len(x):
            uv = _log_chroma(x)
            k = _bin(uv[:, 0], *limits[0], bins) * bins + _bin(uv[:, 1], *limits[1], bins)
            h = np.bincount(k, weights=x.sum(axis=1), minlength=bins * bins)
            h = h / h.sum()
        out.append(np.sqrt(h))
    return np.concatenate(out)


def histogram_features(rs) -> np.ndarray:
    """(N, 2 * HIST_BINS ** 2) :func:`log_chroma_histogram` of each image's
    canonical analysis cells (:func:`recovery.learned.canonical_analysis`)."""
    out = np.zeros((len(rs.truth), 2 * HIST_BINS ** 2))
    for i, (img, cam) in enumerate(zip(rs.images, rs.camera)):
        can, ok, _, _ = L.canonical_analysis(img, usable_mask(img), rs.matrices[cam], L.BRADFORD)
        out[i] = log_chroma_histogram(can, ok)
    return out


def fit_histogram_ridge(X, y, w, groups, ridges=HIST_RIDGES) -> tuple[np.ndarray, np.ndarray, float]:
    """A weighted ridge regression from histograms ``X`` (n, d) to the
    lights' log-chroma ``y`` (n, 2), weights ``w``, the intercept not
    penalised; the ridge the one of ``ridges`` with the lowest weighted mean
    log-chroma distance when each of ``groups`` (cameras; four fixed random
    folds where there is one) is predicted by a fit on the others. Returns
    ``(coef (d, 2), intercept (2,), ridge)``."""
    w = np.asarray(w, float) / np.sum(w)
    groups = np.asarray(groups)
    if len(set(groups.tolist())) < 2:
        groups = np.random.default_rng(0).integers(0, 4, len(y))

    def fit(rows, r):
        ww = w[rows] / w[rows].sum()
        mx, my = ww @ X[rows], ww @ y[rows]
        Xc = X[rows] - mx
        A = (Xc * ww[:, None]).T @ Xc + r * np.eye(X.shape[1])
        b = np.linalg.solve(A, (Xc * ww[:, None]).T @ (y[rows] - my))
        return b, my - mx @ b

    best = None
    for r in ridges:
        d = np.zeros(len(y))
        for g in sorted(set(groups.tolist())):
            te = groups == g
            b, c = fit(np.flatnonzero(~te), r)
            d[te] = np.linalg.norm(X[te] @ b + c - y[te], axis=1)
        s = float(w @ d)
        if best is None or s < best[0]:
            best = (s, r)
    b, c = fit(np.arange(len(y)), best[1])
    return b, c, best[1]


def histogram_evidence(hf, tuv, feats, dataset, camera, fit_rows, rows, uv) -> tuple[dict, np.ndarray, float]:
    """The histogram estimator fitted on images ``fit_rows`` (each
    benchmark and camera weighing the same) and applied to images ``rows``,
    whose learnt estimates are ``uv``: ``hd`` the log distance (canonical
    log-chroma) between its answer and the learnt one; ``hd2`` that and its
    log distance from the reference (bright-pixel) estimate; ``hdv`` the
    difference itself (2). Also its answers and the ridge chosen."""
    b, c, r = fit_histogram_ridge(hf[fit_rows], tuv[fit_rows], T.balance_weights(dataset[fit_rows], camera[fit_rows]),
                                  camera[fit_rows])
    h = hf[rows] @ b + c
    hd = np.log(np.linalg.norm(h - uv, axis=1) + _FLOOR)[:, None]
    hr = np.log(np.linalg.norm(h - feats[rows, L.REFERENCE], axis=1) + _FLOOR)[:, None]
    return {"hd": hd, "hd2": np.concatenate([hd, hr], axis=1), "hdv": h - uv}, h, r


#: The convolutional (FFCC) estimator's fit (``--ffcc``):
#: :data:`benchmarks.train_illuminant.HIST_SETTINGS` (no bias map: a
#: likelihood that moves with the light, tv 1e-3), its iterations capped at 200
#: for time. Set before any figure.
FFCC_SETTINGS = {"maxiter": 200}


def ffcc_evidence(hist, tuv, dataset, camera, fit_rows, rows, uv, log=print) -> tuple[dict, np.ndarray]:
    """The convolutional estimator (:mod:`recovery.chroma_histogram`, Barron
    & Tsai 2017) fitted on images ``fit_rows`` (:func:`benchmarks.train_illuminant.fit_histogram`,
    each benchmark and camera weighing the same) and applied alone (no first stage) to images ``rows``, whose
    learnt estimates are ``uv``: ``fd`` the log distance (canonical log-chroma, the nearer image on the torus)
    between its answer (the windowed posterior mean about its mode) and the learnt one; ``fw`` its own
    uncertainty: the log RMS width of its posterior in that window, and the entropy of ``softmax(H)`` over the
    grid. Also its answers."""
    from recovery import chroma_histogram as CH

    st = {**T.HIST_SETTINGS, **FFCC_SETTINGS}
    grid = CH.Grid(*st["grid"])
    f, b, _ = T.fit_histogram(hist[fit_rows], tuv[fit_rows], T.balance_weights(dataset[fit_rows], camera[fit_rows]),
                              st, log=log)
    h_all, cov_all, ent_all = [], [], []
    for a in range(0, len(rows), 500):
        h = CH.scores(np.asarray(hist[rows[a:a + 500]], float), f, b)
        m, cov = CH.posterior_mean(h, grid)
        z = h.reshape(len(h), -1)
        z = z - z.max(axis=1, keepdims=True)
        p = np.exp(z)
        p /= p.sum(axis=1, keepdims=True)
        ent_all.append(-(p * np.log(p + 1e-300)).sum(axis=1))
        h_all.append(m)
        cov_all.append(cov)
    est, cov, ent = np.concatenate(h_all), np.concatenate(cov_all), np.concatenate(ent_all)
    period = np.array([grid.nu, grid.nv]) * grid.step
    d = (est - uv + period / 2) % period - period / 2
    fd = np.log(np.linalg.norm(d, axis=1) + _FLOOR)[:, None]
    fw = np.stack([0.5 * np.log(np.trace(cov, axis1=1, axis2=2) + 1e-6), ent], axis=1)
    return {"fd": fd, "fw": fw}, uv + d


def bayes_evidence(rs, Ks, cache=None, log=print) -> dict:
    """The light posterior of every image (:func:`recovery.bayes.estimate_bayes`
    with the default candidates and reflectances; the camera from its colour
    matrix, :func:`recovery.cameras.camera_from_matrix`, as a RAW upload of a
    camera without measured sensitivities gets): ``uv`` (N, 2) its estimate in
    the canonical log-chroma of :func:`benchmarks.train_illuminant.dataset_features`
    (NaN after a fallback), ``w`` (N, 3) its log posterior spread (degrees), its
    posterior entropy and the logit of its own confidence. ``cache``: an
    ``.npz`` of the posteriors (with each image's seconds, ``time``) read when
    it exists, written otherwise (41 s for the 7,524 photographs on one core)."""
    from pathlib import Path

    from benchmarks.realdata import usable_mask
    from recovery.bayes import estimate_bayes
    from recovery.cameras import camera_from_matrix

    n = len(rs.truth)
    if cache is not None and Path(cache).exists():
        with np.load(cache) as z:
            d = {k: z[k] for k in z.files}
        if len(d["rgb"]) != n:
            raise SystemExit(f"{cache} holds {len(d['rgb'])} images, not {n} (--quick needs its own cache)")
    else:
        cams = {k: camera_from_matrix(m) for k, m in rs.matrices.items()}
        d = {"rgb": np.full((n, 3), np.nan), "spread": np.full(n, np.nan), "entropy": np.full(n, np.nan),
             "conf": np.full(n, np.nan), "time": np.zeros(n), "fallback": np.zeros(n, bool)}
        t0 = time.perf_counter()
        for i in range(n):
            a = time.perf_counter()
            r, spec, g = estimate_bayes(rs.images[i], usable_mask(rs.images[i]), cams[rs.camera[i]])
            d["rgb"][i], d["fallback"][i] = r, spec is None
            d["spread"][i] = g.get("posterior_spread_deg", np.nan)
            d["entropy"][i] = g.get("posterior_entropy", np.nan)
            d["conf"][i] = g.get("confidence", np.nan)
            d["time"][i] = time.perf_counter() - a
            if i % 1000 == 999:
                log(f"  light posterior: {i + 1} images, {time.perf_counter() - t0:.0f} s")
        if cache is not None:
            np.savez(cache, **d)
    rgb = np.where(d["fallback"][:, None], np.nan, d["rgb"])           # NaN rows stay NaN
    K = np.stack([Ks[c] for c in rs.camera])
    uv = L.rgb_to_uv(np.clip(np.einsum("nij,nj->ni", K, rgb), 1e-9, None))
    c = np.clip(np.nan_to_num(d["conf"], nan=0.0), 1e-4, 1 - 1e-4)
    w = np.stack([np.log(np.nan_to_num(d["spread"], nan=90.0) + 0.05), np.nan_to_num(d["entropy"], nan=5.0),
                  np.log(c / (1 - c))], axis=1)
    return {"uv": uv, "w": w}


def extra_evidence(model, feats, rows, uv, ref_rows, wf=None, system=None, bz=None) -> dict:
    """The further evidence of images ``rows`` whose estimates ``uv``
    ``model`` made; ``ref_rows`` its training images (the nearest-neighbour references);
    ``bz`` the light posterior's (:func:`bayes_evidence`)."""
    f = feats[rows]
    d = np.linalg.norm(f - uv[:, None, :], axis=-1)
    out = {"dist": np.log(d + _FLOOR)}
    z = (model.inputs(f) - model.mean) / model.scale
    out["z"] = z
    zr = (model.inputs(feats[ref_rows]) - model.mean) / model.scale
    sub = zr[np.random.default_rng(0).choice(len(zr), min(1500, len(zr)), replace=False)]
    D = np.sqrt(np.maximum((z ** 2).sum(1)[:, None] + (sub ** 2).sum(1)[None] - 2 * z @ sub.T, 0.0))
    out["knn"] = np.log(np.sort(D, axis=1)[:, :10].mean(1) + 1e-3)[:, None]
    if system is not None:
        out.update(leverage_evidence(model, feats, rows, uv, system))
    if bz is not None:
        db = np.linalg.norm(bz["uv"][rows] - uv, axis=1)
        out["bd"] = np.log(np.where(np.isfinite(db), db, 1.0) + _FLOOR)[:, None]
        out["bw"] = bz["w"][rows]
    if wf is not None:
        w = wf[rows]
        valid = np.all(np.isfinite(w), axis=(2, 3))
        wu = np.full((len(rows), 9, 2), np.nan)
        if valid.any():
            wu[valid] = model.predict(model.inputs(w[valid])) + w[valid][:, L.REFERENCE]
        dd = np.where(valid, np.linalg.norm(np.where(valid[..., None], wu, 0.0) - uv[:, None, :], axis=-1), np.nan)
        n = valid.sum(1)
        few = n < 2
        with np.errstate(all="ignore"):
            rms = np.sqrt(np.nanmean(dd ** 2, axis=1))
            mx = np.nanmax(dd, axis=1)
            mean = np.nanmean(np.where(valid[..., None], wu, np.nan), axis=1, keepdims=True)
            sp = np.sqrt(np.nanmean(np.where(valid, ((wu - mean) ** 2).sum(-1), np.nan), axis=1))
        whole = d.mean(1)
        out["win"] = np.stack([np.log(np.where(few, whole, rms) + _FLOOR), np.log(np.where(few, whole, mx) + _FLOOR),
                               np.log(np.where(few, whole, sp) + _FLOOR), n / 9.0], axis=1)
    return out


class Law:
    """A confidence law: ``"logistic"`` (:func:`recovery.confidence.fit_logistic`),
    ``"stumps"`` (:func:`recovery.confidence.fit_stumps`, ``rounds``) or ``"trees2"``
    (:func:`recovery.confidence.fit_trees`, depth 2, ``rounds``, ``rate``)."""

    def __init__(self, kind: str, rounds: int = 200, rate: float = 0.1):
        self.kind, self.rounds, self.rate = kind, rounds, rate

    def fit(self, x, ok3, w):
        if self.kind == "stumps":
            self.c0, self.st = C.fit_stumps(x, ok3, w, rounds=self.rounds)
        elif self.kind == "trees2":
            self.c0, self.st = C.fit_trees(x, ok3, w, rounds=self.rounds, rate=self.rate)
        else:
            self.m, self.s = x.mean(0), x.std(0) + 1e-9
            self.c = C.fit_logistic((x - self.m) / self.s, ok3, w, T.FLAG_SETTINGS["l2"])
        return self

    def confidence(self, x):
        if self.kind == "stumps":
            a = C.stump_score(x, self.c0, self.st)
        elif self.kind == "trees2":
            a = C.tree_score(x, self.c0, self.st)
        else:
            a = self.c[0] + ((x - self.m) / self.s) @ self.c[1:]
        return 1.0 / (1.0 + np.exp(-np.clip(a, -50, 50)))


def folds(rs, feats, tuv, Ks, gam, regions, wf, log=print, leverage=False, hf=None, ch=None, bz=None) -> dict:
    """Per left-out benchmark: the inner out-of-fold rows, errors, benchmarks,
    ten inputs and further evidence, and the same for the left-out images."""
    good = T.usable(feats)
    loc = T.locus()
    out = {}
    for b in rs.datasets:
        t0 = time.perf_counter()
        tr = np.flatnonzero((rs.dataset != b) & good)
        te = np.flatnonzero(rs.dataset == b)
        ridge, sigma, conf, _, oof = T.select_and_calibrate(rs, feats, tuv, Ks, tr, loc, T.SETTINGS, lambda s: None,
                                                            gam, regions)
        ex = {}
        for g, m in oof["models"].items():
            sel = rs.dataset[tr] == g
            sy = training_system(m, feats, tuv, rs.dataset, rs.camera, tr[~sel]) if leverage else None
            ev = extra_evidence(m, feats, tr[sel], oof["uv"][sel], tr[~sel], wf, sy, bz)
            if hf is not None:
                hev, h, r = histogram_evidence(hf, tuv, feats, rs.dataset, rs.camera, tr[~sel], tr[sel], oof["uv"][sel])
                ev.update(hev)
                e_h = T.camera_errors(h, rs.truth[tr[sel]], rs.camera[tr[sel]], Ks)
                log(f"    histogram estimator (ridge {r:g}) on {g}: mean / median {e_h.mean():.2f} / "
                    f"{np.median(e_h):.2f} deg (learnt {oof['err'][sel].mean():.2f} / {np.median(oof['err'][sel]):.2f})")
            if ch is not None:
                fev, h = ffcc_evidence(ch, tuv, rs.dataset, rs.camera, tr[~sel], tr[sel], oof["uv"][sel], log)
                ev.update(fev)
                e_h = T.camera_errors(h, rs.truth[tr[sel]], rs.camera[tr[sel]], Ks)
                log(f"    FFCC estimator on {g}: mean / median {e_h.mean():.2f} / {np.median(e_h):.2f} deg")
            for k, v in ev.items():
                ex.setdefault(k, np.zeros((len(tr), v.shape[1])))[sel] = v
        model = T.fit_model(feats[tr], tuv[tr], rs.dataset[tr], rs.camera[tr], ridge, loc, T.SETTINGS, sigma, conf,
                            {}, gam=gam[tr])
        res = T.apply(model, rs, feats, tuv, Ks, te, None, gam, None, None)
        u = res["usable"]
        x_te = T.flag_inputs(model, feats, res["uv"][u], gam, regions, te[u])
        ex_te = extra_evidence(model, feats, te[u], res["uv"][u], tr, wf,
                               training_system(model, feats, tuv, rs.dataset, rs.camera, tr) if leverage else None, bz)
        if hf is not None:
            hev, h, r = histogram_evidence(hf, tuv, feats, rs.dataset, rs.camera, tr, te[u], res["uv"][u])
            ex_te.update(hev)
            e_h = T.camera_errors(h, rs.truth[te[u]], rs.camera[te[u]], Ks)
            log(f"    histogram estimator (ridge {r:g}) on {b} (left out): mean / median {e_h.mean():.2f} / "
                f"{np.median(e_h):.2f} deg")
        if ch is not None:
            fev, h = ffcc_evidence(ch, tuv, rs.dataset, rs.camera, tr, te[u], res["uv"][u], log)
            ex_te.update(fev)
            e_h = T.camera_errors(h, rs.truth[te[u]], rs.camera[te[u]], Ks)
            log(f"    FFCC estimator on {b} (left out): mean / median {e_h.mean():.2f} / {np.median(e_h):.2f} deg")
        out[b] = {"inner": {"rows": tr, "err": oof["err"], "x": oof["x"], "ex": ex, "grp": rs.dataset[tr],
                            "cam": rs.camera[tr]},
                  "out": {"x": x_te, "ex": ex_te, "usable": u, "err_all": res["err"]}}
        log(f"  fold {b} left out: {time.perf_counter() - t0:.0f} s")
    return out


def _x(part, keys):
    """The columns of variant ``keys``: ``base`` the ten inputs, ``base-idist`` them without
    ``log_input_distance``, ``idist`` that one alone, otherwise a further evidence's."""
    j = C.INPUT_NAMES.index("log_input_distance")

    def cols(k):
        if k == "base":
            return part["x"]
        if k == "base-idist":
            return np.delete(part["x"], j, axis=1)
        if k == "idist":
            return part["x"][:, [j]]
        return part["ex"][k]

    return np.concatenate([cols(k) for k in keys], axis=1)


def score(F, keys, law) -> dict:
    """Inner LOBO and LOCO AUROC, and the left-out AUROC, catch and flag, per outer fold."""
    res = {}
    for b, f in F.items():
        inn, out = f["inner"], f["out"]
        xi, xo = _x(inn, keys), _x(out, keys)
        w = T.balance_weights(inn["grp"], inn["cam"])
        fail, ok3 = inn["err"] > 6, inn["err"] < 3
        lobo, lobo_conf = [], np.zeros(len(xi))
        for g in sorted(set(inn["grp"].tolist())):
            tr, te = inn["grp"] != g, inn["grp"] == g
            lobo_conf[te] = law.fit(xi[tr], ok3[tr], w[tr]).confidence(xi[te])
            lobo.append(C.auroc(-lobo_conf[te], fail[te]))
        loco = np.zeros(len(xi))
        for c in sorted(set(inn["cam"].tolist())):
            te = inn["cam"] == c
            loco[te] = law.fit(xi[~te], ok3[~te], w[~te]).confidence(xi[te])
        loco_auc = np.mean([C.auroc(-loco[inn["grp"] == g], fail[inn["grp"] == g]) for g in sorted(set(inn["grp"].tolist()))])
        law.fit(xi, ok3, w)
        t, _ = C.choose_threshold(law.confidence(xi), fail, inn["grp"], T.FLAG_SETTINGS["max_flag"])
        conf = np.zeros(len(out["err_all"]))
        conf[out["usable"]] = law.confidence(xo)
        fa, low = out["err_all"] > 6, conf < t
        res[b] = {"lobo": float(np.mean(lobo)), "loco": float(loco_auc), "auroc": C.auroc(1 - conf, fa),
                  "catch": float(low[fa].mean()), "flag": float(low.mean()),
                  "conf": {"lobo": lobo_conf, "loco": loco}, "fail": fail, "grp": inn["grp"]}
    return res


#: resamples of :func:`paired_bootstrap`
RESAMPLES = 200


def paired_bootstrap(r, ref, resamples=RESAMPLES, seed=0) -> dict:
    """The inner AUROC gain of variant results ``r`` over ``ref``
    (:func:`score`, the same images) and its spread from the sampling of the
    images scored: the images of each inner benchmark of each outer fold
    resampled with replacement (the same draw for both variants; the fitted
    laws kept), the gain (mean over outer folds of the mean over inner
    benchmarks, as printed) recomputed. Returns, per protocol (``lobo``,
    ``loco``), the gain, its bootstrap standard error and the share of
    resamples where it is positive. Only the scoring is resampled, not the
    fits: the fits' own variation is not in this spread."""
    rng = np.random.default_rng(seed)
    out = {}
    for proto in ("lobo", "loco"):
        gains = np.zeros(resamples + 1)
        for k in range(resamples + 1):
            per_fold = []
            for b in r:
                fail, grp = r[b]["fail"], r[b]["grp"]
                per_g = []
                for g in sorted(set(grp.tolist())):
                    idx = np.flatnonzero(grp == g)
                    if k:
                        idx = rng.choice(idx, len(idx))
                    per_g.append(C.auroc(-r[b]["conf"][proto][idx], fail[idx])
                                 - C.auroc(-ref[b]["conf"][proto][idx], fail[idx]))
                per_fold.append(np.mean(per_g))
            gains[k] = np.mean(per_fold)
        out[proto] = {"gain": float(gains[0]), "se": float(gains[1:].std(ddof=1)),
                      "positive": float(np.mean(gains[1:] > 0))}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(REAL_DIR))
    ap.add_argument("--windows", action="store_true", help="also the 3 x 3 windows' evidence (slow)")
    ap.add_argument("--trees", action="store_true", help="also boosted trees of depth 2 on the ten inputs")
    ap.add_argument("--leverage", action="store_true",
                    help="also the estimator's own uncertainty: its leverage and its ensemble's spread")
    ap.add_argument("--histogram", action="store_true",
                    help="also a second, differently built estimator's disagreement with the learnt one: a ridge "
                         "regression on log-chroma histograms of the cells and their edges")
    ap.add_argument("--ffcc", action="store_true",
                    help="also the disagreement of a convolutional log-chroma histogram estimator (FFCC) with the "
                         "learnt one, and its posterior's width (slow: one L-BFGS fit per fold)")
    ap.add_argument("--bayes", action="store_true",
                    help="also the light posterior's disagreement with the learnt answer and its width (under a "
                         "minute for the posteriors; --bayes-cache keeps them)")
    ap.add_argument("--bayes-cache", default=None, help="an .npz of the light posteriors: read if it exists, else written")
    ap.add_argument("--only", default=None,
                    help="comma-separated variant names as printed (e.g. 'base; stumps 200,base+lev; stumps 200')")
    ap.add_argument("--paired", action="store_true",
                    help="also each variant's inner gain over the shipped stumps with a paired bootstrap of the "
                         "images scored (its standard error; not a choice rule, a measure of the noise)")
    ap.add_argument("--quick", action="store_true", help="every third image (development; not the figures)")
    ap.add_argument("--third", type=int, default=0, choices=(0, 1, 2),
                    help="with --quick: which third (images k, k + 3, ...; the three are disjoint)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    rs = load_real(a.data)
    if a.quick:
        rs = rs.subset(np.arange(a.third, len(rs.truth), 3))
    feats, tuv, Ks, gam = T.dataset_features(rs)
    regions = T.dataset_regions(rs)
    wf = window_features(rs) if a.windows else None
    hf = histogram_features(rs) if a.histogram else None
    ch = T.dataset_histograms(rs) if a.ffcc else None
    bz = bayes_evidence(rs, Ks, a.bayes_cache) if a.bayes else None
    print(f"evidence of {len(rs.truth)} images: {time.perf_counter() - t0:.0f} s")
    with T.single_threaded():
        F = folds(rs, feats, tuv, Ks, gam, regions, wf, leverage=a.leverage, hf=hf, ch=ch, bz=bz)
    variants = [(["base"], Law("logistic")), (["base", "dist"], Law("logistic")), (["base", "z"], Law("logistic")),
                (["base", "knn"], Law("logistic")), (["base"], Law("stumps", 50)), (["base"], Law("stumps", 100)),
                (["base"], Law("stumps", 200)), (["base"], Law("stumps", 400)), (["base", "knn"], Law("stumps"))]
    if a.trees:
        variants += [(["base"], Law("trees2", 50)), (["base"], Law("trees2", 75)), (["base"], Law("trees2", 100)),
                     (["base"], Law("trees2", 150)), (["base"], Law("trees2", 200)), (["base"], Law("trees2", 200, 0.05)),
                     (["base", "knn"], Law("trees2", 100)), (["base", "dist"], Law("trees2", 100))]
    if wf is not None:
        variants += [(["base", "win"], Law("logistic")), (["base", "win"], Law("stumps"))]
    if a.leverage:
        variants += [(["base", "lev"], Law("logistic")), (["base", "lev"], Law("stumps")),
                     (["base", "ens"], Law("logistic")), (["base", "ens"], Law("stumps")),
                     (["base", "lev", "ens"], Law("stumps")), (["lev"], Law("logistic")), (["ens"], Law("logistic")),
                     (["base", "lev1"], Law("stumps")), (["base", "lev10"], Law("stumps")),
                     (["idist"], Law("logistic")), (["base-idist", "lev"], Law("stumps"))]
    if hf is not None:
        variants += [(["base", "hd"], Law("stumps")), (["base", "hd"], Law("logistic")),
                     (["base", "hd2"], Law("stumps")), (["base", "hdv"], Law("stumps")),
                     (["base", "hd", "hdv"], Law("stumps")), (["hd"], Law("logistic"))]
    if ch is not None:
        variants += [(["base", "fd"], Law("stumps")), (["base", "fd"], Law("logistic")),
                     (["base", "fd", "fw"], Law("stumps")), (["base", "fw"], Law("stumps")), (["fd"], Law("logistic")),
                     (["fd", "fw"], Law("logistic"))]
    if bz is not None:
        variants += [(["base", "bd"], Law("stumps")), (["base", "bd"], Law("logistic")),
                     (["base", "bw"], Law("stumps")), (["base", "bd", "bw"], Law("stumps")),
                     (["base", "bd", "bw"], Law("logistic")), (["bd"], Law("logistic")), (["bw"], Law("logistic")),
                     (["bd", "bw"], Law("logistic"))]
    if ch is not None and hf is not None:
        variants += [(["base", "hd", "fd", "fw"], Law("stumps"))]
    only = None if a.only is None else {v.strip() for v in a.only.split(",")}
    print("\nAUROC of (1 - confidence) for errors above 6 degrees; inner figures averaged over the three outer "
          "folds (the choice); left out: AUROC / catch / flag per benchmark (not used for the choice)")
    print(f"{'variant':34s} {'LOBO':>6s} {'LOCO':>6s} | " + " | ".join(f"{b[:16]:>16s}" for b in F))
    ref = None
    for keys, law in variants:
        name = ("+".join(keys) + f"; {law.kind}" + (f" {law.rounds}" if law.kind in ("stumps", "trees2") else "")
                + (f" rate {law.rate:g}" if law.rate != 0.1 else ""))
        if only is not None and name not in only:
            continue
        r = score(F, keys, law)
        print(f"{name:34s} {np.mean([v['lobo'] for v in r.values()]):6.3f} {np.mean([v['loco'] for v in r.values()]):6.3f} | "
              + " | ".join(f"{v['auroc']:.3f}/{v['catch']:.2f}/{v['flag']:.2f}" for v in r.values()), flush=True)
        if a.paired:
            if ref is None:
                ref = score(F, ["base"], Law("stumps", 200))
            pb = paired_bootstrap(r, ref)
            print(f"{'':34s} gain over the shipped stumps (paired bootstrap of the images scored, {RESAMPLES}): "
                  + "; ".join(f"{p.upper()} {v['gain']:+.3f} +- {v['se']:.3f} (> 0 in {v['positive']:.0%})"
                              for p, v in pb.items()), flush=True)
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
