"""Measured reflectance sets and measured cameras for the surface prior (issue 31).

Two shipped files, built by ``python -m benchmarks.build_prior_data`` (which
records their provenance):

* ``data/surface_sets.npz``: 274 measured reflectances in five sets that
  colour-science ships (the BabelColor average of the ColorChecker, the 190
  rawtoaces training patches, the CIE test colour samples (CIE 2024 edition, 15),
  the NIST CQS 9.0 samples (15), the preferred-memory-colour chart PMC of
  Luo 2024 (30: skin, food, sky, foliage, greys));
* ``data/camera_set_rawtoaces.npz``: 47 cameras' measured R, G, B
  sensitivities (Academy Software Foundation ``rawtoaces-data``, Apache-2.0,
  ``data/camera_set_rawtoaces.LICENSE``).

A third, derived file, ``data/surface_band_scale.json``, holds the factors
per wavelength that calibrate the bands of the surface prior (written by
``python -m benchmarks.surfaces --write-calibration`` from leave-one-set-out
errors; read by :func:`band_calibration`).

Both are stored on 380-780 nm at 5 nm and linearly interpolated to the grid
asked for (smooth data: at 10 nm the interpolation error is below 1e-3).

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 11-12 and Fig. 5 (linear
models fitted to measured surfaces; the camera's sensor functions).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from .grid import DEFAULT_WAVELENGTHS

__all__ = ["SURFACE_SETS", "surface_sets", "camera_set", "band_calibration"]

_DATA = Path(__file__).resolve().parent / "data"

#: The reflectance sets of ``surface_sets.npz`` (the names the prior's
#: cross-validation leaves out in turn).
SURFACE_SETS = ("colorchecker", "rawtoaces-190", "tcs", "vs", "pmc")


@functools.lru_cache(maxsize=4)
def _npz(name: str) -> dict:
    with np.load(_DATA / name) as z:
        return {k: z[k] for k in z.files}


def _on(wl_src, values, wavelengths) -> np.ndarray:
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    v = np.asarray(values, float)
    flat = v.reshape(-1, v.shape[-1]) if v.ndim > 1 else v[None]
    out = np.stack([np.interp(wl, np.asarray(wl_src, float), row) for row in flat])
    return out.reshape(v.shape[:-1] + (wl.size,)) if v.ndim > 1 else out[0]


def surface_sets(wavelengths=None, sets=None) -> tuple[np.ndarray, np.ndarray]:
    """Measured reflectances ``(M, N)`` on ``wavelengths`` and their set labels ``(M,)``.

    Parameters
    ----------
    wavelengths : array_like, optional
        Default 400-700 nm at 10 nm.
    sets : iterable of str, optional
        Keep only these sets (names from :data:`SURFACE_SETS`).

    Examples
    --------
    >>> R, lab = surface_sets()
    >>> R.shape, sorted(set(lab)) == sorted(SURFACE_SETS)
    ((274, 31), True)
    """
    d = _npz("surface_sets.npz")
    lab = d["set"].astype(str)
    keep = np.ones(lab.size, bool) if sets is None else np.isin(lab, list(sets))
    unknown = set(sets or ()) - set(SURFACE_SETS)
    if unknown:
        raise KeyError(f"unknown reflectance set(s) {sorted(unknown)}; accepted: {list(SURFACE_SETS)}")
    return _on(d["wavelengths"], d["reflectances"][keep], wavelengths), lab[keep]


def camera_set(wavelengths=None) -> tuple[list[str], np.ndarray]:
    """The 47 measured cameras: names and sensitivities ``(K, N, 3)`` on ``wavelengths``.

    Each camera keeps its measured channel balance, scaled so its largest
    value on the 5 nm grid is 1.

    Examples
    --------
    >>> names, S = camera_set()
    >>> len(names), S.shape
    (47, (47, 31, 3))
    """
    d = _npz("camera_set_rawtoaces.npz")
    sens = np.swapaxes(d["sensitivities"], 1, 2)                  # (K, 3, N5)
    return [str(n) for n in d["names"]], np.swapaxes(_on(d["wavelengths"], sens, wavelengths), 1, 2)


@functools.lru_cache(maxsize=1)
def _calibration_file() -> dict | None:
    import json

    f = _DATA / "surface_band_scale.json"
    return json.loads(f.read_text()) if f.exists() else None


def band_calibration(wavelengths=None) -> dict:
    """Band calibration factors of the surface prior, per camera kind and light.

    Returns
    -------
    dict
        ``{"level": 0.9, "z": 1.645, "scale": {"measured/estimated": (N,), ...},
        "provenance": str}``: the posterior standard deviation times
        ``scale[kind/light]`` at each wavelength makes ``mean +- z std`` hold the
        truth at ``level`` on reflectance sets left out (``kind`` one of
        ``measured``, ``matrix``, ``generic``; ``light`` ``true`` or
        ``estimated``). Interpolated linearly to ``wavelengths`` (held constant
        beyond the stored range). Empty ``scale`` when the file is absent.

    Examples
    --------
    >>> sorted(band_calibration()["scale"])[:2]
    ['generic/estimated', 'generic/true']
    """
    d = _calibration_file()
    if d is None:
        return {"level": 0.9, "z": 1.6448536269514722, "scale": {}, "provenance": "none (file absent)"}
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    src = np.asarray(d["wavelengths"], float)
    return {"level": float(d["level"]), "z": float(d["z"]), "provenance": d["provenance"],
            "scale": {k: np.interp(wl, src, np.asarray(v, float)) for k, v in d["scale"].items()}}
