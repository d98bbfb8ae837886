"""Real photographs with measured lights: the default (learnt) estimator
against the classical peers, leave one *benchmark* out (the headline) and
leave one camera out beside it, in one run.

Headline, leave-one-benchmark-out: for each of the three development
benchmarks (NUS 8-camera, Cube+, INTEL-TAU field) the whole training
procedure of :mod:`benchmarks.train_illuminant` (its settings chosen by an
inner leave-one-benchmark-out among the two training benchmarks, its
uncertainty calibrated on that inner loop's out-of-fold predictions) runs on
the other two, and the model predicts the left-out benchmark, each camera
described only by its colour matrix (LibRaw's table, as a RAW upload of that
model gets). Nothing about the left-out benchmark is used for any choice.

Beside it, leave-one-camera-out: each of the 12 cameras predicted by a model
fitted on the other 11 (with the ridge that the outer loop chose without
that camera's benchmark). NUS 8-camera's cameras photographed largely the
same scenes, so this protocol flatters a learnt method.

The peers (gray world, white patch, shades of gray p = 6, gray edge of 1st
and 2nd order) need no training and run on every image in the same run;
the light posterior (``bayes``) on a fixed subsample (``--sample`` per
camera, default 0: it costs ~0.1 s an image).

Prints per left-out benchmark, per camera and pooled: mean, median,
trimean, best 25 %, worst 25 %, 95th percentile, ms per image; the ratios
to shades of gray the issue's targets are stated in; the coverage of the
reported 90 % region on each left-out benchmark; the confidence's
reliability; the cost of an estimate warm and in a fresh process. Writes
``out/real_photos.json``.

Usage::

    python -m benchmarks.real_photos [--quick] [--sample 0] [--out out] [--no-loco] [--histogram-stage]

``--histogram-stage`` measures the learnt model with its second, histogram
stage (:mod:`recovery.chroma_histogram`, its settings chosen by inner
leave-one-benchmark-out, fused with the first stage): not the shipped
model, which leaves the stage out (the figures and why: the docstring of
:mod:`benchmarks.train_illuminant`).
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
from .train_illuminant import (dataset_features, dataset_histograms, dataset_regions, leave_one_benchmark_out,
                               leave_one_camera_out, reliability, single_threaded)

PEERS = {
    "gray-world": lambda im, m: gray_world(im, m),
    "white-patch": lambda im, m: white_patch(im, m),
    "shades-of-gray p=6": lambda im, m: shades_of_gray(im, m, 6.0),
    "gray-edge 1st p=6": lambda im, m: gray_edge(im, m, 6.0, 1.0, 1),
    "gray-edge 2nd p=6": lambda im, m: gray_edge(im, m, 6.0, 1.0, 2),
}
SOG = "shades-of-gray p=6"
LEARNED = "learned (LODO)"
FIRST = "  first stage alone"

#: the issue's targets, leave-one-benchmark-out
TARGET_MEAN_RATIO, TARGET_MEDIAN_RATIO, TARGET_POOLED_MEAN, TARGET_POOLED_MEDIAN = 0.8, 0.85, 2.3, 1.7


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
    """The product's own estimate_illuminant on images ``idx``."""
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
    further new camera, and the steady cost per 64 x 64 estimate (through
    ``estimate_illuminant``, the product's whole path)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-c", _FIRST_USE, json.dumps([m.tolist() for m in matrices])],
                       capture_output=True, text=True, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])


#: the issue's targets for the flag, per left-out benchmark
FAIL_DEG, TARGET_AUROC, TARGET_CATCH, TARGET_FLAG = 6.0, 0.8, 0.6, 0.2


