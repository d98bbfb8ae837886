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
bootstrap refits (:func:`leverage_evidence`).

Usage::

    python -m benchmarks.flag_variants [--windows] [--leverage] [--only NAMES] [--quick]
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
    from recovery.light_mixture import MIN_WINDOW_CELLS, STEP, WINDOW, _starts

    out = np.full((len(rs.truth), 9, len(L.FEATURE_NAMES), 2), np.nan)
    for i, (img, cam) in enumerate(zip(rs.images, rs.camera)):
        can, ok, _, _ = L.canonical_analysis(img, usable_mask(img), rs.matrices[cam], L.BRADFORD)
        h, w = ok.shape
        k = 0
        for r in _starts(h, WINDOW, STEP):
            for c in _starts(w, WINDOW, STEP):
                sl = (slice(r, min(h, r + WINDOW)), slice(c, min(w, c + WINDOW)))
                if k < 9 and int(ok[sl].sum()) >= MIN_WINDOW_CELLS:
                    try:
                        out[i, k] = L.features(can[sl], ok[sl])
                    except L.InsufficientSurfaceVariation:
                        pass
                k += 1
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


def extra_evidence(model, feats, rows, uv, ref_rows, wf=None, system=None) -> dict:
    """The further evidence of images ``rows`` whose estimates ``uv``
    ``model`` made; ``ref_rows`` its training images (the nearest-neighbour references)."""
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
    """A confidence law: ``"logistic"`` (:func:`recovery.confidence.fit_logistic`)
    or ``"stumps"`` (:func:`recovery.confidence.fit_stumps`, ``rounds``)."""

    def __init__(self, kind: str, rounds: int = 200):
        self.kind, self.rounds = kind, rounds

    def fit(self, x, ok3, w):
        if self.kind == "stumps":
            self.c0, self.st = C.fit_stumps(x, ok3, w, rounds=self.rounds)
        else:
            self.m, self.s = x.mean(0), x.std(0) + 1e-9
            self.c = C.fit_logistic((x - self.m) / self.s, ok3, w, T.FLAG_SETTINGS["l2"])
        return self

    def confidence(self, x):
        a = C.stump_score(x, self.c0, self.st) if self.kind == "stumps" else self.c[0] + ((x - self.m) / self.s) @ self.c[1:]
        return 1.0 / (1.0 + np.exp(-np.clip(a, -50, 50)))


def folds(rs, feats, tuv, Ks, gam, regions, wf, log=print, leverage=False) -> dict:
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
            for k, v in extra_evidence(m, feats, tr[sel], oof["uv"][sel], tr[~sel], wf, sy).items():
                ex.setdefault(k, np.zeros((len(tr), v.shape[1])))[sel] = v
        model = T.fit_model(feats[tr], tuv[tr], rs.dataset[tr], rs.camera[tr], ridge, loc, T.SETTINGS, sigma, conf,
                            {}, gam=gam[tr])
        res = T.apply(model, rs, feats, tuv, Ks, te, None, gam, None, None)
        u = res["usable"]
        x_te = T.flag_inputs(model, feats, res["uv"][u], gam, regions, te[u])
        out[b] = {"inner": {"rows": tr, "err": oof["err"], "x": oof["x"], "ex": ex, "grp": rs.dataset[tr],
                            "cam": rs.camera[tr]},
                  "out": {"x": x_te, "ex": extra_evidence(model, feats, te[u], res["uv"][u], tr, wf,
                                                          training_system(model, feats, tuv, rs.dataset, rs.camera, tr)
                                                          if leverage else None),
                          "usable": u, "err_all": res["err"]}}
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
        lobo = []
        for g in sorted(set(inn["grp"].tolist())):
            tr, te = inn["grp"] != g, inn["grp"] == g
            lobo.append(C.auroc(-law.fit(xi[tr], ok3[tr], w[tr]).confidence(xi[te]), fail[te]))
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
                  "catch": float(low[fa].mean()), "flag": float(low.mean())}
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(REAL_DIR))
    ap.add_argument("--windows", action="store_true", help="also the 3 x 3 windows' evidence (slow)")
    ap.add_argument("--leverage", action="store_true",
                    help="also the estimator's own uncertainty: its leverage and its ensemble's spread")
    ap.add_argument("--only", default=None,
                    help="comma-separated variant names as printed (e.g. 'base; stumps 200,base+lev; stumps 200')")
    ap.add_argument("--quick", action="store_true", help="every third image (development; not the figures)")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    rs = load_real(a.data)
    if a.quick:
        rs = rs.subset(np.arange(0, len(rs.truth), 3))
    feats, tuv, Ks, gam = T.dataset_features(rs)
    regions = T.dataset_regions(rs)
    wf = window_features(rs) if a.windows else None
    print(f"evidence of {len(rs.truth)} images: {time.perf_counter() - t0:.0f} s")
    with T.single_threaded():
        F = folds(rs, feats, tuv, Ks, gam, regions, wf, leverage=a.leverage)
    variants = [(["base"], Law("logistic")), (["base", "dist"], Law("logistic")), (["base", "z"], Law("logistic")),
                (["base", "knn"], Law("logistic")), (["base"], Law("stumps", 50)), (["base"], Law("stumps", 100)),
                (["base"], Law("stumps", 200)), (["base"], Law("stumps", 400)), (["base", "knn"], Law("stumps"))]
    if wf is not None:
        variants += [(["base", "win"], Law("logistic")), (["base", "win"], Law("stumps"))]
    if a.leverage:
        variants += [(["base", "lev"], Law("logistic")), (["base", "lev"], Law("stumps")),
                     (["base", "ens"], Law("logistic")), (["base", "ens"], Law("stumps")),
                     (["base", "lev", "ens"], Law("stumps")), (["lev"], Law("logistic")), (["ens"], Law("logistic")),
                     (["base", "lev1"], Law("stumps")), (["base", "lev10"], Law("stumps")),
                     (["idist"], Law("logistic")), (["base-idist", "lev"], Law("stumps"))]
    only = None if a.only is None else {v.strip() for v in a.only.split(",")}
    print("\nAUROC of (1 - confidence) for errors above 6 degrees; inner figures averaged over the three outer "
          "folds (the choice); left out: AUROC / catch / flag per benchmark (not used for the choice)")
    print(f"{'variant':34s} {'LOBO':>6s} {'LOCO':>6s} | " + " | ".join(f"{b[:16]:>16s}" for b in F))
    for keys, law in variants:
        name = "+".join(keys) + f"; {law.kind}" + (f" {law.rounds}" if law.kind == "stumps" else "")
        if only is not None and name not in only:
            continue
        r = score(F, keys, law)
        print(f"{name:34s} {np.mean([v['lobo'] for v in r.values()]):6.3f} {np.mean([v['loco'] for v in r.values()]):6.3f} | "
              + " | ".join(f"{v['auroc']:.3f}/{v['catch']:.2f}/{v['flag']:.2f}" for v in r.values()), flush=True)
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
