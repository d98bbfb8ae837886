"""The light posterior for a camera known only by its colour matrix: the
sensitivities derived from the matrix and the CIE 1931 colour matching
functions (:func:`recovery.cameras.camera_from_matrix`, what the product
uses) against the mean of the 47 measured cameras' Gaussian conditioned on
the matrix (:func:`recovery.surface_prior.camera_posterior`, the camera
model of the surface estimates), each with :func:`recovery.bayes.estimate_bayes`
and its defaults (issue 27 item 3: "make the posterior robust to
matrix-derived cameras").

Two sets, in one run:

* the real photographs of the three benchmarks (``../shared/data/real``),
  each camera described by the matrix LibRaw holds for it; a camera of the
  benchmarks that is also among the 47 measured cameras (Canon EOS-1Ds
  Mark III, EOS 600D, Nikon D810; the EOS 5DS for the 5DS R) is left out of
  the prior that describes it;
* chart and Mondrian scenes (:mod:`benchmarks.chart_scenes`' lights and
  layouts, pixels rather than DNGs) seen by every 4th of the 47 measured
  cameras, described by their least-squares matrix; the scene's camera is
  left out of the prior.

Prints the mean / median angular error per benchmark and per camera.

Usage::

    python -m benchmarks.matrix_camera [--quick]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

#: benchmark cameras that are (or are the sibling of) one of the 47 measured cameras
SAME = {"Canon EOS-1Ds Mark III": ("Canon EOS-1Ds Mark III",), "Canon EOS 600D": ("Canon EOS 600D",),
        "Nikon D810": ("Nikon D810",), "Canon EOS 5DS R": ("Canon EOS 5DS",)}


def cameras_for(color_matrix, exclude=()):
    """The two descriptions of a camera known by ``color_matrix``: (matrix-derived, the camera posterior's mean)."""
    from recovery import Camera
    from recovery.cameras import camera_from_matrix
    from recovery.surface_prior import camera_posterior

    a = camera_from_matrix(color_matrix)
    mean, _ = camera_posterior(color_matrix, a.wavelengths, n=0, exclude=exclude)
    b = Camera(a.wavelengths, mean / mean.max(), a.name + " (camera posterior mean)", "matrix-derived", a.notes,
               np.asarray(color_matrix, float))
    return a, b


def angle(a, b) -> float:
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    return float(np.degrees(2 * np.arctan2(np.linalg.norm(a - b), np.linalg.norm(a + b))))


def real_photographs(step: int = 1) -> None:
    from recovery.bayes import estimate_bayes

    from .realdata import REAL_DIR, load_real, usable_mask

    rs = load_real(REAL_DIR)
    rows = np.arange(0, len(rs.truth), step)
    cams = {k: cameras_for(m, SAME.get(k, ())) for k, m in rs.matrices.items()}
    err = np.zeros((len(rows), 2))
    for n, i in enumerate(rows):
        mk = usable_mask(rs.images[i])
        for j in range(2):
            r, _, _ = estimate_bayes(rs.images[i], mk, cams[rs.camera[i]][j])
            err[n, j] = angle(r, rs.truth[i])
    print("\n## Real photographs (mean / median degrees)\n")
    print("| | matrix-derived (shipped) | camera posterior mean | posterior mean better on |")
    print("|---|---|---|---|")
    for key, sel in [(b, rs.dataset[rows] == b) for b in rs.datasets] + \
                     [(f"  {c}", rs.camera[rows] == c) for c in np.unique(rs.camera)]:
        e = err[sel]
        print(f"| {key} | {e[:, 0].mean():.2f} / {np.median(e[:, 0]):.2f} | {e[:, 1].mean():.2f} / "
              f"{np.median(e[:, 1]):.2f} | {np.mean(e[:, 1] < e[:, 0]):.0%} |")


def chart_scenes(every: int = 4, seeds=(1,)) -> None:
    import models
    from recovery.bayes import estimate_bayes
    from testing import dngwriter as W

    from .chart_scenes import LIGHTS, measured_sensitivities, rawtoaces_cameras

    wl = models.wavelength_grid(400, 700, 5)
    dl = models.wavelength_step(wl)
    refl = models.reflectance_set("all", wl)
    d65 = models.illuminant("D65", wl)
    cmfs = models.observer("CIE 1931 2 Degree Standard Observer", wl)
    print("\n## Chart and Mondrian scenes, cameras known by their least-squares matrix (mean / median degrees)\n")
    print("| camera | matrix-derived (shipped) | camera posterior mean |")
    print("|---|---|---|")
    tot = []
    for path in rawtoaces_cameras(every):
        h = json.loads(path.read_text())["header"]
        name = f"{h['manufacturer']} {h['model']}"
        sens = measured_sensitivities(path, wl)
        xyz, cam = (refl * d65 * dl) @ cmfs, (refl * d65 * dl) @ sens
        mt, *_ = np.linalg.lstsq(xyz, cam, rcond=None)
        pair = cameras_for(W._normalise_color_matrix(mt.T), (name,))
        per = []
        for seed in seeds:
            for light in LIGHTS:
                for layout in ("grid", "mondrian"):
                    rng = np.random.default_rng([seed, 7])
                    if layout == "grid":
                        surf, pick, shading = models.reflectance_set("colorchecker", wl), np.arange(24), np.ones(24)
                    else:
                        surf = refl
                        pick = rng.choice(surf.shape[0], 16, replace=False)
                        shading = rng.uniform(0.5, 1.0, 16)
                    e = models.illuminant(light, wl) * dl
                    R = np.vstack([surf[pick], np.full((1, wl.size), 0.05)])
                    patch = np.append(shading, 1.0)[:, None] * ((R * e) @ sens)
                    px = np.repeat(patch / patch.max() * 0.9, 50, axis=0)     # 50 pixels a patch, 1 % noise
                    px = px * (1 + 0.01 * rng.standard_normal(px.shape))
                    per.append([angle(estimate_bayes(px, None, c)[0], e @ sens) for c in pair])
        per = np.array(per)
        tot.append(per)
        print(f"| {name} | {per[:, 0].mean():.2f} / {np.median(per[:, 0]):.2f} | {per[:, 1].mean():.2f} / "
              f"{np.median(per[:, 1]):.2f} |", flush=True)
    t = np.concatenate(tot)
    print(f"| **all** | {t[:, 0].mean():.2f} / {np.median(t[:, 0]):.2f} | {t[:, 1].mean():.2f} / "
          f"{np.median(t[:, 1]):.2f} |")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="every 10th photograph, every 12th camera")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    real_photographs(10 if a.quick else 1)
    chart_scenes(12 if a.quick else 4)
    print(f"\ntotal {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
