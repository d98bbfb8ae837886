"""One light or a light map: how often the automatic choice is right.

Run as::

    python -m benchmarks.spatial [--scenes 25] [--size 64] [--seed 0] [--ks 4,8,16,32] [--jobs 2]

Uniformly lit scenes are the development benchmark's Mondrians
(``docs/DESIGN.md``; :func:`testing.scenes.draw_scene`, the same scenes).
Two-light scenes are the same Mondrians (same surfaces, shading, noise,
cameras, light list) lit by two of colour-science's illuminants whose camera
responses are more than ``--min-separation`` degrees apart (3 by default),
in one of two layouts:

* ``halves``: light A on one side of a straight vertical or horizontal
  boundary at a random position (35-65 % of the side), light B on the other;
* ``gradient``: the light changes smoothly, ``E(x) = (1 - a(x)) E_A + a(x)
  E_B`` with ``a`` a linear ramp from 0 to 1 across the image (horizontal,
  vertical or diagonal), as a window on one side and lamps on the other.

Printed: the fraction of uniform scenes given one light, the fraction of
two-light scenes given a map (per K, layout and separation), and the
angular error at the map's region centres with the map against with one
light (median and 95th percentile over all centres of all scenes, against
the true light at each centre).

References
----------
Wandell (1985) [docs/references.md#seed-002], Fig. 1 and 'A condition on spatial
variation' (a light that varies slowly across the image, estimated in
regions). ``docs/DESIGN.md``, "The development benchmark".
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from recovery import angular_error, estimate_illuminant
from testing.scenes import LAYOUTS, draw_scene, draw_two_light_scene, named_camera

__all__ = ["evaluate", "run", "main"]

def _points(size: int, n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Evaluation points: the centres of an ``n`` x ``n`` grid of regions."""
    c = (np.arange(n) + 0.5) * size / n - 0.5
    r, cc = np.meshgrid(c, c, indexing="ij")
    return r.ravel(), cc.ravel()


def _errors_at(est, camera, truth, rows, cols, use_map: bool) -> np.ndarray:
    ri, ci = np.round(rows).astype(int), np.round(cols).astype(int)
    t = truth[ri, ci]
    if use_map and est.light_map is not None:
        rgb = camera.response(est.light_map.spectra_at(rows, cols))
    else:
        rgb = np.broadcast_to(est.rgb, t.shape)
    return angular_error(rgb, t)


def evaluate(task) -> dict:
    """One scene: the automatic choice, and the angular errors at the
    evaluation points with one light, with the choice, and (two-light
    scenes) with a map pinned by ``spatial=True``."""
    kind, seed, k, index, size, min_sep = task
    if kind == "uniform":
        sc = draw_scene(seed, k, index, size)
        img, cam_name, sep = sc.image, sc.camera_name, 0.0
        truth = np.broadcast_to(sc.rgb_true, img.shape)
        lights = (sc.illuminant_name,)
    else:
        img, truth, sep, cam_name, la, lb = draw_two_light_scene(seed, k, index, kind, size, min_sep)
        lights = (la, lb)
    cam = named_camera(cam_name)
    t0 = time.perf_counter()
    est = estimate_illuminant(img, cam, "auto", white_level=1.0, spatial="auto")
    ms = (time.perf_counter() - t0) * 1e3
    rows, cols = _points(size)
    chose_map = est.light_map is not None
    rec = {"kind": kind, "K": k, "index": index, "camera": cam_name, "lights": lights, "separation_deg": sep,
           "map": chose_map, "ms": ms, "reason": est.diagnostics.get("spatial_reason"),
           "trend": bool(est.diagnostics["spatial_test"]["trend_says_map"]),
           "regions": bool(est.diagnostics["spatial_test"]["regions_say_map"]),
           "err_one": _errors_at(est, cam, truth, rows, cols, False).tolist(),
           "err_auto": _errors_at(est, cam, truth, rows, cols, True).tolist()}
    if kind != "uniform":
        forced = est if chose_map else estimate_illuminant(img, cam, "auto", white_level=1.0, spatial=True)
        rec["err_map"] = _errors_at(forced, cam, truth, rows, cols, True).tolist()
    return rec


def run(scenes: int = 25, size: int = 64, seed: int = 0, ks=(4, 8, 16, 32), jobs: int = 1,
        min_separation: float = 3.0) -> list[dict]:
    """Every scene of every kind (uniform, then each layout), per K."""
    tasks = [(kind, seed, k, i, size, min_separation) for kind in ("uniform",) + LAYOUTS for k in ks
             for i in range(scenes)]
    if jobs > 1:
        import multiprocessing as mp

        with mp.get_context("fork" if "fork" in mp.get_all_start_methods() else None).Pool(jobs) as pool:
            return list(pool.imap(evaluate, tasks, chunksize=4))
    return [evaluate(t) for t in tasks]


def _pct(x) -> str:
    return f"{100 * np.mean(x):5.1f}%" if len(x) else "    -"


