"""Drew and Finlayson's comparisons reproduced: metamers, products, bounces.

``python -m benchmarks.sharpening`` prints, for the sharpened bases of
:mod:`models.sharpening` (Drew and Finlayson 2003 [docs/references.md#seed-003]):
the metameric mismatch under A of ColorChecker surfaces and their smooth
metamers for D65, with full spectra, sharpened bases of 3-9 functions and
three-channel (RGB, XYZ) von Kries rendering (their Fig. 5 and Table 4);
the spectral error of products of spectra as products of coefficients
(Table 3); and the CIEDE2000 of light accumulated over 1-5 bounces (Table
1). The metamer generator and the mismatch measure are here because only
the comparison uses them.
"""

from __future__ import annotations

import numpy as np

from models.grid import DEFAULT_WAVELENGTHS, wavelength_step
from models.illuminants import illuminant, illuminants
from models.observers import observer
from models.reflectances import reflectance_set
from models.sharpening import (DEFAULT_TRAINING_LIGHTS, multibounce, pca_product_rule, product_errors,
                               sharpened_rule)
from models.spectral_rule import SpectralRule

__all__ = ["metameric_pairs", "metamer_mismatch", "lab", "xyz_errors", "comparison", "main"]


def metameric_pairs(reflectances, light, cmfs, wavelengths=None, per_surface: int = 3,
                    order: int = 4, fill: float = 0.9, rng=None, basis=None) -> np.ndarray:
    """Pairs of reflectances with equal tristimulus values under ``light``.

    For each reflectance ``r`` a smooth metameric black ``b`` is built: a
    random Fourier series of ``order`` harmonics over the grid, projected on
    the null space of ``M = (cmfs * light * dlambda)^T`` (Wyszecki and
    Stiles' metameric blacks; Drew and Funt 1992, "Natural metamers", in
    Drew and Finlayson 2003's references; their Fig. 3 shows such pairs).
    The partner ``r + a b`` uses ``a`` = ``fill`` times the largest
    amplitude keeping it in [0, 1], so it is a physical reflectance matching
    ``r`` exactly under ``light``.

    Parameters
    ----------
    reflectances : ndarray, shape (M, N)
    light : ndarray, shape (N,)
        The light under which the pairs match.
    cmfs : ndarray, shape (N, 3)
    per_surface : int
        Metamers per reflectance.
    order, fill, rng
        Harmonics of the random series, share of the largest amplitude,
        random generator (default seed 0).
    basis : ndarray, shape (N, K), optional
        Draw the black from this span instead (e.g. a reflectance PCA, for
        "natural" metamers in Drew and Funt's sense).

    Returns
    -------
    ndarray, shape (P, 2, N)
        ``[:, 0]`` the original, ``[:, 1]`` its metamer.
    """
    refl = np.atleast_2d(np.asarray(reflectances, dtype=float))
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, dtype=float)
    rng = np.random.default_rng(0) if rng is None else rng
    M = (np.asarray(cmfs, float) * (np.asarray(light, float) * wavelength_step(wl))[:, None]).T
    x = (wl - wl[0]) / (wl[-1] - wl[0])
    if basis is None:
        F = np.stack([np.ones_like(x)] + [f(np.pi * k * x) for k in range(1, order + 1)
                                         for f in (np.sin, np.cos)], axis=1)
    else:
        F = np.asarray(basis, dtype=float)
    gram = M @ M.T
    out = []
    for r in refl:
        for _ in range(int(per_surface)):
            f = F @ rng.normal(size=F.shape[1])
            b = f - M.T @ np.linalg.solve(gram, M @ f)
            with np.errstate(divide="ignore", invalid="ignore"):
                up = np.where(b > 0, (1.0 - r) / b, np.inf)
                down = np.where(b < 0, -r / b, np.inf)
            a = fill * max(0.0, min(up.min(), down.min()))
            out.append((r, np.clip(r + a * b, 0.0, 1.0)))
    return np.asarray(out)


def lab(xyz, white):
    import colour

    return colour.XYZ_to_Lab(xyz / white[1], colour.XYZ_to_xy(white))


