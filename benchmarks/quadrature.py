"""Meyer's Tables 1a/1b and 2 and Borges' Table 1 reproduced beside the papers' numbers.

``python -m benchmarks.quadrature`` prints, for the rules of
:mod:`models.quadrature`: Meyer's Gaussian quadrature on the opponent
fundamentals AC1C2 (nodes, weights, undefined orders; Meyer 1988, Tables
1a/1b [docs/references.md#seed-000]), the mean CIELAB error of his four
wavelengths on the ColorChecker under illuminant C (Table 2), Borges'
shared abscissas (Borges 1992, Table 1 [docs/references.md#seed-004]) with
the sensitivity of his eq. 11 to rounding, and the XYZ rules' CIEDE2000 on
the ColorChecker under five lights. The published tables only the
reproduction needs (Meyer's Table 2, Borges' Table 1) are here; those the
rules use (Meyer's eq. 9 matrix, his Table 1a for the weight scale) stay in
:mod:`models.quadrature`.
"""

from __future__ import annotations

import numpy as np

from models.grid import wavelength_step
from models.illuminants import illuminant
from models.quadrature import (AC1C2_CHANNELS, BORGES_INTERVAL_NM, MEYER_STEP_NM, MEYER_TABLE_1A,
                               MEYER_XYZ_TO_AC1C2, ac1c2_eigenvalues, ac1c2_fundamentals,
                               borges_chebyshev_moments, cie1931, eq11_literal, gauss_ac1c2_rule,
                               interpolatory_weights, meyer_grid, meyer_weight_scale, quasi_gauss_xyz_rule,
                               xyz_to_ac1c2_matrix)
from models.reflectances import reflectance_set
from models.spectral_rule import interpolation_matrix

__all__ = ["MEYER_TABLE_2", "BORGES_TABLE_1", "meyer_table2_error", "eq11_sensitivity", "delta_e00", "main"]


#: Meyer (1988) Table 2: {row: {channel: (nodes, weights)}, "error": mean L*a*b* error}.
#: Row 1: A order 3, C1 order 2, C2 order 1 (six wavelengths; the table's A weight
#: "0.71595" is Table 1a's 0.71695 misprinted). Row 2: the two C1 wavelengths also used
#: for A, with A's weights recomputed by eq. 13 (four wavelengths).
MEYER_TABLE_2 = {
    1: {"A": ([483.0, 557.7, 632.3], [0.15908, 0.71695, 0.18035]),
        "C1": ([490.9, 631.4], [0.31824, -0.46008]),
        "C2": ([456.4], [0.54640]), "error": 5.432},
    2: {"A": ([490.9, 557.7, 631.4], [0.18892, 0.67493, 0.19253]),
        "C1": ([490.9, 631.4], [0.31824, -0.46008]),
        "C2": ([456.4], [0.54640]), "error": 5.429},
}

#: Borges (1992) Table 1: quasi-Gaussian abscissas (nm) per degree sequence (xbar, ybar, zbar).
BORGES_TABLE_1 = {
    (1, 1, 1): [445.3, 535.8, 619.4],
    (2, 1, 1): [441.0, 523.4, 574.3, 643.1],
    (1, 2, 1): [443.1, 531.8, 607.6, 720.0],
    (1, 1, 2): [425.3, 469.3, 543.0, 627.6],
    (2, 2, 2): [419.8, 461.7, 526.6, 582.7, 638.6, 707.7],
    (3, 3, 3): [391.4, 422.6, 453.8, 488.8, 539.1, 587.7, 635.2, 689.4, 767.2],
}


