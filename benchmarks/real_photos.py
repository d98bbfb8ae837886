"""Real photographs with measured lights, leave one camera out: the default
(learnt) estimator against the classical peers, the light posterior and
the literal Maloney-Wandell method, in one run.

For each of the 10 development cameras (NUS 8-camera's nine and Cube+'s
Canon EOS 550D) the learnt estimator is fitted on the other nine
(:func:`benchmarks.train_illuminant.leave_one_camera_out`, the settings of
the shipped model) and tested on the tenth, each camera described only by
its colour matrix (LibRaw's table, as a RAW upload of that model gets). The
peers need no training and run on every image; the light posterior
(``bayes``) and the literal method cost more and run on a fixed subsample
(``--sample`` per camera), where every method is also reported.

Prints per camera and pooled: mean, median, trimean, best 25 %, worst 25 %,
95th percentile and time per image; the learnt estimator's median and worst
25 % as ratios to shades of gray's on the same camera; the coverage of its
reported 90 % region (calibrated on the other cameras); writes
``out/real_photos.json`` and a plot of the error distributions
``out/real_photos_errors.png``.

Usage::

    python -m benchmarks.real_photos [--sample 20] [--out out] [--no-plot]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from recovery import learned as L
from recovery.estimators import gray_edge, gray_world, shades_of_gray, white_patch

from .realdata import REAL_DIR, angular_error, error_stats, load_real, usable_mask
from .train_illuminant import (coverage_by_camera, dataset_features, held_out_confidence, leave_one_camera_out,
                               reliability, single_threaded)

PEERS = {
    "gray-world": lambda im, m: gray_world(im, m),
    "white-patch": lambda im, m: white_patch(im, m),
    "shades-of-gray p=6": lambda im, m: shades_of_gray(im, m, 6.0),
    "gray-edge 1st p=6": lambda im, m: gray_edge(im, m, 6.0, 1.0, 1),
    "gray-edge 2nd p=6": lambda im, m: gray_edge(im, m, 6.0, 1.0, 2),
}
SOG = "shades-of-gray p=6"


def _run_peer(fn, images, masks):
    out = np.zeros((len(images), 3))
    t0 = time.perf_counter()
    for i, (im, m) in enumerate(zip(images, masks)):
        try:
            out[i] = fn(im, m)
        except Exception:          # a peer that cannot run (no edges): gray world, as the product falls back
            out[i] = gray_world(im, m)
    return out, (time.perf_counter() - t0) / max(1, len(images))


def _product(method, rs, idx):
    """The product's own estimate_illuminant (bayes, maloney-wandell, learned) on images ``idx``."""
    from recovery import estimate_illuminant
    from recovery.cameras import camera_from_matrix

    out = np.zeros((len(idx), 3))
    cams = {}
    t0 = time.perf_counter()
    for j, i in enumerate(idx):
        c = rs.camera[i]
        if c not in cams:
            cams[c] = camera_from_matrix(rs.matrices[c])
        out[j] = estimate_illuminant(rs.images[i].astype(float), cams[c], method, white_level=1.0).rgb
    return out, (time.perf_counter() - t0) / max(1, len(idx))


_FIRST_USE = r"""
import json, sys, time
import numpy as np
t0 = time.perf_counter()
from recovery import estimate_illuminant
from recovery.cameras import camera_from_matrix
mats = json.loads(sys.argv[1])
img = np.random.default_rng(0).uniform(0.05, 0.9, (64, 64, 3))
out = {"import_s": time.perf_counter() - t0, "first_s": [], "again_ms": []}
for m in mats:
    cam = camera_from_matrix(np.array(m))
    t = time.perf_counter(); estimate_illuminant(img, cam); out["first_s"].append(time.perf_counter() - t)
    t = time.perf_counter()
    for _ in range(20):
        estimate_illuminant(img, cam)
    out["again_ms"].append((time.perf_counter() - t) / 20 * 1e3)
print(json.dumps(out))
"""


