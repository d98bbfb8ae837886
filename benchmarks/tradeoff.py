"""The speed/accuracy trade, measured (issue 4).

``python -m benchmarks.tradeoff [--scenes 12] [--size 1024] [--seed 0] [--out out]``

For each knob (estimator, analysis resolution, wavelength grid, D(E) and
D(S), region size and overlap, the ``quality`` presets) the same Mondrian
scenes of the development benchmark (``docs/DESIGN.md``; here at
``size`` x ``size`` pixels so that time per megapixel means something) are
analysed and rendered under D65; the table gives median and 95th-percentile
angular error, median end-to-end CIEDE2000 (as in :mod:`benchmarks.synthetic`) and
the time per megapixel of estimate + render. The Pareto front (no other
setting both faster and more accurate) is marked and plotted.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from recovery import METHODS, Camera, angular_error, estimate_illuminant
from testing.scenes import draw_scene

from .synthetic import delta_e00_scene

__all__ = ["configurations", "run_tradeoff", "pareto_front"]


def configurations() -> list[dict]:
    """Every setting measured: ``{"knob", "label", "method", "kwargs"}``."""
    cfg = []
    for m in METHODS:
        cfg.append({"knob": "estimator", "label": m, "method": m, "kwargs": {}})
    for px in (16384, 4096, 1024):
        for m in ("auto", "shades-of-gray"):
            cfg.append({"knob": "resolution", "label": f"{m} @{px}px", "method": m,
                        "kwargs": {"analysis_pixels": px}})
    for step in (5.0, 20.0):
        for m in ("auto", "maloney-wandell"):
            cfg.append({"knob": "grid", "label": f"{m} @{step:g}nm", "method": m,
                        "kwargs": {"wavelength_step": step}})
    for ds, de in ((2, 2), (1, 2), (1, 1)):
        cfg.append({"knob": "D(S),D(E)", "label": f"maloney-wandell D(S)={ds} D(E)={de}",
                    "method": "maloney-wandell", "kwargs": {"surface_dim": ds, "light_dim": de}})
    for size, ov in ((64, 0.5), (128, 0.5), (128, 0.0), (256, 0.5)):
        cfg.append({"knob": "regions", "label": f"maloney-wandell map {size}px ov{ov:g}",
                    "method": "maloney-wandell", "kwargs": {"spatial": True, "region_size": size,
                                                             "overlap": ov}})
    for q in ("fast", "balanced", "accurate"):
        cfg.append({"knob": "quality", "label": f"auto quality={q}", "method": "auto",
                    "kwargs": {"quality": q}})
    return cfg


def pareto_front(times, errors) -> np.ndarray:
    """Boolean mask of the settings no other setting beats in both time
    and error."""
    t = np.asarray(times, float)
    e = np.asarray(errors, float)
    front = np.ones(t.size, bool)
    for i in range(t.size):
        dominated = (t <= t[i]) & (e <= e[i]) & ((t < t[i]) | (e < e[i]))
        front[i] = not dominated.any()
    return front


def run_tradeoff(scenes: int = 12, size: int = 1024, seed: int = 0, configs=None, progress=None) -> list[dict]:
    """Measure every configuration on the same scenes; returns one row per
    configuration."""
    configs = configs or configurations()
    ks = (4, 8, 16, 32)
    scene_list = [draw_scene(seed, ks[i % 4], i, size) for i in range(scenes)]
    cams = {s.camera_name: Camera.named(s.camera_name) for s in scene_list}
    from recovery import render

    # warm caches (bases, colour-science data) outside the timings
    for c in configs:
        estimate_illuminant(scene_list[0].image[:32, :32], cams[scene_list[0].camera_name], c["method"],
                            white_level=1.0, **c["kwargs"])
    rows = []
    for j, c in enumerate(configs):
        angles, des, secs, est_secs = [], [], [], []
        for s in scene_list:
            cam = cams[s.camera_name]
            t0 = time.perf_counter()
            est = estimate_illuminant(s.image, cam, c["method"], white_level=1.0, **c["kwargs"])
            t1 = time.perf_counter()
            out = render(s.image, cam, est, target="D65", output="XYZ")
            secs.append(time.perf_counter() - t0)
            est_secs.append(t1 - t0)
            del out
            angles.append(float(angular_error(est.rgb, s.rgb_true)))
            de, _ = delta_e00_scene(s, cam, est)
            des.append(float(np.median(de)))
        mp = size * size / 1e6
        rows.append({**{k: c[k] for k in ("knob", "label", "method")}, "kwargs": c["kwargs"],
                     "median_angle": float(np.median(angles)), "p95_angle": float(np.percentile(angles, 95)),
                     "median_de00": float(np.median(des)), "s_per_mp": float(np.median(secs)) / mp,
                     "estimate_s_per_mp": float(np.median(est_secs)) / mp})
        if progress:
            progress(j + 1, len(configs))
    front = pareto_front([r["s_per_mp"] for r in rows], [r["median_de00"] for r in rows])
    for r, f in zip(rows, front):
        r["pareto"] = bool(f)
    return rows


def format_table(rows) -> str:
    lines = [f"{'knob':11s} {'setting':40s} {'med deg':>8s} {'p95 deg':>8s} {'med dE00':>9s} "
             f"{'s/MP':>8s} {'est s/MP':>9s} pareto"]
    for r in rows:
        lines.append(f"{r['knob']:11s} {r['label']:40s} {r['median_angle']:8.2f} {r['p95_angle']:8.2f} "
                     f"{r['median_de00']:9.2f} {r['s_per_mp']:8.3f} {r['estimate_s_per_mp']:9.3f} "
                     f"{'*' if r['pareto'] else ''}")
    return "\n".join(lines)


def plot(rows, path: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 5.5))
    knobs = sorted({r["knob"] for r in rows})
    colors = dict(zip(knobs, plt.cm.tab10.colors))
    for ax, key, name in ((axes[0], "median_de00", "median CIEDE2000 under D65"),
                          (axes[1], "median_angle", "median angular error (deg)")):
        t = np.array([r["s_per_mp"] for r in rows])
        e = np.array([r[key] for r in rows])
        for r, ti, ei in zip(rows, t, e):
            ax.scatter(ti, ei, color=colors[r["knob"]], s=28, edgecolor="k" if r["pareto"] else "none")
        front = pareto_front(t, e)
        order = np.argsort(t[front])
        ax.plot(t[front][order], e[front][order], "k--", lw=1, label="Pareto front")
        for r, ti, ei, f in zip(rows, t, e, front):
            if f:
                ax.annotate(r["label"], (ti, ei), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel("seconds per megapixel (estimate + render)")
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    handles = [plt.Line2D([], [], marker="o", ls="", color=colors[k], label=k) for k in knobs]
    axes[0].legend(handles=handles + [plt.Line2D([], [], ls="--", color="k", label="Pareto front")], fontsize=8)
    fig.suptitle("Speed/accuracy trade on the development Mondrians")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Speed/accuracy trade-off table and Pareto plot")
    ap.add_argument("--scenes", type=int, default=12)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="out")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    rows = run_tradeoff(args.scenes, args.size, args.seed,
                        progress=lambda i, n: print(f"\r{i}/{n} settings", end="", flush=True))
    print()
    print(format_table(rows))
    os.makedirs(args.out, exist_ok=True)
    plot(rows, os.path.join(args.out, "tradeoff_pareto.png"))
    with open(os.path.join(args.out, "tradeoff.json"), "w") as f:
        json.dump(rows, f, indent=1)
    print(f"\nwrote {args.out}/tradeoff_pareto.png and tradeoff.json ({time.perf_counter() - t0:.0f} s; "
          f"{args.scenes} scenes of {args.size}x{args.size})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
