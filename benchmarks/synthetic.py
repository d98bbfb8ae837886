"""The development benchmark: synthetic Mondrians, every estimator, one run.

Run as::

    python -m benchmarks.synthetic [--scenes N] [--size 64] [--seed 0] [--ks 4,8,16,32] [--out DIR] [--jobs 1]

Implements ``docs/DESIGN.md``, section "The development benchmark".
Mondrian scenes of K surfaces (colour-science's reflectances, each a
rectangle with a random shading factor in [0.5, 1]) under one of
colour-science's illuminants, seen by one of the three shipped cameras, are
synthesised spectrally on a 5 nm grid (400-700 nm), scaled so the maximum is
0.9, given 1 % multiplicative and 0.0005 additive Gaussian noise and clipped
to [0, 1]. The estimators then work on the project's default 10 nm grid, so
the camera model and the world do not match exactly (as with real data).

Metrics, per method and per K:

* angle between the estimated and the true camera RGB of the light
  (:func:`recovery.angular_error`): mean, median, trimean (Tukey,
  ``(Q1 + 2 Q2 + Q3) / 4``), 95th percentile, mean of the worst 25 %;
* end-to-end CIEDE2000: :func:`recovery.render` to XYZ under D65, averaged
  over each surface's (eroded) rectangle, against the true XYZ of that
  surface under D65 (CIE 1931 2°, white Y = 1, times its shading), after
  one least-squares exposure scale on Y per scene; median and mean over all
  surfaces of all scenes;
* time per estimate (ms) and, for the subspace methods, how often they fell
  back to a peer.

A ``true-light`` row renders with the true illuminant spectrum (on the 10 nm
grid): its ΔE00 is the floor the surface model and the camera allow, and its
angle is the error of the 10 nm camera model against the 5 nm world.

References
----------
``docs/DESIGN.md``, "The development benchmark".
Wandell (1985) [docs/references.md#seed-002], eq. 29-36 (the literal
Maloney-Wandell method, ``maloney-wandell``) and eq. 22-25 with Fig. 6
(rendering for an observer from camera data).
Buchsbaum (1980) gray world; Land & McCann (1971) white patch; Finlayson &
Trezzi (2004) shades of gray (p = 6); van de Weijer, Gevers & Gijsenij
(2007) first-order gray edge (p = 6, σ = 1).
Hordley & Finlayson (2006) and Gijsenij, Gevers & van de Weijer (2011) for
the angular-error summary statistics (median, trimean, worst 25 %).
Sharma, Wu & Dalal (2005) for CIEDE2000 (via colour-science).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import os
import sys
import time
from functools import lru_cache

import numpy as np
from scipy import ndimage

import models

from recovery import Camera, IlluminantEstimate, angular_error, estimate_illuminant, render
from testing.scenes import MondrianScene, draw_scene, grid_illuminant, named_camera

__all__ = ["METHODS_BENCHED", "true_xyz_d65", "summarise_angles", "delta_e00_scene", "evaluate_scene",
           "run_benchmark", "format_tables", "main"]

#: Estimators run on every scene, in table order (``true-light`` is added).
METHODS_BENCHED = ("maloney-wandell", "auto", "bayes", "gray-world", "white-patch", "shades-of-gray", "gray-edge")
TRUE_LIGHT = "true-light"
#: The usual RAW pipeline with the true light: diagonal white balance, then
#: a fixed camera-to-XYZ matrix fitted under D65.
TRUE_LIGHT_DIAGONAL = "true-light diag+matrix"
SUBSPACE_METHODS = ("maloney-wandell", "auto", "bayes")


@lru_cache(maxsize=None)
def _observer(step: float) -> np.ndarray:
    return models.observer("CIE 1931 2 Degree Standard Observer", models.wavelength_grid(400, 700, step))


def true_xyz_d65(scene: MondrianScene) -> np.ndarray:
    """CIE 1931 XYZ of each surface under D65, times its shading, ``(K, 3)``,
    with a perfect white under D65 at Y = 1, on the scene's grid."""
    step = float(scene.wavelengths[1] - scene.wavelengths[0])
    cmf = _observer(step)
    d65 = grid_illuminant("D65", step)
    white = d65 @ cmf
    return scene.shading[:, None] * ((d65 * scene.reflectances) @ cmf) / white[1]


