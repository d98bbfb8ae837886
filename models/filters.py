"""Low-pass resampling filters for point sampling (Kment 2011, sec. 4.4-4.5).

Kment prepares a densely sampled spectrum for point sampling by *ideal
sampling rate conversion* (his Fig. 4.2, after Hayes 1999): up-sample, low-pass
with a windowed FIR filter, decimate. For a spectrum given on a regular dense
grid this is the same as evaluating, at each new node, the filtered signal

    y(node) = sum_k w((node - lambda_k) / dlambda) x_k / sum_m w(frac + m)

with the window ``w`` centred on the node (eq. 4.4-4.5: convolution), the
denominator making the filter's DC gain 1 on the infinite lattice. Values
outside the grid count as 0 (Kment sec. 6.1: "sample values which are not
within 380 nm and 780 nm are counted as equal to 0.0").

The window argument ``x`` is measured in dense-grid samples. The *extent* is
Kment's "how many sample points influence the filter" (odd integers 3 to 21 in
his tests): the window's half-width is ``extent / 2`` samples, so exactly
``extent`` samples fall inside it when the node sits on a grid point.

Windows (Kment eq. 4.13-4.19; ``u = x / (extent / 2)`` is the position in the
window, in [-1, 1]):

======== ======================================================== ============
name     w                                                        parameters
======== ======================================================== ============
box      1                                        (eq. 4.13)      extent
tent     1 - |u|                                  (eq. 4.14)      extent
welch    1 - u**2                                 (eq. 4.15)      extent
gauss    exp(-alpha x**2) - exp(-alpha (extent/2)**2)  (eq. 4.16) extent, alpha
mitchell Mitchell-Netravali cubic k(2 u; b, c)    (eq. 4.17)      extent, b, c
lanczos  sinc(tau u) sinc(u)                      (eq. 4.18)      extent, tau
hann     alpha + (1 - alpha) cos(pi u), alpha=0.5 (eq. 4.19)      extent
hamming  same with alpha = 0.54                   (eq. 4.19)      extent
======== ======================================================== ============

The Mitchell cubic has support |x| < 2 in its own unit; it is stretched to fill
the extent (Kment's best Mitchell extents, 11 to 21 samples, would otherwise
hold at most 3 samples). The Lanczos window is the sinc with ``tau`` cycles
across the half-window ("tau determines the number of sinc cycles"), tapered
by the central lobe of a sinc the width of the window (Turkowski and Gabriel
1990); ``tau`` need not be an integer (Kment's best values: 0.05 to 2.70).

References
----------
Kment, T. (2011). Spectral data representation techniques for realistic image
synthesis. TU Wien [docs/references.md#seed-001], ch. 4 and sec. 6.3, Tables A.1, A.2 and 7.1.
Mitchell, D. P. and Netravali, A. N. (1988). Reconstruction filters in
computer graphics. SIGGRAPH 22(4).
"""

from __future__ import annotations

import numpy as np

__all__ = ["FILTERS", "filter_names", "filter_window", "default_extent", "lowpass_matrix"]

#: filter name -> (parameter names besides ``extent``, their defaults)
FILTERS: dict[str, dict[str, float]] = {
    "box": {},
    "tent": {},
    "welch": {},
    "gauss": {"alpha": 0.05},
    "mitchell": {"b": 1.0 / 3.0, "c": 1.0 / 3.0},
    "lanczos": {"tau": 2.0},
    "hann": {},
    "hamming": {},
}

#: Default extent in units of the output node spacing (when ``extent`` is not
#: given): box one spacing (the Riemann interval), the tapered windows two, the
#: cubic and the sinc four, i.e. each kernel at its natural scale for the new
#: sampling rate (cut-off pi / M, Kment eq. 4.11).
_DEFAULT_SPAN = {"box": 1.0, "tent": 2.0, "welch": 2.0, "gauss": 2.0, "hann": 2.0,
                 "hamming": 2.0, "mitchell": 4.0, "lanczos": 4.0}


