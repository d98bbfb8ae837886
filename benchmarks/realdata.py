"""The development photographs with measured lights (``../shared/data/real``):
loading, the usable-pixel mask, the per-camera colour matrices, the error
statistics of the colour-constancy literature.

Not part of the product: the photographs are for development and tests
only and are not shipped (their README).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recovery.api import angular_error

__all__ = ["REAL_DIR", "RealSet", "load_real", "usable_mask", "error_stats", "angular_error"]

REAL_DIR = Path(os.environ.get("WANDELL_REAL_DATA", Path(__file__).resolve().parents[1].parent / "shared" / "data" / "real"))

#: values at or above this fraction of 1 are saturated (the data's README)
SATURATED = 0.98


@dataclass
class RealSet:
    images: np.ndarray        # (N, 64, 64, 3) float32 linear camera RGB, max 1
    truth: np.ndarray         # (N, 3) measured light, camera RGB, sum 1
    camera: np.ndarray        # (N,) model name
    name: np.ndarray          # (N,) image name
    matrices: dict            # model -> (3, 3) XYZ -> camera (D65)
    dataset: np.ndarray = None  # (N,) benchmark of each image ("NUS 8-camera", "Cube+", "INTEL-TAU field")

    @property
    def cameras(self) -> list[str]:
        return sorted(set(self.camera.tolist()))


    @property
    def datasets(self) -> list[str]:
        return [k for k in BENCHMARKS if k in set(self.dataset.tolist())]

    def subset(self, sel) -> "RealSet":
        return RealSet(self.images[sel], self.truth[sel], self.camera[sel], self.name[sel], self.matrices,
                       self.dataset[sel])


#: benchmark -> file (the data's README)
BENCHMARKS = {"NUS 8-camera": "nus8.npz", "Cube+": "cubeplus.npz", "INTEL-TAU field": "tau_field.npz"}


def load_real(directory=None, benchmarks=None) -> RealSet:
    """The development benchmarks (default all three present: NUS 8-camera,
    Cube+, INTEL-TAU field) as one set, each image labelled with its
    benchmark."""
    d = Path(directory) if directory else REAL_DIR
    names = [b for b in (benchmarks or BENCHMARKS) if benchmarks or (d / BENCHMARKS[b]).is_file()]
    parts = [np.load(d / BENCHMARKS[b]) for b in names]
    mats = json.loads((d / "cameras.json").read_text())
    return RealSet(np.concatenate([p["images"] for p in parts]).astype(np.float32) / 65535.0,
                   np.concatenate([p["illuminant_rgb"] for p in parts]).astype(float),
                   np.concatenate([p["camera"] for p in parts]).astype(str),
                   np.concatenate([p["name"] for p in parts]).astype(str),
                   {k: np.asarray(v["xyz_to_camera_D65"], float) for k, v in mats.items()},
                   np.concatenate([np.full(len(p["camera"]), b) for b, p in zip(names, parts)]))


#: a channel at or below this fraction of the image maximum is dark (the
#: product's own rule, ``recovery.api`` ``dark_fraction``)
DARK = 1e-3


def usable_mask(image: np.ndarray) -> np.ndarray:
    """The pixels the product's estimation uses on such an image
    (``estimate_illuminant(image, camera, white_level=1.0)``): no channel
    saturated (>= 0.98, the data's README) and no channel dark (<= 1e-3 of
    the maximum; this also leaves out the calibration target, zeroed in
    the thumbnails)."""
    top = float(image.max()) if image.size else 0.0
    return ~(np.any(image >= SATURATED, axis=-1) | np.any(image <= DARK * top, axis=-1))


def error_stats(err) -> dict:
    """Mean, median, trimean, best 25 %, worst 25 %, 95th percentile (the
    statistics of Hordley & Finlayson 2006 used by the colour-constancy
    literature)."""
    e = np.sort(np.asarray(err, float))
    q1, q2, q3 = np.percentile(e, [25, 50, 75])
    k = max(1, int(round(0.25 * e.size)))
    return {"mean": float(e.mean()), "median": float(q2), "trimean": float((q1 + 2 * q2 + q3) / 4),
            "best25": float(e[:k].mean()), "worst25": float(e[-k:].mean()), "p95": float(np.percentile(e, 95)),
            "n": int(e.size)}
