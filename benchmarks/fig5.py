"""How many terms do surface reflectances need? Wandell (1985), Fig. 5.

Run as ``python -m benchmarks.fig5 [--out DIR] [--max-terms 12] [--step 10]``.

For every reflectance set shipped with colour-science
(:func:`models.reflectance_set_names`, ``"all"`` included) and for 1 to
``max_terms`` basis functions, fit each reflectance by least squares in

* the Fourier basis (:func:`models.fourier_model`: DC, then sine/cosine
  pairs over 400-700 nm, Wandell's Fig. 4b);
* principal components through the origin (:func:`models.pca_model` with
  ``centred=False``), trained on the set itself (in-sample);
* the same principal components trained *without* the set (leave the set's
  group out, train on every other shipped set): a cross-validated number,
  which says how well a basis learned elsewhere describes new surfaces.

and report the median, 90th percentile and worst normalised RMSE
(:func:`models.normalised_rmse`, ``||s - s_hat|| / ||s||``). Prints a table,
writes ``fig5_rmse_vs_terms.png`` and ``fig5_rmse_vs_terms.csv``.

References
----------
Wandell (1985), *The Synthesis and Analysis of Color Images*,
[docs/references.md#seed-002], section "Fourier Basis": Fig. 5 plots the median
normalised RMSE of least-squares Fourier fits to 462 Munsell chips against
the number of terms; Fig. 4a shows the worst fit. Section "Principal
Components Analysis" (Cohen 1964) motivates the PCA comparison.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
import time

import numpy as np

from models.bases import fourier_model, normalised_rmse, pca_model
from models.grid import wavelength_grid
from models.reflectances import reflectance_set, reflectance_set_names

__all__ = ["FIG5_MODELS", "FIG5_STATS", "CV_GROUPS", "fig5_table", "format_table", "write_csv",
           "plot", "main"]

#: Model labels, in the order of the ``values`` axis 0 of :func:`fig5_table`.
FIG5_MODELS = ("fourier", "pca", "pca-cv")
#: Statistic labels, in the order of the ``values`` axis 2.
FIG5_STATS = ("median", "p90", "worst")

#: Sets that are measurements of the same physical surfaces and so are left
#: out together in the cross-validated PCA (BabelColor's average and Ohta's
#: measurement are both the 24-patch ColorChecker; 13 of the 24 Ohta
#: patches lie within 5 % relative distance of their BabelColor twins).
CV_GROUPS = (("colorchecker", "colorchecker-ohta"),)


def _group_of(name: str) -> tuple[str, ...]:
    for g in CV_GROUPS:
        if name in g:
            return g
    return (name,)


def _stats(err: np.ndarray) -> np.ndarray:
    return np.array([np.median(err), np.percentile(err, 90), np.max(err)])


def fig5_table(max_terms: int = 12, sets=None, wavelengths=None) -> dict:
    """Normalised RMSE of least-squares fits against the number of terms.

    The computation behind Wandell (1985), Fig. 5 ([docs/references.md#seed-002],
    section "Fourier Basis"), for colour-science's reflectance sets instead
    of the 462 Munsell chips, and with PCA through the origin beside the
    Fourier basis.

    Parameters
    ----------
    max_terms : int
        Largest number of basis functions; rows for ``1..max_terms``.
    sets : sequence of str, optional
        Reflectance set names; default :func:`models.reflectance_set_names`
        (the individual sets and ``"all"``).
    wavelengths : array_like, optional
        Grid in nm; default 400-700 nm at 10 nm (the range of Fig. 5).

    Returns
    -------
    dict
        ``terms`` : (T,) int, 1..max_terms;
        ``sets`` : list of S set names;
        ``n_samples`` : (S,) int, reflectances per set;
        ``models`` : :data:`FIG5_MODELS`; ``stats`` : :data:`FIG5_STATS`;
        ``values`` : (3, S, 3, T) float, ``values[m, s, q, t]`` is statistic
        ``q`` (median, 90th percentile, worst) over the reflectances of set
        ``s`` of the normalised RMSE ``||s - s_hat|| / ||s||`` of model ``m``
        with ``terms[t]`` terms. NaN where a model cannot have that many
        terms (PCA of a set with fewer samples than terms).
        ``wavelengths`` : (N,) grid used.

    Notes
    -----
    * ``fourier``: :func:`models.fourier_model`, DC then sine/cosine pairs
      (Fig. 4b).
    * ``pca``: :func:`models.pca_model` (``centred=False``) trained on the
      set being evaluated (in-sample; for ``"all"`` trained on all).
    * ``pca-cv``: trained on every shipped set except the evaluated set's
      group (:data:`CV_GROUPS`: the two ColorChecker measurements are one
      group). For ``"all"`` each reflectance is scored with the basis that
      left its own group out, and the errors are pooled.
    * Wandell's caption says the variance accounted for is ``sqrt(1 - y)``
      for a normalised RMSE ``y``; with ``y = ||s - s_hat|| / ||s||`` and a
      least-squares (orthogonal) fit the fraction of ``||s||^2`` accounted
      for is ``1 - y**2``.

    Examples
    --------
    >>> t = fig5_table(max_terms=3, sets=["tcs"])
    >>> t["values"].shape
    (3, 1, 3, 3)
    >>> bool(np.all(np.diff(t["values"][0, 0, 0]) <= 0))   # more terms, smaller error
    True
    """
    wl = wavelength_grid(400, 700, 10) if wavelengths is None else np.asarray(wavelengths, float)
    names = list(reflectance_set_names() if sets is None else sets)
    singles = [n for n in reflectance_set_names() if n != "all"]
    data = {n: reflectance_set(n, wl) for n in singles}
    if "all" in names:
        data["all"] = np.concatenate([data[n] for n in singles])
    for n in names:
        if n not in data:
            data[n] = reflectance_set(n, wl)
    terms = np.arange(1, int(max_terms) + 1)
    T = terms.size
    values = np.full((len(FIG5_MODELS), len(names), len(FIG5_STATS), T), np.nan)

    # cross-validated bases: one per group, trained on every other single set
    cv_basis = {}
    for g in {_group_of(n) for n in singles}:
        train = np.concatenate([data[n] for n in singles if n not in g])
        cv_basis[g] = pca_model(train, min(T, min(train.shape)), wl, centred=False).basis

    def fit_err(basis, x, d):
        if d > basis.shape[1]:
            return np.full(x.shape[0], np.nan)
        b = basis[:, :d]
        w, *_ = np.linalg.lstsq(b, x.T, rcond=None)
        return normalised_rmse(x, (b @ w).T)

    for s, name in enumerate(names):
        x = data[name]
        four = fourier_model(T, wl).basis
        own = pca_model(x, min(T, min(x.shape)), wl, centred=False).basis
        if name == "all":
            parts = [(data[n], cv_basis[_group_of(n)]) for n in singles]
        else:
            parts = [(x, cv_basis[_group_of(name)])]
        for t, d in enumerate(terms):
            values[0, s, :, t] = _stats(fit_err(four, x, d))
            e = fit_err(own, x, d)
            values[1, s, :, t] = np.nan if np.all(np.isnan(e)) else _stats(e)
            e = np.concatenate([fit_err(b, xp, d) for xp, b in parts])
            values[2, s, :, t] = np.nan if np.all(np.isnan(e)) else _stats(e)
    return {"terms": terms, "sets": names, "n_samples": np.array([data[n].shape[0] for n in names]),
            "models": FIG5_MODELS, "stats": FIG5_STATS, "values": values, "wavelengths": wl}


def format_table(table: dict) -> str:
    """Plain-text table: one block per set, rows = number of terms,
    columns = model x statistic."""
    v = table["values"]
    head = "terms " + " ".join(f"{m[:7] + ' ' + q:>14}" for m in table["models"] for q in table["stats"])
    lines = []
    for s, name in enumerate(table["sets"]):
        lines.append(f"\n{name} ({table['n_samples'][s]} reflectances): normalised RMSE ||s - s_hat||/||s||")
        lines.append(head)
        for t, d in enumerate(table["terms"]):
            cells = " ".join(f"{v[m, s, q, t]:14.4f}" for m in range(v.shape[0]) for q in range(v.shape[2]))
            lines.append(f"{d:5d} {cells}")
    return "\n".join(lines).lstrip("\n")


def write_csv(table: dict, path: str) -> None:
    """Long-format CSV: set, n_samples, model, terms, median, p90, worst."""
    v = table["values"]
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["set", "n_samples", "model", "terms", *table["stats"]])
        for s, name in enumerate(table["sets"]):
            for m, model in enumerate(table["models"]):
                for t, d in enumerate(table["terms"]):
                    w.writerow([name, int(table["n_samples"][s]), model, int(d),
                                *[("" if np.isnan(x) else f"{x:.6g}") for x in v[m, s, :, t]]])


def plot(table: dict, path: str) -> None:
    """One panel per set: median (solid) and 90th percentile (dashed)
    normalised RMSE against the number of terms, log scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = table["sets"]
    ncol = 3
    nrow = int(np.ceil(len(names) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 3.4 * nrow), sharex=True, sharey=True,
                             squeeze=False)
    colours = {"fourier": "C0", "pca": "C1", "pca-cv": "C2"}
    labels = {"fourier": "Fourier", "pca": "PCA (in-sample)", "pca-cv": "PCA (set left out)"}
    v = table["values"]
    x = table["terms"]
    for s, name in enumerate(names):
        ax = axes[s // ncol, s % ncol]
        for m, model in enumerate(table["models"]):
            ax.plot(x, v[m, s, 0], "-o", ms=3, color=colours[model], label=f"{labels[model]}, median")
            ax.plot(x, v[m, s, 1], "--", color=colours[model], lw=1, label=f"{labels[model]}, 90th pct")
        ax.set_yscale("log")
        ax.set_title(f"{name} (n={table['n_samples'][s]})", fontsize=10)
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes[-1]:
        ax.set_xlabel("number of basis terms")
    for ax in axes[:, 0]:
        ax.set_ylabel("normalised RMSE")
    for k in range(len(names), nrow * ncol):
        axes[k // ncol, k % ncol].axis("off")
    axes[0, 0].legend(fontsize=7)
    fig.suptitle("Wandell (1985) Fig. 5 for colour-science reflectances: ||s - s_hat|| / ||s||", fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m benchmarks.fig5", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="out", help="output directory (default ./out)")
    ap.add_argument("--max-terms", type=int, default=12, help="largest number of terms (default 12)")
    ap.add_argument("--step", type=float, default=10.0, help="wavelength step in nm over 400-700 (default 10)")
    a = ap.parse_args(argv)
    if a.max_terms < 1:
        ap.error("--max-terms must be >= 1")
    t0 = time.perf_counter()
    table = fig5_table(a.max_terms, wavelengths=wavelength_grid(400, 700, a.step))
    os.makedirs(a.out, exist_ok=True)
    png = os.path.join(a.out, "fig5_rmse_vs_terms.png")
    csv_path = os.path.join(a.out, "fig5_rmse_vs_terms.csv")
    write_csv(table, csv_path)
    plot(table, png)
    print(format_table(table))
    print(f"\nwrote {csv_path} and {png} ({time.perf_counter() - t0:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
