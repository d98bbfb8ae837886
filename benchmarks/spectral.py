"""Speed bench of spectral rendering: ``python -m benchmarks.spectral``.

A 1024 x 1024 x 31 reflectance Mondrian (400-700 nm, 10 nm; surfaces from
colour-science's ``rawtoaces-190`` set, each rectangle with a shading factor
in [0.5, 1], DESIGN.md's development scenes) rendered under smooth (A, D65,
C) and fluorescent (FL2, FL11) lights: the full 31-band calculation (this
project's best: one (31, 3) matrix per light, float32, chunked; and
colour-science's ``msds_to_XYZ`` for reference) against 4-, 5- and 6-node
rules (uniform, the Wiener point rule, Meyer's four-wavelength XYZ rule, Borges'
quasi-Gaussian (1,1,1) and (2,2,2)), median of several runs in the same process, in both memory layouts:

* band-interleaved ``(H, W, N)`` C order (the ``.npy`` upload): every pixel's
  31 values sit in two cache lines, so a rule that reads 5 bands still pulls
  almost every byte of the cube from memory;
* band-sequential ``(N, H, W)`` (planes, as hyperspectral BSQ files and
  planar readers deliver): a rule that reads ``k`` bands reads ``k/31`` of it.

The Wiener point rule is trained on the other reflectance sets
(ColorChecker x2, CIE TCS, CQS VS), never on the Mondrian's surfaces.
Errors: CIEDE2000 against the full calculation on every pixel (CIELAB
relative to the light's white), the render's own estimate beside it.

The machine may be shared: the figures are noisy, and the load average is
printed with them.
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np

import models
from models import DEFAULT_WAVELENGTHS as WL

from recovery.spectral import ciede2000_between, render_spectra

HELD_OUT_TRAINING = "colorchecker+colorchecker-ohta+tcs+vs"


def mondrian(size: int = 1024, rectangles: int = 96, seed: int = 0, reflectances: str = "rawtoaces-190"):
    """``(size, size, 31)`` float32 Mondrian and its ``(size, size)`` labels."""
    refl = models.reflectance_set(reflectances, WL).astype(np.float32)
    rng = np.random.default_rng(seed)
    labels = np.zeros((size, size), np.int32)
    for k in range(1, rectangles + 1):
        r0, c0 = rng.integers(0, size, 2)
        h, w = rng.integers(size // 16, size // 3, 2)
        labels[r0:r0 + h, c0:c0 + w] = k
    surf = rng.integers(0, refl.shape[0], rectangles + 1)
    shade = rng.uniform(0.5, 1.0, rectangles + 1).astype(np.float32)
    table = refl[surf] * shade[:, None]
    return table[labels], labels


def _time(fn, runs):
    ts, out = [], None
    for _ in range(runs):
        t0 = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t0)
    return float(np.median(ts)) * 1e3, out


def _candidates(include_gauss: bool = True):
    """(label, strategy, n, options) of the rules to time."""
    rules = []
    for n in (4, 5, 6):
        rules.append((f"uniform {n}", "uniform", n, {}))
    for n in (4, 5, 6):
        rules.append((f"wiener-points {n}", "wiener-points", n, {"training": HELD_OUT_TRAINING}))
    if include_gauss:
        # Meyer's four wavelengths (A, C1, C2 orders 3, 2, 1 merged; his Table 2)
        # and Borges' shared abscissas, each in its own setting (light sampled too)
        rules.append(("meyer-xyz 3,2,1", "gauss-ac1c2", None, {"channel": "XYZ"}))
        rules.append(("quasi-gauss-xyz 1,1,1", "quasi-gauss-xyz", None, {"degrees": (1, 1, 1)}))
        rules.append(("quasi-gauss-xyz 2,2,2", "quasi-gauss-xyz", None, {"degrees": (2, 2, 2)}))
    return rules


def run(size=1024, runs=5, lights=("A", "D65", "C", "FL2", "FL11"), layouts=("interleaved", "sequential"),
        colour_reference=True, out=print):
    cube, _ = mondrian(size)
    cubes = {}
    if "interleaved" in layouts:
        cubes["interleaved"] = cube
    if "sequential" in layouts:
        bsq = np.ascontiguousarray(np.moveaxis(cube, -1, 0))
        cubes["sequential"] = np.moveaxis(bsq, 0, -1)
    if "interleaved" not in layouts:
        del cube
    out(f"# spectral render bench: {size}x{size}x31 float32 Mondrian ({size * size * 31 * 4 / 2**20:.0f} MiB), "
        f"median of {runs} runs; load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs (noisy if > 1)")
    out("# times: 'integr' = applying the (N,3) matrix (what the rule changes), median and best run; 'call' = "
        "the whole render_spectra call to linear sRGB (matrices, error estimate on 4096 pixels, integrate; "
        "auto also chooses); runs interleaved over the rules so load drifts alike")
    any_cube = next(iter(cubes.values()))
    if colour_reference:
        import colour

        crop = np.ascontiguousarray(any_cube[:256, :256])
        cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(colour.SpectralShape(400, 700, 10))
        ill = colour.SpectralDistribution(models.illuminant("D65", WL), WL)
        t_c, _ = _time(lambda: colour.msds_to_XYZ(crop, cmfs, ill, method="Integration",
                                                  shape=colour.SpectralShape(400, 700, 10)), 1)
        out(f"colour-science msds_to_XYZ (Integration), D65: {t_c:.0f} ms on 256x256, "
            f"~{t_c * (size * size) / (256 * 256):.0f} ms scaled to {size}x{size} (one run)")
    header = (f"{'light':6} {'layout':11} {'rule':22} {'bands':>5} {'integr ms':>9} {'x full':>6} "
              f"{'min ms':>7} {'x full':>6} {'call ms':>8} {'x full':>6} {'dE00 mean':>9} {'p95':>6} {'est.':>6}")
    summary = []
    rules = [("full (31 bands)", "full", None, {})] + _candidates() + [("auto", "auto", None, {})]
    available = []
    for label, strategy, n, opts in rules:
        try:
            render_spectra(any_cube[:8, :8], WL, "D65", strategy=strategy, n=n, **opts)
            available.append((label, strategy, n, opts))
        except Exception as e:  # noqa: BLE001 - a rule not available in this build
            out(f"# {label}: unavailable in this build ({type(e).__name__}: {str(e)[:90]})")
    for light in lights:
        for layout, c in cubes.items():
            out(header)
            fns = {label: (lambda s=strategy, n=n, o=opts: render_spectra(c, WL, light, strategy=s, n=n,
                                                                          output="linear-sRGB", **o))
                   for label, strategy, n, opts in available}
            results = {label: fn() for label, fn in fns.items()}        # warm caches
            calls = {label: [] for label in fns}
            ints = {label: [] for label in fns}
            for _ in range(runs):                                       # interleaved: load drifts alike
                for label, fn in fns.items():
                    t0 = time.perf_counter()
                    r = fn()
                    calls[label].append((time.perf_counter() - t0) * 1e3)
                    ints[label].append(r.report["timings_ms"]["integrate"])
            full = results["full (31 bands)"]
            white = np.array(full.report["white_xyz"])
            M = _to_xyz()
            ref_xyz = full.image.reshape(-1, 3) @ M
            f_int, f_min, f_call = (float(np.median(ints["full (31 bands)"])), float(np.min(ints["full (31 bands)"])),
                                    float(np.median(calls["full (31 bands)"])))
            for label, strategy, n, opts in available:
                res = results[label]
                t_int, t_min, t_call = float(np.median(ints[label])), float(np.min(ints[label])), \
                    float(np.median(calls[label]))
                d = ciede2000_between(ref_xyz, res.image.reshape(-1, 3) @ M, white)
                name = label if strategy != "auto" else f"auto->{res.report['strategy']} {res.report['n']}"
                out(f"{light:6} {layout:11} {name:22} {res.report['bands_read']:5d} {t_int:9.1f} "
                    f"{f_int / t_int:6.2f} {t_min:7.1f} {f_min / t_min:6.2f} {t_call:8.1f} {f_call / t_call:6.2f} "
                    f"{d.mean():9.3f} {np.percentile(d, 95):6.3f} {res.report['error']['mean']:6.3f}")
                if strategy != "full":
                    summary.append((light, layout, name, res.report["bands_read"], f_int / t_int,
                                    f_call / t_call, float(d.mean()), f_min / t_min))
    out("# target: a 4-6 node rule >= 4x faster than the full calculation with mean CIEDE2000 < 1 "
        "(non-fluorescent lights)")
    for layout in cubes:
        for light in lights:
            ok = [s for s in summary if s[0] == light and s[1] == layout and s[3] <= 6 and s[6] < 1]
            best = max(ok, key=lambda s: s[4], default=None)
            if best:
                out(f"{light:6} {layout:11} best rule under 1 dE00 with <= 6 bands: {best[2]}: "
                    f"integrate {best[4]:.2f}x (median), {best[7]:.2f}x (best run), whole call {best[5]:.2f}x; "
                    f"mean dE00 {best[6]:.3f}")
            else:
                out(f"{light:6} {layout:11} no rule with <= 6 bands under 1 dE00")
    return summary


def _to_xyz():
    """Row-vector matrix from linear sRGB back to XYZ (the sRGB primaries)."""
    return models.display("sRGB").primaries_XYZ.T


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--size", type=int, default=1024)
    p.add_argument("--runs", type=int, default=5)
    p.add_argument("--lights", default="A,D65,C,FL2,FL11")
    p.add_argument("--layouts", default="interleaved,sequential")
    p.add_argument("--no-colour-reference", action="store_true")
    a = p.parse_args(argv)
    run(a.size, a.runs, tuple(a.lights.split(",")), tuple(a.layouts.split(",")), not a.no_colour_reference)


if __name__ == "__main__":
    main()
