"""Point sampling with a linear model of the surfaces: a few bands chosen for
the light at hand, spectra rebuilt by a Wiener (linear least-squares) estimate.

Surfaces are close to a low-dimensional linear model (Wandell 1985,
[docs/references.md#seed-002], eq. 6 and 11; Fig. 5: a handful of terms explain
Munsell reflectances). A spectrum is then known from a few of its samples:
with ``R = E[s s^T]`` the autocorrelation of a training set of reflectances
and ``i`` the sampled bands, the linear least-squares estimate is

    s_hat = R[:, i] R[i, i]^-1 s[i]

(the Wiener estimate through the origin, which keeps the rule linear). As a
:class:`models.sampling.SpectralRule` the analysis reads the bands ``i``
(so a render reads ``n`` bands of ``N``) and the synthesis is
``R[:, i] R[i, i]^-1``. Which bands: chosen greedily, then refined by single
swaps, to minimise the mean CIEDE2000 of the training set's colour signals
under the given light against the full calculation, so spiky lights pull
bands onto their lines (Kment 2011 [docs/references.md#seed-001], ch. 5: fluorescent lights
need their lines represented) while smooth ones spread them over the
colour-matching functions (Meyer 1988 [docs/references.md#seed-000], sec. 3: wavelengths
placed where the observer integrates).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from .grid import wavelength_step
from .spectral_rule import SpectralRule

__all__ = ["wiener_points_rule", "training_reflectances"]


def training_reflectances(training="all", wavelengths=None) -> np.ndarray:
    """Training spectra ``(M, N)``: an array, or reflectance set names of
    :func:`models.reflectance_set` joined by ``+`` (``"colorchecker+tcs"``)."""
    from .reflectances import reflectance_set

    if isinstance(training, str):
        return np.concatenate([reflectance_set(name, wavelengths) for name in training.split("+")])
    arr = np.asarray(training, float)
    if arr.ndim != 2 or arr.shape[0] < 2:
        raise ValueError("training spectra must be an (M, N) array with M >= 2")
    return arr


def _lab(xyz: np.ndarray, white: np.ndarray) -> np.ndarray:
    """CIELAB (CIE 015:2018, eq. 8.1-8.3) of ``(M, 3)`` XYZ against ``white``."""
    t = xyz / white
    d = 6.0 / 29.0
    f = np.where(t > d ** 3, np.cbrt(np.maximum(t, d ** 3)), t / (3 * d * d) + 4.0 / 29.0)
    return np.stack([116 * f[:, 1] - 16, 500 * (f[:, 0] - f[:, 1]), 200 * (f[:, 1] - f[:, 2])], 1)


def _synthesis(Rm: np.ndarray, idx) -> np.ndarray:
    idx = list(idx)
    return np.linalg.solve(Rm[np.ix_(idx, idx)], Rm[idx, :]).T           # (N, n)


def _select(S: np.ndarray, Rm: np.ndarray, W: np.ndarray, white: np.ndarray, n: int) -> tuple[list, float]:
    """Greedy forward selection of ``n`` bands, then single-band swaps until
    no swap lowers the objective: the mean CIELAB Delta E*ab (CIE 1976; cheap
    enough to try every band at every step) of the training set under the
    light against the full calculation."""
    N = S.shape[1]
    ref = _lab(S @ W, white)

    def cost(idx):
        try:
            K = _synthesis(Rm, idx).T @ W                                      # (n, 3)
        except np.linalg.LinAlgError:
            return np.inf
        return float(np.mean(np.linalg.norm(_lab(S[:, list(idx)] @ K, white) - ref, axis=1)))

    chosen: list = []
    for _ in range(n):
        best = min((cost(chosen + [j]), j) for j in range(N) if j not in chosen)
        chosen.append(best[1])
    current = cost(chosen)
    for _ in range(3):
        improved = False
        for pos in range(n):
            for j in range(N):
                if j in chosen:
                    continue
                trial = chosen[:pos] + [j] + chosen[pos + 1:]
                c = cost(trial)
                if c < current - 1e-9:
                    chosen, current, improved = trial, c, True
        if not improved:
            break
    return sorted(chosen), current


@lru_cache(maxsize=64)
def _cached(n, wl, training, light, cmfs, ridge):
    wl = np.asarray(wl)
    S = training_reflectances(training, wl)
    N = wl.size
    Rm = S.T @ S / S.shape[0]
    Rm = Rm + ridge * np.trace(Rm) / N * np.eye(N)
    dl = wavelength_step(wl)
    if light is None:
        E = np.ones(N)
    else:
        E = np.asarray(light, float)
    if cmfs is None:
        from .observers import observer

        C = np.asarray(observer("CIE 1931 2 Degree Standard Observer", wl), float)
    else:
        C = np.asarray(cmfs, float).reshape(N, 3)
    W = C * (E * dl)[:, None]
    W = W / W[:, 1].sum()
    white = W.sum(axis=0)
    idx, err = _select(S, Rm, W, white, n)
    return idx, err, Rm, S.shape[0]


def wiener_points_rule(n: int | None, wavelengths: np.ndarray, training="all", light=None, cmfs=None,
                       ridge: float = 1e-4) -> SpectralRule:
    """``n`` bands of ``wavelengths`` chosen for ``light``, spectra rebuilt by
    the Wiener estimate of a training set (module docstring; Wandell 1985,
    eq. 11 for the linear model).

    Parameters
    ----------
    n : int
        Bands to read, 1..N.
    wavelengths : (N,) ndarray
        Grid of the spectra; the nodes are bands of this grid.
    training : str or (M, N) array
        Reflectance sets (``"all"``, ``"colorchecker+tcs"``...) or spectra.
    light : (N,) array, optional
        Light the bands are chosen for (default equal energy).
    cmfs : (N, 3) array, optional
        Observer (default CIE 1931 2 degree).
    ridge : float
        Added to the autocorrelation's diagonal, relative to its mean
        diagonal (regularises the solve; 1e-4 is below the 12-bit noise of
        measured reflectances).

    Examples
    --------
    >>> from models.grid import DEFAULT_WAVELENGTHS
    >>> from models.illuminants import illuminant
    >>> rule = wiener_points_rule(4, DEFAULT_WAVELENGTHS, "colorchecker", illuminant("D65"))
    >>> rule.n, int((rule.analysis != 0).sum())
    (4, 4)
    """
    wl = np.asarray(wavelengths, float)
    if n is None or int(n) != n or not 1 <= int(n) <= wl.size:
        raise ValueError(f"wiener-points needs n in 1..{wl.size}, not {n!r}")
    n = int(n)
    key_train = training if isinstance(training, str) else tuple(map(tuple, np.asarray(training, float)))
    key_light = None if light is None else tuple(np.asarray(light, float).tolist())
    key_cmfs = None if cmfs is None else tuple(np.asarray(cmfs, float).ravel().tolist())
    idx, err, Rm, m = _cached(n, tuple(wl.tolist()), key_train, key_light, key_cmfs, float(ridge))
    analysis = np.zeros((n, wl.size))
    analysis[np.arange(n), idx] = 1.0
    synthesis = _synthesis(Rm, idx)
    cond = float(np.linalg.cond(Rm[np.ix_(idx, idx)]))
    return SpectralRule("wiener-points", wl, analysis, synthesis, nodes_nm=wl[idx].copy(),
                        multiplicative=False,
                        diagnostics={"training": training if isinstance(training, str) else f"{m} spectra",
                                     "training_spectra": int(m),
                                     "training_mean_delta_e_ab": round(err, 4),
                                     "condition_R_ii": cond,
                                     "bands_chosen_for": "given light" if light is not None else
                                     "equal-energy light"})