def first_use(matrices) -> dict:
    """In a fresh process (nothing cached): the first estimate with a camera
    never seen (the model file, the candidate lights), the first with each
    further new camera, and the steady cost per 64 x 64 estimate."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", _FIRST_USE, json.dumps([m.tolist() for m in matrices])],
                       capture_output=True, text=True, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


def _fmt(s):
    return " ".join(f"{s[k]:6.2f}" for k in ("mean", "median", "trimean", "best25", "worst25", "p95"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(REAL_DIR))
    ap.add_argument("--sample", type=int, default=20, help="images per camera for bayes and maloney-wandell")
    ap.add_argument("--out", default="out")
    ap.add_argument("--no-plot", action="store_true")
    a = ap.parse_args(argv)
    t_all = time.perf_counter()
    rs = load_real(a.data)
    fu = first_use([rs.matrices[c] for c in rs.cameras[:3]])
    print(f"first estimate in a fresh process with a new camera: {fu['first_s'][0]:.3f} s (imports "
          f"{fu['import_s']:.2f} s before it); a second and third new camera: "
          f"{fu['first_s'][1] * 1e3:.0f} / {fu['first_s'][2] * 1e3:.0f} ms; then "
          f"{np.mean(fu['again_ms']):.1f} ms per 64x64 estimate")
    masks = np.array([usable_mask(im) for im in rs.images])
    n = len(rs.truth)
    errs, times = {}, {}

    t0 = time.perf_counter()
    feats, tuv, Ks = dataset_features(rs)
    with single_threaded():
        uv, spread, err = leave_one_camera_out(rs, feats, tuv, Ks, log=lambda s: None)
    errs["learned (LOCO)"] = err
    times["learned (LOCO)"] = (time.perf_counter() - t0) / n   # features + 10 fits, per image
    # the shipped model's cost per estimate on a thumbnail (features + network), as the product runs it
    model = L.load_model()
    t0 = time.perf_counter()
    for i in range(0, n, 10):
        L.estimate_learned(rs.images[i], masks[i], rs.matrices[rs.camera[i]], model)
    times["learned (LOCO)"] = (time.perf_counter() - t0) / len(range(0, n, 10))
    for name, fn in PEERS.items():
        est, times[name] = _run_peer(fn, rs.images, masks)
        errs[name] = angular_error(est, rs.truth)

    rng = np.random.default_rng(0)
    sub = np.sort(np.concatenate([rng.choice(np.flatnonzero(rs.camera == c), min(a.sample, int(np.sum(rs.camera == c))),
                                             replace=False) for c in rs.cameras]))
    sub_errs = {k: v[sub] for k, v in errs.items()}
    for method in ("bayes", "maloney-wandell"):
        est, times[method] = _product(method, rs, sub)
        sub_errs[method] = angular_error(est, rs.truth[sub])

    cover = coverage_by_camera(rs, uv, tuv, spread)
    d2 = ((uv - tuv) ** 2).sum(axis=1)
    report = {"images": n, "cameras": rs.cameras, "pooled": {}, "per_camera": {}, "subsample": {},
              "coverage90": cover, "time_per_image_s": times, "first_use": fu}
    head = f"{'method':22s} {'mean':>6s} {'median':>6s} {'trim':>6s} {'best25':>6s} {'worst25':>6s} {'p95':>6s} {'ms/img':>7s}"
    print(f"\nAll {n} images, leave one camera out (learned); peers need no training\n{head}")
    for k, e in errs.items():
        s = error_stats(e)
        report["pooled"][k] = s
        print(f"{k:22s} {_fmt(s)} {1e3 * times[k]:7.2f}")
    print(f"\nSubsample ({a.sample} per camera, {len(sub)} images): every method\n{head}")
    for k, e in sub_errs.items():
        s = error_stats(e)
        report["subsample"][k] = s
        print(f"{k:22s} {_fmt(s)} {1e3 * times[k]:7.2f}")
    print("\nPer camera (learned vs shades of gray p=6; ratio targets: median <= 0.7, worst 25 % <= 0.8)")
    print(f"{'camera':24s} {'n':>4s} | learned: mean median trim best25 worst25 p95 | sog: mean median worst25 | "
          f"med-ratio w25-ratio | 90% cover")
    for c in rs.cameras:
        te = rs.camera == c
        s, g = error_stats(errs["learned (LOCO)"][te]), error_stats(errs[SOG][te])
        report["per_camera"][c] = {"learned": s, "shades_of_gray": g,
                                   "median_ratio": s["median"] / g["median"], "worst25_ratio": s["worst25"] / g["worst25"],
                                   "others": {k: error_stats(e[te]) for k, e in errs.items()}}
        print(f"{c:24s} {int(te.sum()):4d} | {_fmt(s)} | {g['mean']:5.2f} {g['median']:5.2f} {g['worst25']:5.2f} | "
              f"{s['median'] / g['median']:5.2f} {s['worst25'] / g['worst25']:5.2f} | {cover[c]:5.0%}")
    inside = float(np.mean(d2 <= L.CHI2_90 * L.variance_from_spread(spread, L.fit_uncertainty(spread, d2))))
    pooled_cover = float(np.mean([cover[c] for c in rs.cameras for _ in range(int(np.sum(rs.camera == c)))]))
    print(f"\n90 % region coverage, each camera calibrated on the others: pooled {pooled_cover:.1%} "
          f"(in-sample calibration {inside:.1%})")
    report["coverage90_pooled"] = pooled_cover
    rel = reliability(held_out_confidence(rs, uv, tuv, spread, err, Ks), err)
    report["confidence_reliability"] = rel
    print("confidence on held-out cameras, predicted / observed P(error < 3 deg) by bin: "
          + ", ".join(f"{b['bin'][0]:.1f}-{b['bin'][1]:.1f} {b['predicted']:.2f}/{b['observed']:.2f} (n {b['n']})"
                      for b in rel))
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "real_photos.json").write_text(json.dumps(report, indent=1))
    if not a.no_plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(1, 2, figsize=(12, 4.5))
        names = list(errs)
        ax[0].boxplot([errs[k] for k in names], whis=(5, 95), showfliers=False)
        ax[0].set_xticks(range(1, len(names) + 1), names, rotation=30, ha="right", fontsize=8)
        ax[0].set_ylabel("angular error (degrees)")
        ax[0].set_title(f"{n} real photographs, 10 cameras (whiskers 5-95 %)")
        for k in names:
            e = np.sort(errs[k])
            ax[1].plot(e, np.arange(1, e.size + 1) / e.size, label=k)
        ax[1].set_xlim(0, 12)
        ax[1].set_xlabel("angular error (degrees)")
        ax[1].set_ylabel("fraction of images")
        ax[1].legend(fontsize=8)
        ax[1].grid(alpha=0.3)
        fig.tight_layout()
        fig.savefig(out / "real_photos_errors.png", dpi=110)
        print(f"wrote {out / 'real_photos.json'} and {out / 'real_photos_errors.png'}")
    print(f"total {time.perf_counter() - t_all:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