def meyer_table2_error(row: int = 2, reflectances: str = "colorchecker-ohta",
                       weights: str = "computed") -> dict:
    """Mean CIELAB error of Meyer's Table 2 wavelengths on the ColorChecker under C.

    Meyer (1988), sec. 4.1 and Table 2: the tristimulus values A, C1, C2 of
    the 24 ColorChecker patches under CIE illuminant C are computed with the
    quadrature (A order 3, C1 order 2, C2 order 1; in row 2 A uses C1's two
    wavelengths, four wavelengths in all), turned into XYZ with the inverse of
    eq. 9, and compared in CIE 1976 L*a*b* with the full calculation (5 nm
    sums over 380-770 nm). As in the paper, the white of L*a*b* is illuminant
    C computed the same way as the samples (quadrature white for the
    quadrature colours), so the weights' overall scale cancels.

    Parameters
    ----------
    row : {1, 2}
        Table 2's row.
    reflectances : str
        A set of :func:`models.reflectances.reflectance_set`; the default,
        N. Ohta's ColorChecker, gives 5.42 (row 1) and 5.51 (row 2) against
        Meyer's 5.432 and 5.429; the BabelColor average gives about 4.7.
        Meyer used McCamy et al.'s 1976 curves, which colour-science does
        not ship.
    weights : {"computed", "table"}
        Interpolatory weights (eq. 13) recomputed on this module's
        fundamentals and matrix, or Meyer's printed weights with his printed
        eq. 9 matrix.

    Returns
    -------
    dict
        ``mean``, ``max`` (Delta E*ab), ``paper`` (Meyer's value),
        ``wavelengths`` (distinct nodes) and ``per_patch``.
    """
    import colour

    if row not in MEYER_TABLE_2:
        raise ValueError(f"Meyer's Table 2 has rows 1 and 2, not {row!r}")
    if weights not in ("computed", "table"):
        raise ValueError(f"weights must be 'computed' or 'table', not {weights!r}")
    wl = meyer_grid()
    dl = wavelength_step(wl)
    cmf = cie1931(wl)
    S = reflectance_set(reflectances, wl)
    E = illuminant("C", wl, normalise=False)
    M = MEYER_XYZ_TO_AC1C2 if weights == "table" else xyz_to_ac1c2_matrix()
    F = ac1c2_fundamentals(wl, "printed" if weights == "table" else "computed")
    spec = MEYER_TABLE_2[row]

    def quadrature_xyz(spectra):
        out = []
        for ch, ci in AC1C2_CHANNELS.items():
            nodes, w = spec[ch]
            if weights == "computed":
                w = interpolatory_weights(nodes, F[:, ci], wl)
            vals = np.stack([np.interp(nodes, wl, s) for s in np.atleast_2d(spectra)])
            out.append(vals @ np.asarray(w, dtype=float))
        return np.stack(out, -1) @ np.linalg.inv(M).T

    def lab(xyz, white):
        return colour.XYZ_to_Lab(xyz / white[1], colour.XYZ_to_xy(white))

    white_true = E @ (cmf * dl[:, None])
    true = lab((S * E) @ (cmf * dl[:, None]), white_true)
    approx = lab(quadrature_xyz(S * E), quadrature_xyz(E)[0])
    d = np.linalg.norm(approx - true, axis=1)
    nodes = sorted({v for ch in AC1C2_CHANNELS for v in spec[ch][0]})
    return {"mean": float(d.mean()), "max": float(d.max()), "paper": spec["error"],
            "wavelengths": nodes, "reflectances": reflectances, "per_patch": d.tolist()}


def eq11_sensitivity(degrees, rel_error=1e-15, trials=200, seed=0):
    """90th percentile abscissa shift (nm) when eq. 11 is solved in double precision
    with Borges' analytic moments perturbed by ``rel_error`` (relative, Gaussian)."""
    deg = tuple(int(v) for v in degrees)
    _, raw = borges_chebyshev_moments(sum(deg) + max(deg), 1, BORGES_INTERVAL_NM)
    base = np.sort(np.real(eq11_literal(raw, deg)[1])) * 1000.0
    rng = np.random.default_rng(seed)
    shifts = []
    for _ in range(trials):
        r = eq11_literal(raw * (1.0 + rel_error * rng.standard_normal(raw.shape)), deg)[1]
        if r.size == base.size and np.all(np.abs(np.imag(r)) < 1e-9):
            shifts.append(np.sort(np.real(r)) * 1000.0 - base)
    return np.percentile(np.abs(np.array(shifts)), 90, axis=0)


def delta_e00(rule, light: str, reflectances: str = "colorchecker") -> np.ndarray:
    """CIEDE2000 of an XYZ rule (weights ``(n, 3)``) against 1 nm sums over 360-830 nm,
    per reflectance, with the white of each side computed the same way (Meyer 1988,
    sec. 4.1: a perfect reflector under the light)."""
    import colour

    wl = np.arange(360.0, 830.5, 1.0)
    cmf, E, S = cie1931(wl), illuminant(light, wl), reflectance_set(reflectances, wl)
    full, white = (S * E) @ cmf, E @ cmf
    ce, cs = interpolation_matrix(rule.nodes_nm, wl) @ E, S @ interpolation_matrix(rule.nodes_nm, wl).T
    approx, white_q = (cs * ce) @ rule.weights, ce @ rule.weights
    lab_f = colour.XYZ_to_Lab(full / white[1], colour.XYZ_to_xy(white))
    lab_q = colour.XYZ_to_Lab(approx / white_q[1], colour.XYZ_to_xy(white_q))
    return np.asarray(colour.delta_E(lab_f, lab_q, method="CIE 2000"), dtype=float)


def _fmt(values, digits=1):
    return " ".join(f"{v:{6 + digits}.{digits}f}" for v in values)