def flag_report(rs, err, conf, conf_today, thresholds) -> dict:
    """Per left-out benchmark: the area under the ROC curve of (1 -
    confidence) for errors above 6 degrees, and the share of those failures
    the flag catches and of all photographs it flags, for today's
    confidence (the 90 % radius's law, flag below 0.5; a fallback carried
    none) beside the new one (:mod:`recovery.confidence`, flag below the
    threshold its inner cross-validation chose). Printed and returned."""
    from recovery.confidence import auroc

    print(f"\n=== Flags on left-out benchmarks: failures = error above {FAIL_DEG:g} degrees "
          f"(targets: AUROC >= {TARGET_AUROC}, catch >= {TARGET_CATCH:.0%}, flag <= {TARGET_FLAG:.0%}) ===")
    print(f"{'benchmark':16s} {'fail':>5s} | today: {'AUROC':>5s} {'catch':>6s} {'flag':>6s} | new: {'AUROC':>5s} "
          f"{'catch':>6s} {'flag':>6s} {'thresh':>6s}")
    out = {}
    for b in rs.datasets:
        m = rs.dataset == b
        fail = err[m] > FAIL_DEG
        ct = np.nan_to_num(conf_today[m], nan=1.0)
        low_t = ct < 0.5
        low_n = conf[m] < thresholds[b]
        r = {"failures": float(fail.mean()), "n": int(m.sum()),
             "today": {"auroc": auroc(1 - ct, fail), "catch": float(low_t[fail].mean()), "flag": float(low_t.mean())},
             "new": {"auroc": auroc(1 - conf[m], fail), "catch": float(low_n[fail].mean()), "flag": float(low_n.mean()),
                     "threshold": thresholds[b]}}
        r["met"] = bool(r["new"]["auroc"] >= TARGET_AUROC and r["new"]["catch"] >= TARGET_CATCH
                        and r["new"]["flag"] <= TARGET_FLAG)
        out[b] = r
        t, w = r["today"], r["new"]
        print(f"{b:16s} {fail.mean():5.1%} | today: {t['auroc']:5.2f} {t['catch']:6.1%} {t['flag']:6.1%} | new: "
              f"{w['auroc']:5.2f} {w['catch']:6.1%} {w['flag']:6.1%} {w['threshold']:6.3f}"
              f"  {'met' if r['met'] else 'MISSED'}")
    return out


def _fmt(s):
    return " ".join(f"{s[k]:6.2f}" for k in ("mean", "median", "trimean", "best25", "worst25", "p95"))


