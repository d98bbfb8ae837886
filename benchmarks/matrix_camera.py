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
* the chart and Mondrian scenes of :mod:`benchmarks.chart_scenes`
  (:func:`benchmarks.chart_scenes.matrix_scene`: its lights and layouts,
  the image before its mosaic) seen by every 4th of the 47 measured
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


def real_photographs(step: int = 1) -> None:
    from recovery.bayes import estimate_bayes
    from recovery.metrics import angular_error

    from .realdata import REAL_DIR, load_real, usable_mask

    rs = load_real(REAL_DIR)
    rows = np.arange(0, len(rs.truth), step)
    cams = {k: cameras_for(m, SAME.get(k, ())) for k, m in rs.matrices.items()}
    err = np.zeros((len(rows), 2))
    for n, i in enumerate(rows):
        mk = usable_mask(rs.images[i])
        for j in range(2):
            r, _, _ = estimate_bayes(rs.images[i], mk, cams[rs.camera[i]][j])
            err[n, j] = angular_error(r, rs.truth[i])
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
    from recovery.metrics import angular_error

    from .chart_scenes import LIGHTS, LAYOUTS, least_squares_matrix, matrix_scene, measured_sensitivities, \
        rawtoaces_cameras

    wl = models.wavelength_grid(400, 700, 5)
    print("\n## Chart and Mondrian scenes, cameras known by their least-squares matrix (mean / median degrees)\n")
    print("| camera | matrix-derived (shipped) | camera posterior mean |")
    print("|---|---|---|")
    tot = []
    for path in rawtoaces_cameras(every):
        h = json.loads(path.read_text())["header"]
        name = f"{h['manufacturer']} {h['model']}"
        sens = measured_sensitivities(path, wl)
        pair = cameras_for(least_squares_matrix(sens), (name,))
        per = []
        for seed in seeds:
            for light in LIGHTS:
                for layout in LAYOUTS:
                    img, truth = matrix_scene(sens, light, layout, seed)    # chart_scenes' scene, not mosaicked
                    per.append([angular_error(estimate_bayes(img, None, c)[0], truth) for c in pair])
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
