"""Which kind of spectrum ``method="bayes"`` reports on real photographs
(issue 19 item 5): daylight or Planckian unless the evidence says otherwise.

A fixed subsample of the development photographs (``--per-camera`` images
of each camera, seed ``--seed``) is run through the light posterior
(:func:`recovery.bayes.estimate_bayes` on the product's usable pixels,
camera described by its colour matrix, as ``estimate_illuminant(...,
method="bayes")`` runs it). The images are split by the measured light's
distance from the Planckian locus, ``Duv`` in CIE 1960 uv (Ohno 2013), the
light taken to XYZ through the inverse of the camera's XYZ -> camera matrix:
``|Duv| < 0.01`` is "near the locus" (daylight and Planckian lights are
within about 0.005).

Prints, per split: how often each spectrum family is reported, the mean
posterior mass of each kind of light, and how often a spiky kind holds most
of the posterior mass. Then a synthetic check: Mondrians under real
fluorescent lamps (CIE FL2, FL11 and others) seen by cameras with measured
spectral sensitivities, and how often fluorescent is reported.

Usage::

    python -m benchmarks.bayes_spectra [--per-camera 30] [--seed 0] [--synthetic 12] [--out out]
"""

from __future__ import annotations

import argparse
import json
import time
from collections import Counter
from pathlib import Path

import numpy as np

from .realdata import load_real, usable_mask

KINDS = ("daylight", "planckian", "fluorescent", "LED", "high-pressure", "narrowband", "other")


def true_duv(rgb: np.ndarray, matrix: np.ndarray) -> float:
    """Duv (CIE 1960 uv, Ohno 2013) of a camera-RGB light through the
    inverse of the camera's XYZ -> camera matrix."""
    import colour

    xyz = np.linalg.solve(np.asarray(matrix, float), np.asarray(rgb, float))
    uv = colour.UCS_to_uv(colour.XYZ_to_UCS(xyz))
    return float(colour.temperature.uv_to_CCT_Ohno2013(uv)[1])


def kind_masses(cands, post: np.ndarray) -> dict:
    """Posterior mass per kind of light (mixtures shared by power fraction)."""
    from recovery.illuminant_prior import light_kinds

    out = dict.fromkeys(KINDS, 0.0)
    for i, (n, f) in enumerate(zip(cands.names, cands.families)):
        for k, s in light_kinds(n, f):
            out[k] = out.get(k, 0.0) + float(post[i]) * s
    return out


def posterior_from(diag: dict) -> np.ndarray:
    """The posterior over the candidates, from ``keep_likelihood`` arrays."""
    lp = diag["log_prior"] + diag["log_likelihood_chroma"]
    ll = diag["log_likelihood_lightness"]
    if np.isfinite(ll).any():
        lp = np.where(np.isfinite(ll), lp + np.nan_to_num(ll), -np.inf)
    p = np.exp(lp - lp.max())
    return p / p.sum()


def run_one(img, cam, cands):
    from recovery.bayes import estimate_bayes

    m = usable_mask(img)
    rgb, spd, d = estimate_bayes(np.where(m[..., None], img, 0), m, cam, keep_likelihood=True)
    if d.get("method") != "bayes":
        return None
    return d, kind_masses(cands, posterior_from(d))


def table(rows, title):
    print(f"\n{title}")
    print(f"{'split':24s} {'n':>4s}  reported family (%)                         mean posterior mass (%)")
    print(f"{'':24s} {'':4s}  {'dayl':>5s} {'planck':>6s} {'fluor':>5s} {'other':>5s}   "
          f"{'dayl':>5s} {'planck':>6s} {'fluor':>5s} {'LED':>5s} {'rest':>5s}  spiky>50%  | by mass: smooth "
          f"fluor | evidence: log ratio, 10 colours (nats) p50 p90")
    for name, sel in rows:
        if not sel:
            continue
        n = len(sel)
        fam = Counter(r["family"] for r in sel)
        mm = {k: np.mean([r["mass"][k] for r in sel]) for k in KINDS}
        rest = sum(mm[k] for k in ("high-pressure", "narrowband", "other"))
        spiky = np.mean([sum(v for k, v in r["mass"].items() if k not in ("daylight", "planckian")) > 0.5
                         for r in sel])
        other = n - fam["daylight"] - fam["planckian"] - fam["fluorescent"]
        print(f"{name:24s} {n:4d}  {100 * fam['daylight'] / n:5.0f} {100 * fam['planckian'] / n:6.0f} "
              f"{100 * fam['fluorescent'] / n:5.0f} {100 * other / n:5.0f}   {100 * mm['daylight']:5.0f} "
              f"{100 * mm['planckian']:6.0f} {100 * mm['fluorescent']:5.0f} {100 * mm['LED']:5.0f} "
              f"{100 * rest:5.0f}  {100 * spiky:6.0f}     | "
              f"{100 * np.mean([r['by_mass'] in ('daylight', 'planckian') for r in sel]):13.0f} "
              f"{100 * np.mean([r['by_mass'] == 'fluorescent' for r in sel]):5.0f} | "
              + " ".join(f"{v:5.1f}" for key in ("ratio", "colours") for v in np.nanpercentile(
                  [np.nan if r[key] is None else r[key] for r in sel] + [np.nan], [50, 90])))
    rules = Counter(r["rule"].split(":")[0].split(";")[0][:60] for _, sel in rows[:1] for r in sel)
    for k, v in rules.most_common(4):
        print(f"   rule x{v}: {k}")


