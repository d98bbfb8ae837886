"""Candidate reflectance sets for the surface prior, measured before any is shipped (issue 31).

``python -m benchmarks.surface_candidates [--luxpy-dir DIR] [NAME ...]``

Each candidate is added to the *training* surfaces only; the five shipped
sets (:data:`models.surface_data.SURFACE_SETS`) are left out in turn, strict
(every training surface within 0.02 RMS of a left-out surface removed, the
candidate's too), with the shipped hyper-parameters held fixed
(:data:`recovery.surface_prior.PRIOR_BANDWIDTH` etc.), the true light (D65
and A) and the 6 measured cameras of ``benchmarks.surfaces --cv``: the median
and 90th percentile of the RMSE per surface after one exposure scale per
scene, pooled and per left-out set, against the same run with no candidate.
A screening, not the benchmark: the full protocol (hyper-parameters chosen by
an inner cross-validation, estimated light, bands) with a candidate as a
sixth set is ``python -m benchmarks.surfaces --add-set NAME``.

Candidates (docs/surfaces.md, "Larger reflectance sets" gives what each is
and why none is shipped):

``ces99``
    The 99 colour evaluation samples of CIE 224:2017, as colour-science ships
    them (``colour.quality.cfi2017.load_TCS_CIE2017``; 380-780 nm at 5 nm).
``munsell1269``, ``tm30-2696``, ``cri2012-r210``, ``opstelten215``
    Sets in the luxpy wheel (GPLv3; ``pip download --no-deps luxpy`` and
    unzip it; ``--luxpy-dir`` is its ``luxpy/data/rfls`` folder): the 1269
    matt Munsell chips (University of Joensuu measurements), the 2696 distinct
    spectra of the IES TM-30-15 library of 4880, the 210 real samples of
    CRI2012 (Smet et al. 2013), the 215 test colours of Opstelten (1983). For
    measurement only: the product does not ship them.
``earthlib-measured``
    The 5261 spectra of the earthlib wheel (MIT; ``--earthlib-dir`` is its
    ``earthlib/data`` folder) labelled ``measured`` (4168 soils of the
    ICRAF-ISRIC soil spectral library, 1085 of source ``asd`` (urban
    materials, bark, litter, char), 8 of source ``specevo``; the 2000 PROSAIL
    canopies, simulated, are left out); 400-2450 nm at 10 nm.

References
----------
CIE 224:2017, *CIE 2017 colour fidelity index for accurate scientific use*;
IES TM-30-15 (2015); Smet, Schanda, Whitehead & Luo, Lighting Res. Technol.
45(6) 2013 (CRI2012); Opstelten, CIE 20th session, Amsterdam 1983.
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

from models.surface_data import SURFACE_SETS, camera_set, surface_sets
from recovery import surface_prior as sp

LUXPY_FILES = {"munsell1269": "Munsell1269.dat", "cri2012-r210": "CRI2012_R210.dat",
               "opstelten215": "Opstelten1983_215.dat"}
CANDIDATES = ("ces99", "munsell1269", "tm30-2696", "cri2012-r210", "opstelten215", "earthlib-measured")


def _earthlib(d: Path):
    import csv
    import re

    hdr = (d / "spectra.sli.hdr").read_text()
    w = 1000.0 * np.array([float(x) for x in re.search(r"wavelength = \{([^}]*)\}", hdr).group(1).split(",")])
    lines = int(re.search(r"lines = (\d+)", hdr).group(1))
    a = np.fromfile(d / "spectra.sli", dtype="<f4").reshape(lines, w.size)
    with open(d / "spectra.csv", newline="") as f:
        measured = np.array([r["LEVEL_4"] == "measured" for r in csv.DictReader(f)])
    return w, a[measured]


def candidate(name: str, wavelengths, luxpy_dir=None, earthlib_dir=None) -> np.ndarray:
    """Reflectances ``(M, N)`` of candidate set ``name`` on ``wavelengths`` (linear interpolation)."""
    wl = np.asarray(wavelengths, float)
    if name == "ces99":
        import colour
        from colour.quality.cfi2017 import load_TCS_CIE2017

        m = load_TCS_CIE2017(colour.SpectralShape(380, 780, 5))
        return np.stack([np.interp(wl, m.wavelengths, c) for c in m.values.T])
    if name not in CANDIDATES:
        raise KeyError(f"unknown candidate {name!r}; accepted: {list(CANDIDATES)}")
    if name == "earthlib-measured":
        if earthlib_dir is None:
            raise ValueError("earthlib-measured is read from the earthlib wheel: give --earthlib-dir")
        w, rows = _earthlib(Path(earthlib_dir))
        if wl.min() < w.min():
            raise ValueError(f"earthlib starts at {w.min():.0f} nm, the grid at {wl.min():.0f} nm")
        return np.clip(np.stack([np.interp(wl, w, r) for r in rows]), 0.0, None)
    if luxpy_dir is None:
        raise ValueError(f"{name} is read from the luxpy wheel: give --luxpy-dir (its luxpy/data/rfls folder)")
    d = Path(luxpy_dir)
    if name == "tm30-2696":
        a = np.load(d / "IESTM30_15_R4880.npz")["_IESTM30_R4880"]          # row 0: wavelengths
        idx = np.loadtxt(d / "IESTM30-R4880-subset-with-unique-rfls--2696.dat", delimiter=",")
        idx = np.asarray(idx if idx.ndim == 1 else idx[:, 0], int)
        w, rows = a[0], a[1:][idx]
    else:
        a = np.loadtxt(d / LUXPY_FILES[name], delimiter=",")              # column 0: wavelengths
        w, rows = a[:, 0], a[:, 1:].T
    return np.clip(np.stack([np.interp(wl, w, r) for r in rows]), 0.0, None)


def screen(extra: np.ndarray, wl, cams, lights, hyper) -> dict:
    """RMSE per surface of the five shipped sets left out in turn (strict), ``extra`` in training."""
    from benchmarks.surfaces import dedup, rms, scene_scale

    dl = float(np.diff(wl).mean())
    R, lab = surface_sets(wl)
    out = {}
    for test in SURFACE_SETS:
        T = R[lab == test]
        tr = np.concatenate([R[lab != test], extra])
        tr, _ = dedup(tr, np.zeros(len(tr)), T, True)
        prior = sp.learn_prior(tr, wl, **hyper)
        e = []
        for S in cams:
            for E in lights:
                rho = T @ sp.lighting_operator(S, E, dl).T
                est = sp.surface_estimates(prior, rho, S, E, dl)
                e.append(rms(scene_scale(est.mean, T) * est.mean, T))
        out[test] = np.concatenate(e)
    return out


def main(argv=None) -> None:
    from benchmarks.surfaces import WL, light

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help=f"candidates (default: all of {', '.join(CANDIDATES)} that can be read)")
    ap.add_argument("--luxpy-dir", help="the luxpy wheel's luxpy/data/rfls folder")
    ap.add_argument("--earthlib-dir", help="the earthlib wheel's earthlib/data folder")
    args = ap.parse_args(argv)
    names = args.names or [n for n in CANDIDATES if n == "ces99" or (args.luxpy_dir and n in LUXPY_FILES)
                           or (args.luxpy_dir and n == "tm30-2696") or (args.earthlib_dir and n == "earthlib-measured")]
    t0 = time.perf_counter()
    _, all_cams = camera_set(WL)
    cams = [all_cams[i] for i in range(2, 47, 8)]
    lights = [light("D65"), light("A")]
    hyper = {"bandwidth": sp.PRIOR_BANDWIDTH, "noise": sp.PRIOR_NOISE, "shrinkage": sp.PRIOR_SHRINKAGE,
             "length_nm": sp.PRIOR_LENGTH_NM}
    print(f"load average at start: {os.getloadavg()}; fixed hyper-parameters {hyper}; true light (D65, A); "
          f"6 measured cameras; the five shipped sets left out in turn, strict")
    print("| added to training | surfaces | median RMSE | p90 | " + " | ".join(SURFACE_SETS) + " |")
    print("|---|---|---|---|" + "---|" * len(SURFACE_SETS))
    for name in ["none"] + names:
        try:
            X = np.zeros((0, WL.size)) if name == "none" else candidate(name, WL, args.luxpy_dir, args.earthlib_dir)
        except (KeyError, ValueError, OSError) as e:
            ap.error(str(e))
        out = screen(X, WL, cams, lights, hyper)
        pooled = np.concatenate(list(out.values()))
        print(f"| {name} | {len(X)} | {np.median(pooled):.4f} | {np.percentile(pooled, 90):.4f} | "
              + " | ".join(f"{np.median(out[s]):.4f}" for s in SURFACE_SETS) + " |", flush=True)
    print(f"took {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