def metamer_mismatch(pairs, light, cmfs, rule: SpectralRule | None = None, wavelengths=None,
                     reference_light=None) -> np.ndarray:
    """CIEDE2000 between the two members of each pair under ``light``.

    ``rule=None``: the full-spectrum calculation, ``T = sum E S xbar dl``.
    A multiplicative rule: the coefficient products, ``T = (e * s) @ W``
    (:meth:`SpectralRule.tristimulus_matrix`; eq. 28-29, ``b = R^T Q~^+ c``). ``rule="rgb"``: three-channel
    rendering, the tristimulus values under ``reference_light`` taken to
    linear sRGB and relit by the diagonal von Kries map of the two whites
    (the "standard three-component graphics" of the paper's Fig. 5);
    ``rule="xyz"``: the same diagonal map applied to XYZ. CIELAB is always
    relative to the full-spectrum white of ``light``.

    Returns
    -------
    ndarray, shape (P,)
    """
    import colour

    pairs = np.asarray(pairs, dtype=float)
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, dtype=float)
    dl = wavelength_step(wl)
    cmfs = np.asarray(cmfs, dtype=float)
    light = np.asarray(light, dtype=float)
    white = (light * dl) @ cmfs
    if rule is None:
        xyz = (pairs * light * dl) @ cmfs
    elif isinstance(rule, str):
        if rule not in ("rgb", "xyz"):
            raise ValueError(f"rule must be None, a SpectralRule, 'rgb' or 'xyz', not {rule!r}")
        if reference_light is None:
            raise ValueError("three-channel rendering needs the reference_light the pairs are "
                             "seen under first")
        ref = np.asarray(reference_light, dtype=float)
        m = (colour.models.RGB_COLOURSPACE_sRGB.matrix_XYZ_to_RGB if rule == "rgb"
             else np.eye(3))
        rgb = ((pairs * ref * dl) @ cmfs) @ m.T
        gain = (white @ m.T) / (((ref * dl) @ cmfs) @ m.T)
        xyz = (rgb * gain) @ np.linalg.inv(m).T
    else:
        xyz = rule.coefficients(pairs) @ rule.tristimulus_matrix(light, cmfs)
    return np.asarray(colour.delta_E(lab(xyz[:, 0], white), lab(xyz[:, 1], white),
                                     method="CIE 2000"), dtype=float)


def xyz_errors(rule, lights, reflectances, cmfs, wl, bounces=1, accumulate=False, best=False):
    """CIEDE2000 of the colour signal ``E R^k`` (or accumulated over bounces)
    against the full spectrum, relative to the full white of each light: from
    coefficient products (the paper's "spectral factor model"), or with
    ``best`` from the exact signal projected on the rule's span (its "best
    least squares" approximation, Fig. 2 and Table 1; CIEDE2000 here where
    the paper uses CIELAB).
    """
    import colour

    dl = wavelength_step(wl)
    ks = list(range(1, bounces + 1)) if accumulate else [bounces]
    out = []
    for e in np.atleast_2d(lights):
        white = (e * dl) @ cmfs
        signal = sum(e * reflectances**k for k in ks)
        true = (signal * dl) @ cmfs
        if best:
            c = rule.coefficients(signal)
        else:
            c = multibounce(reflectances, e, bounces, rule, accumulate)
        est = c @ rule.integration_weights(cmfs)
        out.append(colour.delta_E(lab(est, white), lab(true, white), method="CIE 2000"))
    return np.concatenate(out)


def comparison(ns=(3, 4, 5, 6, 7, 8, 9), per_surface: int = 3, seed: int = 1,
               table1_ns=(5, 7, 9), positive_ns=(7, 9)) -> dict:
    """The numbers :func:`main` prints (the tests check the main ones).

    Training: :data:`DEFAULT_TRAINING_LIGHTS` and the reflectance sets other
    than the ColorChecker (rawtoaces 190, CIE TCS, CQS VS); test: the two
    ColorChecker sets (48 surfaces), each with ``per_surface`` metamers for
    D65 under the CIE 1931 observer (:func:`metameric_pairs`).

    Returns a dict: ``full`` (mismatch under A of every pair, full
    spectrum), ``mismatch`` (method -> (mismatch, deviation from full,
    rule or None)), ``products`` (n -> spectral errors of the sharpened and
    the unsharpened diagonal models and the projection floor), ``table1``
    (n -> median CIEDE2000 over 1..5 accumulated bounces, best
    approximation and diagonal model).
    """
    wl = DEFAULT_WAVELENGTHS
    cmfs = np.asarray(observer("CIE 1931 2 Degree Standard Observer", wl))
    d65, a = illuminant("D65", wl), illuminant("A", wl)
    lights = illuminants(DEFAULT_TRAINING_LIGHTS, wl)
    train = np.concatenate([reflectance_set(s, wl) for s in ("rawtoaces-190", "tcs", "vs")])
    test = np.concatenate([reflectance_set(s, wl) for s in ("colorchecker", "colorchecker-ohta")])
    training = (lights, train)
    pairs = metameric_pairs(test, d65, cmfs, wl, per_surface=per_surface,
                            rng=np.random.default_rng(seed))
    full = metamer_mismatch(pairs, a, cmfs, None, wl)
    mismatch = {}
    for label, name in (("rgb", "sRGB von Kries"), ("xyz", "XYZ von Kries")):
        m = metamer_mismatch(pairs, a, cmfs, label, wl, reference_light=d65)
        mismatch[name] = (m, np.abs(m - full), None)
    rules = {}
    for n in ns:
        rules[n] = rule = sharpened_rule(n, wl, training=training)
        m = metamer_mismatch(pairs, a, cmfs, rule, wl)
        mismatch[f"sharpened n={n}"] = (m, np.abs(m - full), rule)
    # the paper's Table 4 setting: a basis specialised to the two lights and the metamers
    special = sharpened_rule(7, wl, training=(np.stack([d65, a]), pairs.reshape(-1, wl.size)),
                             bounces=1)
    m = metamer_mismatch(pairs, a, cmfs, special, wl)
    mismatch["specialised n=7"] = (m, np.abs(m - full), special)
    for n in positive_ns:
        rule = sharpened_rule(n, wl, training=training, positive=True)
        m = metamer_mismatch(pairs, a, cmfs, rule, wl)
        mismatch[f"positive n={n}"] = (m, np.abs(m - full), rule)
    products = {}
    true = (lights[:, None, :] * test[None]).reshape(-1, wl.size)
    for n, rule in rules.items():
        pca = pca_product_rule(n, wl, training=training)
        floor = (np.linalg.norm(rule.reconstruct(rule.coefficients(true)) - true, axis=1)
                 / np.linalg.norm(true, axis=1))
        products[n] = {
            "sharpened": [product_errors(rule, lights, test, k) for k in (1, 2, 3)],
            "pca": [product_errors(pca, lights, test, k) for k in (1, 2)],
            "projection": floor,
            "dE_sharpened": xyz_errors(rule, lights, test, cmfs, wl, 1),
            "dE_pca": xyz_errors(pca, lights, test, cmfs, wl, 1),
        }
    table1 = {}
    for n in table1_ns:
        rule = rules.get(n) or sharpened_rule(n, wl, training=training)
        table1[n] = {kind: [float(np.median(xyz_errors(rule, lights, test, cmfs, wl, k, True,
                                                         kind == "best")))
                            for k in range(1, 6)] for kind in ("best", "diagonal")}
    return {"pairs": pairs, "full": full, "mismatch": mismatch, "products": products,
            "table1": table1}