def real(per_camera: int, seed: int):
    from recovery.cameras import camera_from_matrix
    from recovery.illuminant_prior import default_candidates

    rs = load_real()
    rng = np.random.default_rng(seed)
    idx = np.concatenate([np.sort(rng.choice(np.flatnonzero(rs.camera == c), size=min(per_camera,
                          int(np.sum(rs.camera == c))), replace=False)) for c in rs.cameras])
    cams, out = {}, []
    t0 = time.perf_counter()
    for i in idx:
        c = rs.camera[i]
        if c not in cams:
            cams[c] = camera_from_matrix(rs.matrices[c]).with_color_matrix(rs.matrices[c])
        cam = cams[c]
        cands = default_candidates(cam.wavelengths)
        r = run_one(rs.images[i].astype(float), cam, cands)
        if r is None:
            continue
        d, mass = r
        out.append({"i": int(i), "camera": c, "duv": true_duv(rs.truth[i], rs.matrices[c]),
                    "family": d["spectrum_family"], "rule": d["spectrum_rule"], "mass": mass,
                    "by_mass": d.get("spectrum_family_by_mass", d["spectrum_family"]),
                    "ratio": d.get("spectrum_kind_log_ratio"), "colours": d.get("spectrum_kind_colours_nats")})
    near = [r for r in out if abs(r["duv"]) < 0.01]
    far = [r for r in out if abs(r["duv"]) >= 0.01]
    table([("all", out), ("|Duv| < 0.01 (near)", near), ("|Duv| >= 0.01 (off)", far)],
          f"Real photographs: {per_camera} per camera, seed {seed}, {len(out)} images "
          f"({time.perf_counter() - t0:.0f} s)")
    cam_rows = [(c[:24], [r for r in near if r["camera"] == c]) for c in rs.cameras]
    table(cam_rows, "Near the locus, per camera")
    return out


LAMPS = ("FL2", "FL11", "FL4", "FL10", "FL3.3", "FL7", "FL1", "FL8")
SMOOTH = ("D65", "D50", "A", "D75")


def synthetic(n: int, seed: int = 0):
    from recovery import Camera
    from recovery.illuminant_prior import default_candidates
    from testing.scenes import mondrian_scene

    rows = []
    for cam_name in ("Nikon 5100 (NPL)", "Canon EOS 5D Mark II"):
        try:
            cam = Camera.named(cam_name)
        except Exception:
            continue
        cands = default_candidates(cam.wavelengths)
        for light in LAMPS + SMOOTH:
            for k in range(n):
                sc = mondrian_scene(np.random.default_rng(seed + k), 24, cam_name, light, 64)
                from recovery.bayes import estimate_bayes

                rgb, spd, d = estimate_bayes(sc.image, None, cam, keep_likelihood=True)
                rows.append({"light": light, "camera": cam_name, "family": d["spectrum_family"],
                             "rule": d["spectrum_rule"], "mass": kind_masses(cands, posterior_from(d)),
                             "by_mass": d.get("spectrum_family_by_mass", d["spectrum_family"]),
                             "ratio": d.get("spectrum_kind_log_ratio"), "colours": d.get("spectrum_kind_colours_nats")})
    table([(f"under {lt}", [r for r in rows if r["light"] == lt]) for lt in LAMPS + SMOOTH],
          f"Synthetic Mondrians (24 surfaces, {n} scenes per light and camera)")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-camera", type=int, default=30)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--synthetic", type=int, default=12, help="scenes per light and camera (0: none)")
    ap.add_argument("--out", default="out")
    a = ap.parse_args(argv)
    rows = {}
    if a.per_camera > 0:
        rows["real"] = real(a.per_camera, a.seed)
    if a.synthetic > 0:
        rows["synthetic"] = synthetic(a.synthetic, a.seed)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "bayes_spectra.json").write_text(json.dumps(rows, indent=0, default=float))
    print(f"wrote {out / 'bayes_spectra.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