def format_report(recs: list[dict], ks) -> str:
    """The rates and the region-centre errors as plain-text tables."""
    lines = ["Choice between one light and a light map (spatial='auto', method='auto')", ""]
    lines.append(f"{'scenes':<30}" + "".join(f"{'K=' + str(k):>8}" for k in ks) + f"{'all':>8}")
    uni = [r for r in recs if r["kind"] == "uniform"]
    lines.append(f"{'uniform: one light':<30}" + "".join(f"{_pct([not r['map'] for r in uni if r['K'] == k]):>8}"
                                                         for k in ks) + f"{_pct([not r['map'] for r in uni]):>8}")
    for lay in LAYOUTS:
        two = [r for r in recs if r["kind"] == lay]
        lines.append(f"{'two lights, ' + lay + ': map':<30}"
                     + "".join(f"{_pct([r['map'] for r in two if r['K'] == k]):>8}" for k in ks)
                     + f"{_pct([r['map'] for r in two]):>8}")
    two = [r for r in recs if r["kind"] != "uniform"]
    lines.append(f"{'two lights, both: map':<30}" + "".join(f"{_pct([r['map'] for r in two if r['K'] == k]):>8}"
                                                            for k in ks) + f"{_pct([r['map'] for r in two]):>8}")
    lines.append("")
    lines.append("two-light scenes: map chosen, by separation of the two lights (camera RGB angle)")
    bins = [(3, 6), (6, 10), (10, 20), (20, 180)]
    for lay in LAYOUTS + ("both",):
        rr = [r for r in two if lay == "both" or r["kind"] == lay]
        cells = []
        for lo, hi in bins:
            sel = [r["map"] for r in rr if lo < r["separation_deg"] <= hi]
            cells.append(f"{lo}-{hi} deg: {_pct(sel)} (n={len(sel)})")
        lines.append(f"  {lay:<9} " + "   ".join(cells))
    fa_t = sum(r["trend"] for r in uni)
    fa_r = sum(r["regions"] for r in uni)
    lines.append(f"uniform scenes given a map: {fa_t} by the trend test, {fa_r} by the regions' Bayes factor "
                 f"(of {len(uni)})")
    det_t = sum(r["trend"] for r in two)
    det_r = sum(r["regions"] for r in two)
    lines.append(f"two-light scenes given a map: {det_t} by the trend test, {det_r} by the regions' Bayes "
                 f"factor (of {len(two)})")
    lines.append("")
    lines.append("angular error (deg) at the centres of a 4x4 grid of regions against the true light there:")
    lines.append(f"{'scenes':<22}{'light used':<28}{'median':>8}{'mean':>8}{'p95':>8}")

    def row(name, what, errs):
        e = np.concatenate([np.asarray(x, float) for x in errs]) if errs else np.array([np.nan])
        lines.append(f"{name:<22}{what:<28}{np.median(e):8.2f}{np.mean(e):8.2f}{np.percentile(e, 95):8.2f}")

    row("uniform", "one light", [r["err_one"] for r in uni])
    row("uniform", "automatic choice", [r["err_auto"] for r in uni])
    for lay in LAYOUTS + ("both",):
        rr = [r for r in two if lay == "both" or r["kind"] == lay]
        row(f"two lights, {lay}", "one light", [r["err_one"] for r in rr])
        row(f"two lights, {lay}", "automatic choice", [r["err_auto"] for r in rr])
        row(f"two lights, {lay}", "map (spatial=True)", [r["err_map"] for r in rr])
    ms = np.array([r["ms"] for r in recs])
    lines.append("")
    lines.append(f"time per estimate with spatial='auto' (estimate + decision): median {np.median(ms):.0f} ms, "
                 f"mean {ms.mean():.0f} ms")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.spatial",
                                 description="How often spatial='auto' picks one light / a light map.")
    ap.add_argument("--scenes", type=int, default=25, help="scenes per K and per kind (default 25)")
    ap.add_argument("--size", type=int, default=64, help="image side in pixels (default 64, as the bench)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ks", default="4,8,16,32", help="numbers of surfaces (default 4,8,16,32)")
    ap.add_argument("--min-separation", type=float, default=3.0,
                    help="two-light scenes: the lights' camera responses differ by more than this (deg)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    a = ap.parse_args(argv)
    try:
        ks = tuple(int(x) for x in a.ks.split(",") if x.strip())
    except ValueError:
        ap.error("--ks must be comma-separated integers")
    if not ks or a.scenes < 1 or a.size < 16:
        ap.error("need --scenes >= 1, --size >= 16 and some K")
    t0 = time.perf_counter()
    recs = run(a.scenes, a.size, a.seed, ks, max(1, a.jobs), a.min_separation)
    print(format_report(recs, ks))
    print(f"\n{len(recs)} scenes in {time.perf_counter() - t0:.1f} s ({a.jobs} job(s))")
    return 0


if __name__ == "__main__":
    sys.exit(main())