@lru_cache(maxsize=None)
def _d65_white_xy(step: float) -> tuple[float, float]:
    white = grid_illuminant("D65", step) @ _observer(step)
    return float(white[0] / white.sum()), float(white[1] / white.sum())


# --------------------------------------------------------------------------- metrics
def summarise_angles(errors) -> dict:
    """Mean, median, trimean (Tukey), 95th percentile and mean of the worst
    25 % of angular errors (NaNs, from failed runs, are left out)."""
    e = np.asarray(errors, float)
    e = np.sort(e[np.isfinite(e)])
    if e.size == 0:
        return {k: float("nan") for k in ("mean", "median", "trimean", "p95", "worst25")}
    q1, q2, q3 = np.percentile(e, [25, 50, 75])
    n_worst = max(1, int(math.ceil(0.25 * e.size)))
    return {"mean": float(e.mean()), "median": float(q2), "trimean": float((q1 + 2 * q2 + q3) / 4),
            "p95": float(np.percentile(e, 95)), "worst25": float(e[-n_worst:].mean())}


@lru_cache(maxsize=None)
def _d65_camera_matrix(camera_name: str) -> np.ndarray:
    """The usual RAW pipeline's fixed camera-to-XYZ matrix: least squares
    from white-balanced camera RGB to XYZ of colour-science's reflectances
    under D65 (white Y = 1), on the camera's 10 nm grid."""
    cam = named_camera(camera_name)
    d65 = models.illuminant("D65", cam.wavelengths)
    refl = models.reflectance_set("all", cam.wavelengths)
    cmf = models.observer("XYZ", cam.wavelengths)
    rgb = cam.response(refl * d65)
    white = cam.response(d65)
    xyz = (refl * d65) @ cmf / (d65 @ cmf[:, 1])
    M, *_ = np.linalg.lstsq(rgb / white, xyz, rcond=None)
    return M.T


def diagonal_pipeline_xyz(scene: MondrianScene, camera: Camera, light_rgb: np.ndarray) -> np.ndarray:
    """XYZ under D65 by the usual RAW pipeline: divide by the light's camera
    RGB (a diagonal white balance), then the fixed matrix fitted under D65."""
    M = _d65_camera_matrix(scene.camera_name)
    return (scene.image.astype(np.float64) / np.asarray(light_rgb, float)) @ M.T


