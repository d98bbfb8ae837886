"""The metamer set's range beside the prior's band (issue 31, item 2).

``python -m benchmarks.metamers`` (about 3 minutes; ``--quick``: one camera, one light).

Scenes: each shipped reflectance set (:data:`models.surface_data.SURFACE_SETS`) in charts of at most 24
surfaces (4 x 6 patches of 20 x 20 pixels, 0.3 % multiplicative noise), seen by the shipped cameras
(measured sensitivities) and by the same cameras told only their least-squares colour matrix
(:func:`benchmarks.chart_scenes.least_squares_matrix`, as a RAW upload is), under D65 and A (at most 48
surfaces per set, a fixed random draw); the light
estimated by ``auto`` (:func:`recovery.analyze`), the surfaces read at the patch centres with
:meth:`~recovery.api.AnalysisResult.metamer_range` and
:meth:`~recovery.api.AnalysisResult.surface_estimates`. The truth is put on the estimate's scale by one least
squares factor per scene (as ``benchmarks.surfaces`` scores RMSE).

Printed per set and camera description: the share of true values inside the metamer range (all would be,
with the true light and camera, up to the noise), the share of surfaces whose colour no reflectance gives
under the estimated light (``slack`` > 0) and of those brighter than a white at the surfaces' exposure
(``scale`` > 1), the mean width of the range in three wavelength bands against the width of the calibrated
90 % band (2 x 1.645 x ``reflectance_std``) and its coverage, and the time per surface.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

LIGHTS = ("D65", "A")
#: surfaces per set at most (a fixed random draw: the sets are stored in hue order, and a chart of one hue
#: fools every light estimator, which is measured in ``benchmarks.chart_scenes --switch``, not here)
PER_SET = 48
BANDS = ((400, 450), (450, 650), (650, 701))


def chart(cam, R, light, seed):
    """A 4 x 6 chart of the reflectances ``R`` (at most 24) under ``light``: the image, the patch centres."""
    import models

    wl = cam.wavelengths
    E = models.illuminant(light, wl)
    rho = R @ (cam.sensitivities.T * (E * cam.dlambda)).T
    full = np.vstack([rho, np.tile(rho.mean(0), (24 - rho.shape[0], 1))]) if rho.shape[0] < 24 else rho
    img = np.repeat(np.repeat(full.reshape(4, 6, -1), 20, 0), 20, 1)
    rng = np.random.default_rng(seed)
    img = img / img.max() * 0.8 * (1 + 0.003 * rng.standard_normal(img.shape))
    pts = [(10 + 20 * (i // 6), 10 + 20 * (i % 6)) for i in range(R.shape[0])]
    return img, pts


def run(quick: bool = False, log=print) -> dict:
    import models
    from benchmarks.chart_scenes import least_squares_matrix
    from models.surface_data import SURFACE_SETS, surface_sets
    from recovery import Camera, analyze
    from recovery.cameras import camera_from_matrix

    names = models.camera_names()[:1] if quick else models.camera_names()
    lights = LIGHTS[:1] if quick else LIGHTS
    out = {}
    for set_name in SURFACE_SETS:
        for name in names:
            measured = Camera.named(name)
            wl = measured.wavelengths
            R_all = surface_sets(wl, [set_name])[0]
            R_all = R_all[np.random.default_rng(0).permutation(R_all.shape[0])[:PER_SET]]
            sens5 = models.camera_sensitivities(models.canonical_camera_name(name), models.wavelength_grid(400, 700, 5))
            matrix = camera_from_matrix(least_squares_matrix(sens5), wl)
            for desc, cam in (("measured", measured), ("matrix", matrix)):
                rec = out.setdefault((set_name, desc), {"inside": [], "slack": [], "bright": [], "width": [], "band": [],
                                                        "band_in": [], "ms": [], "wl": wl})
                for light in lights:
                    for s0 in range(0, R_all.shape[0], 24):
                        R = R_all[s0:s0 + 24]
                        # the scene is seen by the real camera; the product is told `cam`
                        img, pts = chart(measured, R, light, s0)
                        res = analyze(img, cam)
                        t0 = time.perf_counter()
                        mr = res.metamer_range(pts)
                        rec["ms"].append(1000 * (time.perf_counter() - t0) / len(pts))
                        pe = res.surface_estimates(pts)
                        k = float(np.sum(pe.mean * R) / np.sum(R * R))
                        T = R * k
                        rec["inside"].append((T >= mr.lower - 1e-6) & (T <= mr.upper + 1e-6))
                        rec["slack"].append(mr.slack > 0)
                        rec["bright"].append(mr.scale > 1)
                        rec["width"].append(mr.width)
                        rec["band"].append(2 * 1.645 * pe.std)
                        rec["band_in"].append(np.abs(T - pe.mean) <= 1.645 * pe.std)
            log(f"  {set_name}: {R_all.shape[0]} surfaces")
    return out


def report(out: dict) -> None:
    print("| set | camera told | surfaces x lights | truth inside the metamer range | colour out of reach | "
          "brighter than white | "
          "range width 400-450 / 450-650 / 650-700 nm | 90 % band width (same bands) | band holds the truth | "
          "ms per surface |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for (set_name, desc), r in out.items():
        wl = r["wl"]
        inside, width, band = (np.concatenate(r[k]) for k in ("inside", "width", "band"))
        sel = [(wl >= a) & (wl < b) for a, b in BANDS]
        print(f"| {set_name} | {desc} | {inside.shape[0]} | {inside.mean():.3f} | "
              f"{np.concatenate(r['slack']).mean():.3f} | {np.concatenate(r['bright']).mean():.3f} | " + " / ".join(f"{width[:, m].mean():.2f}" for m in sel)
              + " | " + " / ".join(f"{band[:, m].mean():.2f}" for m in sel)
              + f" | {np.concatenate(r['band_in']).mean():.3f} | {np.median(r['ms']):.0f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="one camera, one light")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    out = run(a.quick)
    print(f"\n({time.perf_counter() - t0:.0f} s)\n")
    report(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
