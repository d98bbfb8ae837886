"""The light posterior (``method=bayes``) on real photographs: how often it is
right, and whether its own confidence says so.

Run as::

    python -m benchmarks.posterior_real [--step 1] [--write]

The posterior's confidence, ``sigmoid(a + b log spread)``
(:data:`recovery.bayes.CONFIDENCE_COEF`), was fitted on synthetic scenes of
measured surfaces, where its spread tracks its error. This command runs
:func:`recovery.bayes.estimate_bayes` (the product's defaults; each camera
described by its colour matrix, :func:`recovery.cameras.camera_from_matrix`,
as a RAW upload is) on the development photographs
(``../shared/data/real``: NUS 8-camera, Cube+, INTEL-TAU field) and prints,
per benchmark: the mean / median angular error, the rate of errors under 3
degrees, the mean confidence the posterior claims, and the area under the
ROC curve of its spread for errors above 3 degrees (0.5: the spread says
nothing). With ``--write`` it stores the rate (each benchmark weighing the
same) in ``recovery/data/posterior_real_rate.json``: the confidence the
product reports for the posterior on a scene that is not flat patches
(:func:`recovery.api._run_bayes`), as a classical peer reports its measured
rate (issue 27, item 4: "every estimate carries a confidence"; a confidence
"calibrated against real data").

References
----------
Issue 27, item 4; ``docs/confidence.md``, "The light posterior on real
photographs". Hanley & McNeil (1982), the area under the ROC curve as the
Mann-Whitney statistic.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

__all__ = ["posterior_errors", "summary", "main", "RATE_FILE"]

RATE_FILE = Path(__file__).resolve().parents[1] / "recovery" / "data" / "posterior_real_rate.json"


def posterior_errors(rs, rows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Angular error (degrees), claimed confidence and posterior spread
    (degrees) of :func:`recovery.bayes.estimate_bayes` on the photographs
    ``rows`` of ``rs`` (:class:`benchmarks.realdata.RealSet`)."""
    from recovery.bayes import estimate_bayes
    from recovery.cameras import camera_from_matrix
    from recovery.metrics import angular_error

    from .realdata import usable_mask

    cams = {k: camera_from_matrix(m) for k, m in rs.matrices.items()}
    err, conf, spread = (np.full(len(rows), np.nan) for _ in range(3))
    for n, i in enumerate(rows):
        rgb, _, d = estimate_bayes(rs.images[i], usable_mask(rs.images[i]), cams[rs.camera[i]])
        err[n] = angular_error(rgb, rs.truth[i])
        conf[n] = d.get("confidence", np.nan)
        s = d.get("posterior_spread_deg")
        spread[n] = np.nan if s is None else s
    return err, conf, spread


def _auroc(score: np.ndarray, positive: np.ndarray) -> float:
    """P(score of a positive > score of a negative), ties counting half."""
    from scipy.stats import rankdata

    ok = np.isfinite(score)
    score, positive = score[ok], positive[ok]
    n1, n0 = int(positive.sum()), int((~positive).sum())
    if n1 == 0 or n0 == 0:
        return float("nan")
    r = rankdata(score)
    return float((r[positive].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def summary(err, conf, spread, dataset) -> dict:
    """Per benchmark and pooled: mean / median error, rate of errors under 3
    degrees, mean claimed confidence, AUROC of the spread for errors above 3
    degrees; ``rate``: the benchmarks' rates averaged (each weighing the same)."""
    out = {}
    for b in list(dict.fromkeys(dataset.tolist())) + ["all"]:
        sel = np.ones(len(err), bool) if b == "all" else dataset == b
        e = err[sel]
        out[b] = {"photographs": int(sel.sum()), "mean_deg": float(np.mean(e)), "median_deg": float(np.median(e)),
                  "rate_under_3deg": float(np.mean(e < 3.0)), "claimed_confidence": float(np.nanmean(conf[sel])),
                  "auroc_spread": _auroc(spread[sel], e > 3.0)}
    out["rate"] = float(np.mean([v["rate_under_3deg"] for k, v in out.items() if k != "all"]))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--step", type=int, default=1, help="every STEP-th photograph (default all 7,524)")
    ap.add_argument("--write", action="store_true", help=f"store the rate in {RATE_FILE.relative_to(RATE_FILE.parents[2])}")
    args = ap.parse_args(argv)

    from .realdata import REAL_DIR, load_real

    t0 = time.time()
    rs = load_real(REAL_DIR)
    rows = np.arange(0, len(rs.truth), max(1, args.step))
    err, conf, spread = posterior_errors(rs, rows)
    s = summary(err, conf, spread, rs.dataset[rows])
    print(f"light posterior (recovery.bayes.estimate_bayes, defaults) on {len(rows)} development photographs, "
          f"cameras by their colour matrix; {time.time() - t0:.0f} s\n")
    print("| benchmark | photographs | mean / median error (deg) | errors under 3 deg | confidence claimed | "
          "AUROC of the spread (errors > 3 deg) |")
    print("|---|---|---|---|---|---|")
    for b, v in s.items():
        if b == "rate":
            continue
        print(f"| {b} | {v['photographs']} | {v['mean_deg']:.2f} / {v['median_deg']:.2f} | "
              f"{v['rate_under_3deg']:.3f} | {v['claimed_confidence']:.3f} | {v['auroc_spread']:.3f} |")
    print(f"\nrate, each benchmark weighing the same: {s['rate']:.4f}")
    if args.write:
        RATE_FILE.write_text(json.dumps({
            "rate_under_3deg": round(s["rate"], 4),
            "per_benchmark": {b: round(v["rate_under_3deg"], 4) for b, v in s.items() if b not in ("rate", "all")},
            "photographs": int(len(rows)), "auroc_spread": round(s["all"]["auroc_spread"], 3),
            "claimed_confidence": round(s["all"]["claimed_confidence"], 3),
            "made_by": f"python -m benchmarks.posterior_real --step {max(1, args.step)} --write"}, indent=1) + "\n")
        print(f"written: {RATE_FILE}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