def filter_names() -> list[str]:
    """Names :func:`filter_window` and :func:`lowpass_matrix` accept."""
    return list(FILTERS)


def _check(name: str, params: dict) -> dict:
    if name not in FILTERS:
        raise ValueError(f"unknown filter {name!r}; accepted: {', '.join(FILTERS)}")
    unknown = set(params) - set(FILTERS[name])
    if unknown:
        accepted = ", ".join(FILTERS[name]) or "none besides extent"
        raise ValueError(f"filter {name!r} takes no parameter {sorted(unknown)}; accepted: {accepted}")
    out = dict(FILTERS[name])
    for k, v in params.items():
        v = float(v)
        if not np.isfinite(v):
            raise ValueError(f"filter parameter {k} must be finite, not {v}")
        out[k] = v
    if name == "lanczos" and out["tau"] <= 0:
        raise ValueError("lanczos tau must be > 0")
    if name == "gauss" and out["alpha"] <= 0:
        raise ValueError("gauss alpha must be > 0")
    return out


def filter_window(name: str, x, extent: float, **params) -> np.ndarray:
    """Kment's window ``w(x)`` (eq. 4.13-4.19), zero outside the extent.

    Parameters
    ----------
    name : str
        One of :func:`filter_names`.
    x : array_like
        Offsets from the window centre, in dense-grid samples.
    extent : float
        Number of samples the window covers (half-width ``extent / 2``).
    **params
        ``alpha`` (gauss), ``b`` and ``c`` (mitchell), ``tau`` (lanczos).

    Returns
    -------
    numpy.ndarray
        Window values, same shape as ``x`` (not normalised).

    Examples
    --------
    >>> filter_window("tent", [0, 1, 2, 3], extent=5).round(2).tolist()
    [1.0, 0.6, 0.2, 0.0]
    >>> filter_window("mitchell", [0.0], extent=8, b=0, c=0.5).tolist()  # Catmull-Rom: k(0) = 1
    [1.0]
    """
    p = _check(name, params)
    if not np.isfinite(extent) or extent <= 0:
        raise ValueError(f"filter extent must be > 0 samples, not {extent}")
    x = np.asarray(x, dtype=float)
    half = extent / 2.0
    u = x / half
    inside = np.abs(u) < 1.0
    if name == "box":  # eq. 4.13, |x| <= tau
        return np.where(np.abs(u) <= 1.0, 1.0, 0.0)
    if name == "tent":  # eq. 4.14
        w = 1.0 - np.abs(u)
    elif name == "welch":  # eq. 4.15
        w = 1.0 - u**2
    elif name == "gauss":  # eq. 4.16: the border value is subtracted so w = 0 there
        w = np.exp(-p["alpha"] * x**2) - np.exp(-p["alpha"] * half**2)
    elif name == "mitchell":  # eq. 4.17 with the support |t| < 2 stretched over the window
        b, c = p["b"], p["c"]
        t = np.abs(2.0 * u)
        w = np.where(
            t < 1.0,
            (12 - 9 * b - 6 * c) * t**3 + (-18 + 12 * b + 6 * c) * t**2 + (6 - 2 * b),
            (-b - 6 * c) * t**3 + (6 * b + 30 * c) * t**2 + (-12 * b - 48 * c) * t + (8 * b + 24 * c),
        ) / 6.0
    elif name == "lanczos":  # eq. 4.18: tau sinc cycles over the half-window, Lanczos taper
        w = np.sinc(p["tau"] * u) * np.sinc(u)
    elif name in ("hann", "hamming"):  # eq. 4.19
        a = 0.5 if name == "hann" else 0.54
        w = a + (1.0 - a) * np.cos(np.pi * u)
    else:  # pragma: no cover - _check rejects unknown names
        raise AssertionError(name)
    return np.where(inside, w, 0.0)