def main(argv=None) -> int:
    """``python -m benchmarks.sharpening``: print the comparisons of
    :func:`comparison` (metameric mismatch under A, product errors)."""
    import argparse
    import time

    parser = argparse.ArgumentParser(prog="python -m benchmarks.sharpening", description=main.__doc__)
    parser.add_argument("--per-surface", type=int, default=3, help="metamers per test surface")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    res = comparison(per_surface=args.per_surface, seed=args.seed)
    full = res["full"]
    print("Drew & Finlayson (2003) spectral sharpening, 400-700 nm at 10 nm, CIE 1931 observer.")
    print("Bases trained on the smooth CIE lights and the rawtoaces/TCS/VS reflectances; tested on")
    print(f"the 48 ColorChecker surfaces, each with {args.per_surface} smooth metamers for D65 "
          f"({len(full)} pairs, seed {args.seed}).")
    print(f"Full-spectrum mismatch of the pairs under A (CIEDE2000): median {np.median(full):.2f}, "
          f"p10 {np.percentile(full, 10):.2f}, p90 {np.percentile(full, 90):.2f}")
    print()
    print("1. Metameric mismatch under A: |mismatch(method) - mismatch(full spectrum)|, CIEDE2000")
    print(f"   {'method':<18}{'median':>8}{'p90':>8}{'max':>8}{'<= 1':>7}{'mismatch':>10}{'cond(T)':>9}")
    for name, (m, d, rule) in res["mismatch"].items():
        cond = f"{rule.diagnostics['condition_transform']:9.2f}" if rule is not None else f"{'-':>9}"
        print(f"   {name:<18}{np.median(d):8.2f}{np.percentile(d, 90):8.2f}{d.max():8.2f}"
              f"{np.mean(d <= 1):7.0%}{np.median(m):10.2f}{cond}")
    print("   (mismatch: median over pairs; a 3-channel diagonal sees only the equal D65 XYZ, "
          "so its pairs stay matched;")
    print("   positive: sharp functions kept >= 0, eq. 14; specialised: trained on D65, A and the "
          "pairs themselves, as the paper's Table 4)")
    print()
    print("2. Products E*R^k, ColorChecker x training lights: median relative RMS spectral error")
    print(f"   {'n':>3}{'sharp k=1':>11}{'k=2':>8}{'k=3':>8}{'PCA-diag k=1':>14}{'k=2':>8}"
          f"{'projection':>12}{'dE00 sharp':>12}{'dE00 PCA':>10}")
    for n, p in res["products"].items():
        s, q = [np.median(x) for x in p["sharpened"]], [np.median(x) for x in p["pca"]]
        print(f"   {n:>3}{s[0]:11.4f}{s[1]:8.4f}{s[2]:8.4f}{q[0]:14.4f}{q[1]:8.4f}"
              f"{np.median(p['projection']):12.4f}{np.median(p['dE_sharpened']):12.3f}"
              f"{np.median(p['dE_pca']):10.3f}")
    print("   (PCA-diag: the same span unsharpened with the same diagonal model; projection: the")
    print("   exact E*R projected on the span, the best its n coefficients allow; dE00: k = 1)")
    print()
    print("3. As the paper's Table 1: median CIEDE2000 of the signal accumulated over 1..5 bounces")
    print(f"   {'n':>3} {'model':<22}" + "".join(f"{k:>7}" for k in range(1, 6)))
    for n, t in res["table1"].items():
        for kind, label in (("best", "best approximation"), ("diagonal", "spectral factor model")):
            print(f"   {n:>3} {label:<22}" + "".join(f"{v:7.3f}" for v in t[kind]))
    print(f"\n(total {time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