def main() -> None:
    """Print Meyer's Tables 1a/1b and 2 and Borges' Table 1 beside this module's numbers."""
    scale = meyer_weight_scale()
    print("Meyer (1988) Tables 1a/1b: Gaussian quadrature on the AC1C2 fundamentals, 380-770 nm")
    print(f"(CIE 1931 at {MEYER_STEP_NM:g} nm; weights x {scale:.6f}, Meyer's normalising factor)")
    for ch in AC1C2_CHANNELS:
        print(f"\n  {ch}")
        for order in range(1, 11):
            r = gauss_ac1c2_rule(order, None, channel=ch)
            paper = MEYER_TABLE_1A[ch][order]
            if not r.defined:
                mark = "undefined" if paper is None else "undefined, PAPER DEFINED"
                print(f"  {order:2d}  {mark:9s}  ({r.reason})")
                continue
            print(f"  {order:2d}  nodes   {_fmt(r.nodes_nm)}")
            if paper is None:
                print("      paper   undefined")
                continue
            print(f"      paper   {_fmt(paper[0])}   max |diff| {np.max(np.abs(r.nodes_nm - paper[0])):.2f} nm")
            print(f"      weights {_fmt(r.weights * scale, 5)}")
            print(f"      paper   {_fmt(paper[1], 5)}")
    ev = ac1c2_eigenvalues()
    print(f"\n  eigenvalue ratio {ev[0] / ev[2] * 0.0221:.1f} : {ev[1] / ev[2] * 0.0221:.2f} : 0.0221"
          "   (paper, eq. 10: 102.4 : 2.29 : 0.0221)")
    print("\nMeyer Table 2: mean CIELAB error, ColorChecker under illuminant C")
    for row in (1, 2):
        for refl in ("colorchecker-ohta", "colorchecker"):
            for w in ("computed", "table"):
                e = meyer_table2_error(row, refl, w)
                print(f"  row {row} ({len(e['wavelengths'])} wavelengths) {refl:18s} weights={w:8s} "
                      f"mean {e['mean']:.3f} (max {e['max']:.2f})   paper {e['paper']:.3f}")
    print("\nBorges (1992) Table 1: quasi-Gaussian shared abscissas (nm), 360-830 nm")
    print("  analytic = his functions, log-gamma moments of lam*w (the convention that")
    print("  reproduces his table); exact = moments of w as eq. 13 prints; cie = tabulated CIE 1931")
    for deg, paper in BORGES_TABLE_1.items():
        print(f"\n  {deg}  paper    {_fmt(paper)}")
        for label, kw in (("analytic", {}), ("exact", {"lambda_power": 0}), ("cie", {"source": "cie"})):
            r = quasi_gauss_xyz_rule(None, None, deg, **kw)
            if not r.defined:
                print(f"  {'':9s}  {label:8s} undefined: {r.reason}")
                continue
            d = r.diagnostics
            print(f"  {'':9s}  {label:8s} {_fmt(r.nodes_nm)}   max |diff| "
                  f"{np.max(np.abs(r.nodes_nm - paper)):5.2f} nm   cond eq.11 {d['condition_eq11']:.1e}, "
                  f"solved (Chebyshev) {d['condition_chebyshev']:.1e}")
    sens = eq11_sensitivity((3, 3, 3))
    print("\n  (3,3,3): 90th percentile shift of eq. 11 solved in double with moments off by 1e-15:")
    print(f"  {'':9s}  shift    {_fmt(sens)}")
    lights = ("A", "C", "D65", "FL2", "FL11")
    print("\nXYZ rules on the ColorChecker (BabelColor): mean CIEDE2000 against 1 nm sums, "
          "white from the same rule")
    print(f"  {'rule':34s} {'n':>3s} " + " ".join(f"{v:>6s}" for v in lights))
    rules = [("Meyer Table 2 (A3 C1-2 C2-1, shared)", gauss_ac1c2_rule(None, None, "XYZ")),
             ("Meyer A3 C1-2 C2-1, not shared", gauss_ac1c2_rule(None, None, "XYZ", merge_nm=0))]
    for deg in ((1, 1, 1), (2, 2, 2), (3, 3, 3), (4, 4, 4)):
        for src in ("cie", "analytic"):
            rules.append((f"Borges {deg} {src}", quasi_gauss_xyz_rule(None, None, deg, source=src)))
    for label, rule in rules:
        if not rule.defined:
            print(f"  {label:34s}   -  undefined: {rule.reason}")
            continue
        errs = [float(np.mean(delta_e00(rule, v))) for v in lights]
        print(f"  {label:34s} {rule.n:3d} " + " ".join(f"{v:6.2f}" for v in errs))


if __name__ == "__main__":
    main()