def delta_e00_scene(scene: MondrianScene, camera: Camera, estimate: IlluminantEstimate | None,
                    erode: int = 1, xyz: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """CIEDE2000 of each surface, rendered under D65 with ``estimate``.

    ``render(image, camera, estimate, target="D65", output="XYZ")`` is
    averaged over each surface's rectangle eroded by ``erode`` pixels; one
    exposure scale per scene, least squares on Y over the surfaces, maps it
    onto :func:`true_xyz_d65`; both go to CIELAB with the D65 white of the
    same computation, then ``colour.delta_E(method="CIE 2000")``.

    Returns
    -------
    de : (K,) ΔE00 per surface
    scale : the exposure scale applied to the rendering
    """
    import colour

    if xyz is None:
        xyz = render(scene.image, camera, estimate, target="D65", output="XYZ").astype(np.float64)
    k = scene.reflectances.shape[0]
    got = np.empty((k, 3))
    for j in range(k):
        m = scene.labels == j
        if erode:
            me = ndimage.binary_erosion(m, iterations=erode)
            m = me if me.any() else m
        got[j] = xyz[m].mean(axis=0)
    want = true_xyz_d65(scene)
    den = float(got[:, 1] @ got[:, 1])
    scale = float(got[:, 1] @ want[:, 1]) / den if den > 0 else 1.0
    xy = np.array(_d65_white_xy(float(scene.wavelengths[1] - scene.wavelengths[0])))
    lab_got = colour.XYZ_to_Lab(got * scale, xy)
    lab_want = colour.XYZ_to_Lab(want, xy)
    return np.asarray(colour.delta_E(lab_got, lab_want, method="CIE 2000"), float), scale


def _true_estimate(scene: MondrianScene, camera: Camera) -> IlluminantEstimate:
    """The true light as an estimate: its spectrum on the camera's grid
    (unit mean) and the camera's response to it."""
    spd = models.illuminant(scene.illuminant_name, camera.wavelengths)
    spd = spd / spd.mean()
    rgb = camera.response(spd)
    return IlluminantEstimate(rgb=rgb / np.linalg.norm(rgb), spectrum=spd, wavelengths=camera.wavelengths,
                              method=TRUE_LIGHT)


def _fallback_reason(decision: str) -> str:
    d = decision.lower()
    if "non-positive camera response" in d:
        return "non-positive light rgb"
    if "surface variation" in d or "cannot span" in d or "no signal" in d:
        return "too little surface variation"
    if "data not confined" in d:
        return "data not in a subspace"
    if "estimated light spectrum" in d:
        return "non-physical light"
    return "other"


def evaluate_scene(scene: MondrianScene, methods=METHODS_BENCHED, with_true_light: bool = True) -> dict:
    """Run every method on one scene; angle, time, fallback and ΔE00 per method."""
    cam = named_camera(scene.camera_name)
    out = {}
    runs = list(methods) + ([TRUE_LIGHT, TRUE_LIGHT_DIAGONAL] if with_true_light else [])
    for m in runs:
        rec = {"method_ran": None, "angle": float("nan"), "ms": float("nan"), "fallback": False,
               "fallback_reason": None, "de00": [], "error": None}
        try:
            if m == TRUE_LIGHT_DIAGONAL:
                est = _true_estimate(scene, cam)
                de, scale = delta_e00_scene(scene, cam, None, xyz=diagonal_pipeline_xyz(
                    scene, cam, cam.response(est.spectrum)))
                rec.update(method_ran=m, angle=float(angular_error(est.rgb, scene.rgb_true)),
                           de00=[float(x) for x in de], exposure_scale=scale)
                out[m] = rec
                continue
            if m == TRUE_LIGHT:
                est = _true_estimate(scene, cam)
            else:
                t0 = time.perf_counter()
                est = estimate_illuminant(scene.image, cam, method=m, white_level=1.0,
                                          **({"on_failure": "fallback"} if m in SUBSPACE_METHODS else {}))
                rec["ms"] = (time.perf_counter() - t0) * 1000.0
            rec["method_ran"] = est.method
            rec["angle"] = float(angular_error(est.rgb, scene.rgb_true))
            if m in SUBSPACE_METHODS:
                fr = est.diagnostics.get("subspace_fit_ratio")
                rec["subspace_fit_ratio"] = None if fr is None else float(fr)
                rec["decision"] = est.diagnostics.get("decision")
            if m in SUBSPACE_METHODS and est.method not in ("maloney-wandell", "bayes", "learned"):
                rec["fallback"] = True
                rec["fallback_reason"] = _fallback_reason(str(est.diagnostics.get("decision", "")))
            de, scale = delta_e00_scene(scene, cam, est)
            rec["de00"] = [float(x) for x in de]
            rec["exposure_scale"] = scale
        except Exception as e:  # recorded and counted, never silently dropped
            rec["error"] = f"{type(e).__name__}: {e}"
        out[m] = rec
    return out


# --------------------------------------------------------------------------- run
def _summary(records: list[dict], method: str) -> dict:
    recs = [r[method] for r in records]
    ang = summarise_angles([r["angle"] for r in recs])
    de = np.array([x for r in recs for x in r["de00"]], float)
    de = de[np.isfinite(de)]
    ms = np.array([r["ms"] for r in recs], float)
    ms = ms[np.isfinite(ms)]
    reasons: dict[str, int] = {}
    for r in recs:
        if r["fallback"]:
            reasons[r["fallback_reason"]] = reasons.get(r["fallback_reason"], 0) + 1
    n = len(recs)
    return {
        "method": method, "n_scenes": n, "n_surfaces": int(de.size),
        "n_failed": int(sum(r["error"] is not None for r in recs)),
        "fallback_rate": (sum(r["fallback"] for r in recs) / n) if method in SUBSPACE_METHODS and n else None,
        "fallback_reasons": reasons,
        **{f"angle_{k}": v for k, v in ang.items()},
        "de00_median": float(np.median(de)) if de.size else float("nan"),
        "de00_mean": float(de.mean()) if de.size else float("nan"),
        "de00_p95": float(np.percentile(de, 95)) if de.size else float("nan"),
        "ms_mean": float(ms.mean()) if ms.size else float("nan"),
        "ms_median": float(np.median(ms)) if ms.size else float("nan"),
    }


def _scene_task(task) -> dict:
    seed, k, i, size, methods = task
    sc = draw_scene(seed, k, i, size)
    return {"index": i, "camera": sc.camera_name, "illuminant": sc.illuminant_name,
            "surfaces": [int(x) for x in sc.surface_indices], "shading": [float(x) for x in sc.shading],
            "results": evaluate_scene(sc, methods)}


def _warm_up(seed: int, size: int, methods) -> None:
    """Run one scene untimed so lazy imports and caches do not land in the
    first timed estimate."""
    evaluate_scene(draw_scene(seed, 1, 0, size), methods)


def run_benchmark(scenes: int = 100, size: int = 64, seed: int = 0, ks=(4, 8, 16, 32),
                  methods=METHODS_BENCHED, jobs: int = 1, progress=None) -> dict:
    """Run the development benchmark; returns summaries and per-scene records.

    The same scenes (:func:`draw_scene`) are given to every method; scene
    ``i`` for ``K`` depends only on ``(seed, K, i)``, so results do not
    depend on ``jobs`` or on which other K are run.

    Parameters
    ----------
    jobs : int
        Worker processes (each scene is evaluated whole in one process, so
        the per-estimate times stay single-threaded measurements).

    Returns
    -------
    dict with ``config``, ``summary`` (``{K: [per-method dict]}``, plus
    ``"all"`` pooled over K) and ``scenes`` (``{K: [per-scene dict]}``).
    """
    tasks = [(seed, k, i, size, tuple(methods)) for k in ks for i in range(scenes)]
    t_start = time.perf_counter()
    done: dict[int, list] = {k: [] for k in ks}
    if jobs > 1:
        import multiprocessing as mp

        with mp.get_context("fork" if "fork" in mp.get_all_start_methods() else None).Pool(
                jobs, initializer=_warm_up, initargs=(seed, size, tuple(methods))) as pool:
            for task, info in zip(tasks, pool.imap(_scene_task, tasks, chunksize=4)):
                done[task[1]].append(info)
                if progress:
                    progress(task[1], len(done[task[1]]), scenes)
    else:
        _warm_up(seed, size, methods)
        for task in tasks:
            done[task[1]].append(_scene_task(task))
            if progress:
                progress(task[1], len(done[task[1]]), scenes)
    summary, per_scene = {}, {}
    runs = list(methods) + [TRUE_LIGHT, TRUE_LIGHT_DIAGONAL]
    for k in ks:
        per_scene[str(k)] = done[k]
        summary[str(k)] = [_summary([r["results"] for r in done[k]], m) for m in runs]
    pooled = [r["results"] for k in ks for r in done[k]]
    summary["all"] = [_summary(pooled, m) for m in runs]
    config = {"scenes_per_k": scenes, "size": size, "seed": seed, "ks": list(ks), "methods": list(methods),
              "jobs": jobs, "synthesis_grid_nm": [400, 700, 5], "estimation_grid_nm": [400, 700, 10],
              "peak": 0.9, "multiplicative_noise": 0.01, "additive_noise": 0.0005, "shading": [0.5, 1.0],
              "white_level": 1.0, "erode_px": 1, "cameras": models.camera_names(),
              "illuminants": models.illuminant_names(), "reflectances": "models.reflectance_set('all')",
              "wall_seconds": time.perf_counter() - t_start}
    return {"config": config, "summary": summary, "scenes": per_scene}


# --------------------------------------------------------------------------- output
_COLS = [("angle_mean", "mean", "{:7.2f}"), ("angle_median", "median", "{:7.2f}"),
         ("angle_trimean", "trimean", "{:7.2f}"), ("angle_p95", "p95", "{:7.2f}"),
         ("angle_worst25", "worst25", "{:7.2f}"), ("de00_median", "dE00med", "{:7.2f}"),
         ("de00_mean", "dE00mean", "{:8.2f}"), ("ms_mean", "ms", "{:6.1f}")]


def format_tables(result: dict) -> str:
    """One plain-text table per K (and one pooled over K): rows are methods."""
    lines = []
    head = f"{'method':<23}" + "".join(f"{lab:>{len(fmt.format(0.0))+1}}" for _, lab, fmt in _COLS) \
        + f"{'fallback':>9}{'failed':>7}"
    for key, rows in result["summary"].items():
        n = rows[0]["n_scenes"]
        title = f"K = {key}" if key != "all" else "all K pooled"
        lines.append(f"\n{title}: {n} scenes, {rows[0]['n_surfaces']} surfaces; angular error in degrees, "
                     "CIEDE2000 under D65, ms per estimate")
        lines.append(head)
        for r in rows:
            cells = "".join(" " + (fmt.format(r[c]) if math.isfinite(r[c]) else f"{'-':>{len(fmt.format(0.0))}}")
                            for c, _, fmt in _COLS)
            fb = "" if r["fallback_rate"] is None else f"{100 * r['fallback_rate']:.0f}%"
            lines.append(f"{r['method']:<23}{cells}{fb:>9}{r['n_failed']:>7}")
        for r in rows:
            if r["fallback_reasons"]:
                why = ", ".join(f"{v} {k}" for k, v in sorted(r["fallback_reasons"].items(), key=lambda x: -x[1]))
                lines.append(f"  {r['method']} fell back to shades-of-gray: {why}")
    return "\n".join(lines).lstrip("\n")


def _clean(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: _clean(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_clean(v) for v in x]
    if isinstance(x, np.generic):
        return _clean(x.item())
    return x


def write_outputs(result: dict, out_dir: str) -> tuple[str, str]:
    """``bench_summary.csv`` (one row per K and method) and ``bench.json``
    (config, summaries and every per-scene number; NaN written as null)."""
    os.makedirs(out_dir, exist_ok=True)
    csv_path = os.path.join(out_dir, "bench_summary.csv")
    json_path = os.path.join(out_dir, "bench.json")
    fields = ["K", "method", "n_scenes", "n_surfaces", "n_failed", "fallback_rate", "angle_mean", "angle_median",
              "angle_trimean", "angle_p95", "angle_worst25", "de00_median", "de00_mean", "de00_p95",
              "ms_mean", "ms_median"]
    with open(csv_path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(fields)
        for key, rows in result["summary"].items():
            for r in rows:
                vals = [key] + [r[c] for c in fields[1:]]
                w.writerow(["" if v is None or (isinstance(v, float) and not math.isfinite(v))
                            else (f"{v:.6g}" if isinstance(v, float) else v) for v in vals])
    with open(json_path, "w") as f:
        json.dump(_clean(result), f, indent=1, allow_nan=False)
    return csv_path, json_path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.synthetic",
                                 description="The development benchmark of docs/DESIGN.md (Mondrian scenes).")
    ap.add_argument("--scenes", type=int, default=100, help="scenes per K (default 100)")
    ap.add_argument("--size", type=int, default=64, help="image side in pixels (default 64)")
    ap.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    ap.add_argument("--ks", default="4,8,16,32", help="comma-separated numbers of surfaces (default 4,8,16,32)")
    ap.add_argument("--out", default="out", help="output directory (default ./out)")
    ap.add_argument("--jobs", type=int, default=1,
                    help="worker processes (default 1; timings stay per-process single-threaded)")
    ap.add_argument("--quiet", action="store_true", help="no progress on stderr")
    a = ap.parse_args(argv)
    try:
        ks = tuple(int(x) for x in a.ks.split(",") if x.strip())
    except ValueError:
        ap.error("--ks must be comma-separated integers")
    if not ks or any(k < 1 for k in ks) or a.scenes < 1 or a.size < 8:
        ap.error("need --scenes >= 1, --size >= 8 and every K >= 1")

    def progress(k, i, n):
        if not a.quiet and (i == n or i % 10 == 0):
            print(f"  K={k}: {i}/{n} scenes", file=sys.stderr, flush=True)

    t0 = time.perf_counter()
    result = run_benchmark(a.scenes, a.size, a.seed, ks, jobs=max(1, a.jobs), progress=progress)
    csv_path, json_path = write_outputs(result, a.out)
    print(format_tables(result))
    errs = [(k, s["index"], m, r["error"]) for k, v in result["scenes"].items() for s in v
            for m, r in s["results"].items() if r["error"]]
    for k, i, m, e in errs[:10]:
        print(f"error: K={k} scene {i} {m}: {e}", file=sys.stderr)
    print(f"\nwrote {csv_path} and {json_path} ({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
