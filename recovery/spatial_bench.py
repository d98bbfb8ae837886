"""One light or a light map: how often the automatic choice is right.

Run as::

    python -m recovery.spatial_bench [--scenes 25] [--size 64] [--seed 0] [--ks 4,8,16,32] [--jobs 2]

Uniformly lit scenes are the development benchmark's Mondrians
(``shared/DESIGN.md``; :func:`recovery.bench.draw_scene`, the same scenes).
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
Wandell (1985), ``shared/seeds/002``, Fig. 1 and 'A condition on spatial
variation' (a light that varies slowly across the image, estimated in
regions). ``shared/DESIGN.md``, "The development benchmark".
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

import models

from .api import angular_error, estimate_illuminant
from .bench import _camera, _illuminant, _reflectances, _sensitivities, draw_scene, kd_partition

__all__ = ["two_light_scene", "draw_two_light_scene", "evaluate", "run", "main"]

LAYOUTS = ("halves", "gradient")


def _mix_field(rng: np.random.Generator, size: int, layout: str) -> np.ndarray:
    """The fraction ``a(x)`` of light B at each pixel, ``(size, size)``."""
    r, c = np.mgrid[0:size, 0:size].astype(float) + 0.5
    if layout == "halves":
        cut = rng.uniform(0.35, 0.65) * size
        a = (c >= cut) if rng.integers(2) else (r >= cut)
        return a.astype(float)
    if layout == "gradient":
        kind = int(rng.integers(3))
        t = c / size if kind == 0 else (r / size if kind == 1 else (r + c) / (2 * size))
        return t
    raise ValueError(f"layout must be one of {LAYOUTS}, not {layout!r}")


def two_light_scene(rng: np.random.Generator, k: int, camera_name: str, light_a: str, light_b: str,
                    layout: str, size: int = 64, *, shading=(0.5, 1.0), peak: float = 0.9,
                    multiplicative_noise: float = 0.01, additive_noise: float = 0.0005, step: float = 5.0):
    """A development-benchmark Mondrian lit by two lights.

    As :func:`recovery.bench.mondrian_scene` (Wandell 1985, eq. 12 on a
    ``step`` nm grid, the same noise and scaling), but the light at pixel
    ``x`` is ``(1 - a(x)) E_A + a(x) E_B`` (unit-mean spectra), so the sensor
    value is ``s_j [(1 - a) rho_A,j + a rho_B,j]``: light is additive.

    Returns
    -------
    image : (size, size, 3) float32 in [0, 1]
    truth : (size, size, 3) unit camera response to the light at each pixel
    separation : angle (deg) between the two lights' camera responses
    """
    wl = models.wavelength_grid(400, 700, step)
    library = _reflectances(step)
    R = _sensitivities(camera_name, step) * models.wavelength_step(wl)[:, None]
    Ea, Eb = _illuminant(light_a, step), _illuminant(light_b, step)
    idx = rng.choice(library.shape[0], size=k, replace=False)
    refl = library[idx]
    rects = kd_partition(rng, (size, size), k, 4)
    shade = rng.uniform(shading[0], shading[1], size=k)
    labels = np.empty((size, size), dtype=int)
    for j, (r0, r1, c0, c1) in enumerate(rects):
        labels[r0:r1, c0:c1] = j
    a = _mix_field(rng, size, layout)[..., None]
    rho_a = shade[:, None] * ((Ea * refl) @ R)
    rho_b = shade[:, None] * ((Eb * refl) @ R)
    img = (1 - a) * rho_a[labels] + a * rho_b[labels]
    img = img * (peak / img.max())
    img = img * (1.0 + multiplicative_noise * rng.standard_normal(img.shape))
    img = img + additive_noise * rng.standard_normal(img.shape)
    img = np.clip(img, 0.0, 1.0).astype(np.float32)
    ea, eb = Ea @ R, Eb @ R
    truth = (1 - a) * ea + a * eb
    truth = truth / np.linalg.norm(truth, axis=2, keepdims=True)
    return img, truth, float(angular_error(ea, eb))


def draw_two_light_scene(seed: int, k: int, index: int, layout: str, size: int = 64,
                         min_separation: float = 3.0):
    """Two-light scene ``index``: camera and two lights drawn uniformly from
    the shipped ones (as :func:`recovery.bench.draw_scene`), redrawn until
    the lights are more than ``min_separation`` degrees apart for that
    camera. Independent of the uniform scenes (its own generator)."""
    rng = np.random.default_rng([int(seed), int(k), int(index), 2, LAYOUTS.index(layout)])
    cams = models.camera_names()
    lights = models.illuminant_names()
    cam = cams[int(rng.integers(len(cams)))]
    R = _sensitivities(cam, 5.0)
    for _ in range(1000):
        la, lb = (lights[int(i)] for i in rng.choice(len(lights), 2, replace=False))
        if angular_error(_illuminant(la, 5.0) @ R, _illuminant(lb, 5.0) @ R) > min_separation:
            break
    img, truth, sep = two_light_scene(rng, k, cam, la, lb, layout, size)
    return img, truth, sep, cam, la, lb


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
    cam = _camera(cam_name)
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
    ap = argparse.ArgumentParser(prog="python -m recovery.spatial_bench",
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
