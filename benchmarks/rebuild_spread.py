"""How far the rebuilt learnt model moves between OpenBLAS kernels.

Machines of this kind may set ``OPENBLAS_CORETYPE`` (older OpenBLAS builds
compute wrong results on some processors), and the kernel each setting
selects orders floating-point sums differently. The training (a convex
robust ridge iterated to a tolerance, :func:`recovery.learned.fit_robust_ridge`)
should not carry those last-bit differences into the model. This command
rebuilds the shipped model (``train_illuminant --final-only``) once per
kernel, each in its own process (the kernel is chosen when OpenBLAS loads),
and prints the largest angle between the estimates of any two rebuilds (and
the shipped model) on a fixed sample of the development photographs, the
largest change of the 90 % radius, and whether the inner cross-validation
chose the same settings. The rebuild test's tolerance
(``tests/test_learned.py``) is set from these figures.

Usage::

    python -m benchmarks.rebuild_spread [--data DIR] [--kernels Haswell SkylakeX Prescott] [--every 359]
"""

from __future__ import annotations

import argparse
import itertools
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from .realdata import REAL_DIR


def estimates(model_path, rs, idx):
    from recovery import learned as L

    from .realdata import usable_mask

    m = L.load_model(model_path)
    out = [L.estimate_learned(rs.images[i], usable_mask(rs.images[i]), rs.matrices[rs.camera[i]], m) for i in idx]
    return m, np.array([r.rgb for r in out]), np.array([r.radius90_deg for r in out])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(REAL_DIR))
    ap.add_argument("--kernels", nargs="+", default=["Haswell", "SkylakeX", "Prescott"])
    ap.add_argument("--every", type=int, default=25, help="sample every k-th development image")
    ap.add_argument("--jobs", type=int, default=2, help="rebuilds run at once")
    a = ap.parse_args(argv)
    from recovery.metrics import angular_error

    from .realdata import load_real

    tmp = Path(tempfile.mkdtemp(prefix="rebuild-spread-"))
    root = Path(__file__).resolve().parents[1]
    paths, failed = {}, []
    for start in range(0, len(a.kernels), a.jobs):          # at most ``jobs`` rebuilds at once
        running = []
        for k in a.kernels[start:start + a.jobs]:
            env = dict(os.environ, OPENBLAS_CORETYPE=k, PYTHONPATH=str(root))
            paths[k] = tmp / f"{k}.npz"
            with open(tmp / f"{k}.log", "w") as log:
                running.append((k, subprocess.Popen(
                    [sys.executable, "-m", "benchmarks.train_illuminant", "--final-only", "--data", a.data, "--out",
                     str(paths[k])],
                    env=env, stdout=log, stderr=subprocess.STDOUT, cwd=root)))
        failed += [k for k, p in running if p.wait() != 0]
    if failed:
        print(f"rebuild failed with OPENBLAS_CORETYPE={', '.join(failed)}: see the logs in {tmp}")
        return 1
    rs = load_real(a.data)
    from benchmarks.train_illuminant import dataset_features, usable

    idx = [i for i in range(0, len(rs.truth), a.every)]
    feats, _, _, _ = dataset_features(rs.subset(np.array(idx)))
    idx = [i for i, ok in zip(idx, usable(feats)) if ok]          # images the learnt estimator can run on
    res = {k: estimates(str(v), rs, idx) for k, v in paths.items()}
    res["shipped"] = estimates(None, rs, idx)
    worst_est = worst_rad = 0.0
    same = True
    for x, y in itertools.combinations(res, 2):
        (mx, ex, rx), (my, ey, ry) = res[x], res[y]
        d = max(angular_error(p, q) for p, q in zip(ex, ey))
        dr = float(np.abs(rx - ry).max())
        same &= mx.info["selection"] == my.info["selection"]
        worst_est, worst_rad = max(worst_est, d), max(worst_rad, dr)
        print(f"{x:>9s} vs {y:<9s} largest estimate angle {d:.2e} deg, largest 90 % radius change {dr:.2e} deg")
    print(f"spread over {len(idx)} images: estimates {worst_est:.2e} deg, 90 % radius {worst_rad:.2e} deg; "
          f"inner cross-validation chose {'the same' if same else 'DIFFERENT'} settings")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