HEAD = f"{'':26s} {'mean':>6s} {'median':>6s} {'trim':>6s} {'best25':>6s} {'worst25':>6s} {'p95':>6s} {'ms/img':>7s}"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(REAL_DIR))
    ap.add_argument("--quick", action="store_true", help="every third image only (development; not the figures)")
    ap.add_argument("--sample", type=int, default=0, help="images per camera for bayes (default 0: not run)")
    ap.add_argument("--no-loco", action="store_true", help="skip leave-one-camera-out")
    ap.add_argument("--histogram-stage", action="store_true",
                    help="the learnt model with the histogram stage (recovery.chroma_histogram), not shipped: "
                         "about 25 minutes instead of 3")
    ap.add_argument("--out", default="out")
    a = ap.parse_args(argv)
    t_all = time.perf_counter()
    rs = load_real(a.data)
    if a.quick:
        rs = rs.subset(np.arange(0, len(rs.truth), 3))
    n = len(rs.truth)
    fu = first_use([rs.matrices[c] for c in rs.cameras[:3]])
    print(f"first estimate in a fresh process with a new camera: {fu['first_s'][0]:.3f} s (imports "
          f"{fu['import_s']:.2f} s before it); a second and third new camera: "
          f"{fu['first_s'][1] * 1e3:.0f} / {fu['first_s'][2] * 1e3:.0f} ms; then "
          f"{np.mean(fu['again_ms']):.1f} ms per 64x64 estimate (estimate_illuminant, warm)")
    masks = np.array([usable_mask(im) for im in rs.images])
    errs, times = {}, {}
    for name, fn in PEERS.items():
        est, times[name] = _run_peer(fn, rs.images, masks)
        errs[name] = angular_error(est, rs.truth)

    t0 = time.perf_counter()
    feats, tuv, Ks, gam = dataset_features(rs)
    hist = dataset_histograms(rs) if a.histogram_stage else None
    t_feat = (time.perf_counter() - t0) / n
    t0 = time.perf_counter()
    regions = dataset_regions(rs)
    t_reg = (time.perf_counter() - t0) / n
    with single_threaded():
        lodo = leave_one_benchmark_out(rs, feats, tuv, Ks, sog=errs[SOG], gam=gam, hist=hist, regions=regions)
    err = np.zeros(n)
    inside = {}
    conf = np.zeros(n)            # an image too poor for the learnt estimator: a fallback, confidence 0 (flagged)
    conf_today = np.full(n, np.nan)      # today's: the fallback carried none (never flagged)
    thresholds = {}
    for b, (model, res, te) in lodo.items():
        err[te] = res["err"]
        inside[b] = float(res["inside90"].mean())
        conf[te[res["usable"]]] = res["confidence"]
        conf_today[te[res["usable"]]] = res["radius_confidence"]
        thresholds[b] = model.flag.threshold
    errs[LEARNED] = err
    if hist is not None:
        errs[FIRST] = np.zeros(n)
        for b, (_, res, te) in lodo.items():
            errs[FIRST][te] = res["err_first_stage"]
    # cost of the learnt estimate itself (features + model), on a thumbnail
    model = next(iter(lodo.values()))[0]
    t0 = time.perf_counter()
    sub_t = range(0, n, max(1, n // 300))
    for i in sub_t:
        try:
            L.estimate_learned(rs.images[i], masks[i], rs.matrices[rs.camera[i]], model)
        except L.InsufficientSurfaceVariation:
            pass
    times[LEARNED] = (time.perf_counter() - t0) / len(sub_t)
    if FIRST in errs:
        times[FIRST] = times[LEARNED]
    print(f"  (features {1e3 * t_feat:.1f} ms per image; the confidence's quadrant features {1e3 * t_reg:.1f} ms)")

    if not a.no_loco:
        with single_threaded():
            errs["learned (LOCO)"] = leave_one_camera_out(
                rs, feats, tuv, Ks, {b: m.info["selection"]["chosen_ridge"] for b, (m, _, _) in lodo.items()},
                sog=errs[SOG], gam=gam, hist=hist,
                start_by_benchmark={b: m for b, (m, _, _) in lodo.items()} if hist is not None else None,
                log=lambda s: None)
        times["learned (LOCO)"] = times[LEARNED]

    report = {"images": n, "quick": a.quick, "benchmarks": rs.datasets, "cameras": rs.cameras,
              "leave_one_benchmark_out": {}, "per_camera": {}, "pooled": {}, "coverage90": inside,
              "time_per_image_s": times, "first_use": fu}
    order = [LEARNED, *([FIRST] if FIRST in errs else []), *(["learned (LOCO)"] if "learned (LOCO)" in errs else []),
             *PEERS]
    print(f"\n=== Leave one benchmark out (fit on the other two; the learnt row) - the headline ===")
    targets = {}
    for b in rs.datasets:
        m = rs.dataset == b
        print(f"\n{b} ({int(m.sum())} images, {len(set(rs.camera[m]))} cameras; left out of training)\n{HEAD}")
        report["leave_one_benchmark_out"][b] = {}
        for k in order:
            s = error_stats(errs[k][m])
            report["leave_one_benchmark_out"][b][k] = s
            print(f"{k:26s} {_fmt(s)} {1e3 * times[k]:7.2f}")
        s, g = error_stats(err[m]), error_stats(errs[SOG][m])
        rm, rd = s["mean"] / g["mean"], s["median"] / g["median"]
        targets[b] = (rm <= TARGET_MEAN_RATIO, rd <= TARGET_MEDIAN_RATIO)
        print(f"  learnt / shades of gray: mean {rm:.2f} (target <= {TARGET_MEAN_RATIO}), median {rd:.2f} "
              f"(target <= {TARGET_MEDIAN_RATIO}); 90 % region holds the light for {inside[b]:.1%} "
              f"(target 85-95 %)")
    print(f"\nPooled over the three benchmarks ({n} images)\n{HEAD}")
    for k in order:
        s = error_stats(errs[k])
        report["pooled"][k] = s
        print(f"{k:26s} {_fmt(s)} {1e3 * times[k]:7.2f}")
    ps = error_stats(err)
    print(f"  pooled learnt (LODO): mean {ps['mean']:.2f} (target <= {TARGET_POOLED_MEAN}), median "
          f"{ps['median']:.2f} (target <= {TARGET_POOLED_MEDIAN})")

    print("\nPer camera, leave one benchmark out (learnt vs shades of gray p=6; target: worst 25 % not above sog's)")
    print(f"{'camera':24s} {'n':>4s} | learnt: mean median trim best25 worst25 p95 | sog: mean median worst25 | "
          f"w25-ratio" + (" | LOCO mean median worst25" if "learned (LOCO)" in errs else ""))
    w25_ok = {}
    for c in rs.cameras:
        te = rs.camera == c
        s, g = error_stats(err[te]), error_stats(errs[SOG][te])
        w25_ok[c] = s["worst25"] <= g["worst25"]
        report["per_camera"][c] = {"benchmark": str(rs.dataset[te][0]), "learned_lodo": s, "shades_of_gray": g,
                                   "worst25_ratio": s["worst25"] / g["worst25"],
                                   "others": {k: error_stats(e[te]) for k, e in errs.items()}}
        line = (f"{c:24s} {int(te.sum()):4d} | {_fmt(s)} | {g['mean']:5.2f} {g['median']:5.2f} {g['worst25']:5.2f} | "
                f"{s['worst25'] / g['worst25']:5.2f}")
        if "learned (LOCO)" in errs:
            lc = error_stats(errs["learned (LOCO)"][te])
            line += f" | {lc['mean']:5.2f} {lc['median']:5.2f} {lc['worst25']:5.2f}"
        print(line)

    report["flags"] = flag_report(rs, err, conf, conf_today, thresholds)

    rel = reliability(conf[err > -1], err)
    report["confidence_reliability_lodo"] = rel
    print("\nconfidence on left-out benchmarks, predicted / observed P(error < 3 deg) by bin: "
          + ", ".join(f"{b['bin'][0]:.1f}-{b['bin'][1]:.1f} {b['predicted']:.2f}/{b['observed']:.2f} (n {b['n']})"
                      for b in rel))

    if a.sample:
        rng = np.random.default_rng(0)
        sub = np.sort(np.concatenate([rng.choice(np.flatnonzero(rs.camera == c),
                                                 min(a.sample, int(np.sum(rs.camera == c))), replace=False)
                                      for c in rs.cameras]))
        est, t_b = _product("bayes", rs, sub)
        eb = angular_error(est, rs.truth[sub])
        print(f"\nSubsample ({a.sample} per camera, {len(sub)} images)\n{HEAD}")
        for k, e in ((LEARNED, err[sub]), (SOG, errs[SOG][sub]), ("bayes", eb)):
            print(f"{k:26s} {_fmt(error_stats(e))} {1e3 * (t_b if k == 'bayes' else times[k]):7.2f}")

    print("\nTargets (leave one benchmark out): "
          + "; ".join(f"{b}: mean {'met' if t[0] else 'MISSED'}, median {'met' if t[1] else 'MISSED'}"
                      for b, t in targets.items())
          + f"; pooled mean {'met' if ps['mean'] <= TARGET_POOLED_MEAN else 'MISSED'}, pooled median "
            f"{'met' if ps['median'] <= TARGET_POOLED_MEDIAN else 'MISSED'}; worst 25 % not above sog on "
            f"{sum(w25_ok.values())} of {len(w25_ok)} cameras"
          + f"; coverage 85-95 % on {sum(0.85 <= v <= 0.95 for v in inside.values())} of {len(inside)} benchmarks"
          + "; flags (AUROC >= 0.8, catch >= 60 %, flag <= 20 %): " + ", ".join(
              f"{b} {'met' if f['met'] else 'MISSED'}" for b, f in report["flags"].items())
          + f"; warm {np.mean(fu['again_ms']):.1f} ms (target <= 20), first {fu['first_s'][0]:.2f} s (target <= 0.5)")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "real_photos.json").write_text(json.dumps(report, indent=1))
    print(f"wrote {out / 'real_photos.json'}; total {time.perf_counter() - t_all:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
