"""Held-out checks of the default estimator (issue 4): data its model did
not see.

``python -m benchmarks.heldout [--scenes 120] [--seed 123]``

1. Lights not in the candidate set: random mixtures of daylights and
   blackbodies (:func:`recovery.illuminant_prior.random_lights`).
2. Surfaces not in the density: the posterior's reflectance density is
   built from the ColorCheckers, TCS and VS only; scenes use the 190
   rawtoaces patches.

Both on 64x64 Mondrians of 8x8-pixel cells synthesised on a 5 nm grid with
the development benchmark's noise (1 % multiplicative, 0.0005 additive),
printed next to the classical peers on the same scenes.
"""

from __future__ import annotations

import argparse

import numpy as np

import models

from recovery import Camera, angular_error, estimate_illuminant
from recovery.bayes import estimate_bayes
from recovery.illuminant_prior import random_lights

PEERS = ("gray-world", "white-patch", "shades-of-gray", "gray-edge")


def _scene(rng, refl, light, cam_name, wl5, k):
    S = models.camera_sensitivities(cam_name, wl5) * models.wavelength_step(wl5)[:, None]
    idx = rng.choice(len(refl), k, replace=False)
    lab = rng.integers(0, k, (8, 8)).repeat(8, 0).repeat(8, 1)
    rgb = (refl[idx] * light) @ S * rng.uniform(0.5, 1.0, k)[:, None]
    img = rgb[lab]
    img = img / img.max() * 0.9
    img = img * (1 + 0.01 * rng.standard_normal(img.shape)) + 0.0005 * rng.standard_normal(img.shape)
    return np.clip(img, 0, 1), light @ S


def run(scenes: int = 120, seed: int = 123) -> dict:
    """Median and 95th percentile angular errors per check and method."""
    wl5 = models.wavelength_grid(400, 700, 5)
    rng = np.random.default_rng(seed)
    out = {}
    # 1. lights outside the candidate set
    spds, _ = random_lights(rng, scenes, wl5)
    refl = models.reflectance_set("all", wl5)
    errs = {m: [] for m in ("auto",) + PEERS}
    for i in range(scenes):
        cam_name = models.camera_names()[i % 3]
        cam = Camera.named(cam_name)
        img, truth = _scene(rng, refl, spds[i], cam_name, wl5, (4, 8, 16, 32)[i % 4])
        for m in errs:
            errs[m].append(float(angular_error(estimate_illuminant(img, cam, m, white_level=1.0).rgb, truth)))
    out["lights not in the candidate set"] = errs
    # 2. surfaces outside the density
    train = np.concatenate([models.reflectance_set(s) for s in ("colorchecker", "colorchecker-ohta", "tcs", "vs")])
    test = models.reflectance_set("rawtoaces-190", wl5)
    lights = models.illuminant_names()
    errs = {m: [] for m in ("bayes (density without the test surfaces)",) + PEERS}
    for i in range(scenes):
        cam_name = models.camera_names()[i % 3]
        cam = Camera.named(cam_name)
        light = models.illuminant(lights[int(rng.integers(len(lights)))], wl5)
        img, truth = _scene(rng, test, light, cam_name, wl5, (4, 8, 16, 32)[i % 4])
        rgb, _, _ = estimate_bayes(img, None, cam, reflectances=train, white_level=1.0)
        errs["bayes (density without the test surfaces)"].append(float(angular_error(rgb, truth)))
        for m in PEERS:
            errs[m].append(float(angular_error(estimate_illuminant(img, cam, m, white_level=1.0).rgb, truth)))
    out["surfaces not in the density"] = errs
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="held-out checks of the default estimator")
    ap.add_argument("--scenes", type=int, default=120)
    ap.add_argument("--seed", type=int, default=123)
    args = ap.parse_args(argv)
    for check, errs in run(args.scenes, args.seed).items():
        print(f"\n{check} ({args.scenes} scenes): angular error in degrees")
        print(f"{'method':45s} {'median':>7s} {'p95':>7s}")
        for m, v in errs.items():
            print(f"{m:45s} {np.median(v):7.2f} {np.percentile(v, 95):7.2f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