def default_extent(name: str, spacing_nm: float, step_nm: float) -> int:
    """An odd extent (in dense samples) giving the filter its natural width for
    nodes ``spacing_nm`` apart on a grid of step ``step_nm`` (at least 3).

    Examples
    --------
    >>> default_extent("box", 25.0, 5.0), default_extent("mitchell", 25.0, 5.0)
    (5, 21)
    """
    if name not in FILTERS:
        raise ValueError(f"unknown filter {name!r}; accepted: {', '.join(FILTERS)}")
    e = int(round(_DEFAULT_SPAN[name] * spacing_nm / step_nm))
    e = max(e, 3)
    return e if e % 2 == 1 else e + 1


def lowpass_matrix(nodes_nm, wavelengths, name: str, extent: float | None = None,
                   spacing_nm: float | None = None, edge: str = "zero", **params) -> np.ndarray:
    """``(n, N)`` matrix: row ``i`` low-pass filters a spectrum on ``wavelengths``
    and reads it at ``nodes_nm[i]`` (Kment's ideal sampling rate conversion,
    Fig. 4.2 and eq. 4.4; windows eq. 4.13-4.19).

    Parameters
    ----------
    nodes_nm : array_like, shape (n,)
        Where the filtered spectrum is read.
    wavelengths : array_like, shape (N,)
        The dense, regular grid the spectra are given on.
    name : str
        Filter name (:func:`filter_names`).
    extent : float, optional
        Window extent in dense samples; default :func:`default_extent` for
        ``spacing_nm`` (the node spacing, default the mean node spacing).
    edge : {"zero", "renormalise"}
        ``"zero"`` (Kment): values outside the grid are 0, each row is divided
        by the window's sum over the infinite lattice, so rows near the ends
        sum to less than 1. ``"renormalise"``: each row sums to 1.
    **params
        Filter parameters (``alpha``, ``b``, ``c``, ``tau``).

    Raises
    ------
    ValueError
        Irregular grid, unknown filter or parameter, bad extent or a window
        whose weights sum to zero (e.g. a Mitchell (b, c) that cancels).

    Examples
    --------
    >>> wl = np.arange(380.0, 781.0, 5.0)
    >>> A = lowpass_matrix([500.0, 600.0], wl, "box", extent=5)
    >>> A.sum(axis=1).round(12).tolist(), int((A[0] > 0).sum())
    ([1.0, 1.0], 5)
    """
    wl = np.asarray(wavelengths, dtype=float)
    nodes = np.atleast_1d(np.asarray(nodes_nm, dtype=float))
    if wl.ndim != 1 or wl.size < 2:
        raise ValueError("filters need a grid of at least two wavelengths")
    d = np.diff(wl)
    if not np.allclose(d, d[0], rtol=1e-9, atol=1e-9) or d[0] <= 0:
        raise ValueError("low-pass filters need a regular, increasing wavelength grid")
    step = float(d[0])
    if edge not in ("zero", "renormalise"):
        raise ValueError(f"edge must be 'zero' or 'renormalise', not {edge!r}")
    if extent is None:
        if spacing_nm is None:
            spacing_nm = float(np.mean(np.diff(nodes))) if nodes.size > 1 else float(wl[-1] - wl[0])
        extent = default_extent(name, spacing_nm, step)
    p = _check(name, params)
    pos = (nodes - wl[0]) / step  # node positions in samples
    offsets = pos[:, None] - np.arange(wl.size)[None, :]
    A = filter_window(name, offsets, extent, **p)
    # window sum over the whole (infinite, zero-padded) lattice at each node's phase
    reach = int(np.ceil(extent / 2.0)) + 1
    frac = pos - np.floor(pos)
    m = np.arange(-reach, reach + 1)
    lattice = filter_window(name, frac[:, None] - m[None, :], extent, **p).sum(axis=1)
    norm = A.sum(axis=1) if edge == "renormalise" else lattice
    if np.any(np.abs(norm) < 1e-12):
        raise ValueError(f"filter {name!r} with extent {extent} and {p} has zero DC gain")
    return A / norm[:, None]
