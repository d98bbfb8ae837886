"""A learnt model fitted on windows against the whole-image model applied to them (issue 27, item 1).

``python -m benchmarks.window_model`` (about 3 minutes on the quiet 2-core machine; the windows' classical
estimates are cached in ``--cache``, default ``out/window_features.npz``).

The light map's windows (:func:`recovery.light_mixture.window_evidence`: 3 x 3 windows of half the analysis
grid's side) are read by the learnt model fitted on *whole* photographs. A window holds a quarter of the
scene, so its classical estimates are noisier and differently distributed; would a model fitted on windows
read them better? Leave one benchmark out: on the other two, the whole-image model (:func:`fit_model` with
the shipped model's ridges, on the whole photographs) and a window model (the same fit on every usable
window of those photographs, each window labelled with its photograph's measured light and weighing as
much as any other window of its camera, as photographs do in the whole-image fit); on the left-out benchmark's single-light photographs, each usable window's
error, each whole photograph's, and the error of the windows' mean per photograph (what the map's level
leans on). Not shipped (docs/mixed_light.md, "A model fitted on windows").
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from recovery import learned as L
from recovery import light_mixture as LM

from . import train_illuminant as T
from .realdata import REAL_DIR, load_real, usable_mask


def window_features_all(rs) -> np.ndarray:
    """(N, 9, F, 2) each photograph's windows' classical estimates as the product computes them
    (:func:`recovery.learned.window_features`), NaN where a window is not usable."""
    W = np.full((len(rs.truth), 9, len(L.FEATURE_NAMES), 2), np.nan)
    for i, (img, cam) in enumerate(zip(rs.images, rs.camera)):
        can, ok, _, _ = L.canonical_analysis(img, usable_mask(img), rs.matrices[cam], L.BRADFORD)
        wins = LM.window_slices(ok.shape)[0]
        enough = [k for k, sl in enumerate(wins) if int(ok[sl].sum()) >= LM.MIN_WINDOW_CELLS]
        if enough:
            f_all, v_all = L.window_features(can, ok, [wins[k] for k in enough])
            for k, f, v in zip(enough, f_all, v_all):
                if v:
                    W[i, k] = f
    return W


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(REAL_DIR))
    ap.add_argument("--cache", default="out/window_features.npz")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    rs = load_real(a.data)
    cache = Path(a.cache)
    if cache.exists():
        z = np.load(cache)
        feats, tuv, gam, W = z["feats"], z["tuv"], z["gam"], z["W"]
        Ks = {k: L.canonical_transform(m, L.BRADFORD) for k, m in rs.matrices.items()}
    else:
        feats, tuv, Ks, gam = T.dataset_features(rs)
        W = window_features_all(rs)
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, feats=feats, tuv=tuv, gam=gam, W=W)
    print(f"evidence {time.perf_counter() - t0:.0f} s", flush=True)
    ridge = L.load_model().info["selection"]["chosen_ridge"]
    loc = T.locus()
    good = T.usable(feats)
    ds, cams = rs.dataset, rs.camera
    wv = np.all(np.isfinite(W), axis=(2, 3))          # (N, 9) usable windows
    print("degrees, mean / median; the left-out benchmark's single-light photographs")
    for b in rs.datasets:
        tr = np.flatnonzero((ds != b) & good)
        te = np.flatnonzero((ds == b) & good)
        ii, kk = np.nonzero(wv[tr])
        ii = tr[ii]
        models = {"whole-image model": T.fit_model(feats[tr], tuv[tr], ds[tr], cams[tr], ridge, loc, gam=gam[tr]),
                  "window model": T.fit_model(W[ii, kk], tuv[ii], ds[ii], cams[ii], ridge, loc, gam=gam[ii])}
        jj, ll = np.nonzero(wv[te])
        jj = te[jj]
        fw = W[jj, ll]
        for name, m in models.items():
            uvw = m.predict(m.inputs(fw), gam[jj]) + fw[:, L.REFERENCE]
            ew = T.camera_errors(uvw, rs.truth[jj], cams[jj], Ks)
            uvi = m.predict(m.inputs(feats[te]), gam[te]) + feats[te][:, L.REFERENCE]
            ei = T.camera_errors(uvi, rs.truth[te], cams[te], Ks)
            # the windows' unweighted mean per photograph
            sums = np.zeros((len(rs.truth), 2))
            np.add.at(sums, jj, uvw)
            n = np.bincount(jj, minlength=len(rs.truth))
            has = te[n[te] > 0]
            em = T.camera_errors(sums[has] / n[has, None], rs.truth[has], cams[has], Ks)
            print(f"{b:16s} {name:18s} windows {ew.mean():.2f} / {np.median(ew):.2f} ({len(ew)} windows) | "
                  f"whole photographs {ei.mean():.2f} / {np.median(ei):.2f} | windows' mean per photograph "
                  f"{em.mean():.2f} / {np.median(em):.2f}", flush=True)
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
