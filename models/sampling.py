"""Wavelength sampling and spectral representation behind one interface.

A *rule* turns a spectrum given on a dense wavelength grid into ``n``
coefficients and back, and says how to integrate a product of spectra against
colour-matching functions with those ``n`` numbers. Every strategy (uniform
point sampling, Riemann sums, Fourier, PCA, sharpened PCA, composite
smooth-plus-spikes, Gaussian quadrature, quasi-Gaussian shared-abscissa rules)
is a :class:`SpectralRule`, so synthesis code does not need to know which one
it holds.

The tristimulus integral the rules approximate is (Wandell 1985, eq. 22-23;
Meyer 1988, eq. 1)

    T_k = sum_lambda E(lambda) S(lambda) xbar_k(lambda) dlambda .

A rule approximates ``S`` (and, when the light is represented too, ``E``) with
``n`` coefficients ``c``, so that ``T ~= c @ M`` with an ``(n, 3)`` matrix ``M``
built once per light (:meth:`SpectralRule.tristimulus_matrix`).

The registry :data:`STRATEGIES` (end of this module) names every strategy,
those built here and those of :mod:`models.sharpening`,
:mod:`models.quadrature` and :mod:`models.band_selection`;
:func:`sampling_rule` builds any of them by name.

References
----------
Meyer (1988) [docs/references.md#seed-000]; Kment (2011)
[docs/references.md#seed-001]; Drew and Finlayson (2003)
[docs/references.md#seed-003]; Borges (1992) [docs/references.md#seed-004].
"""

from __future__ import annotations

import numpy as np

from .band_selection import wiener_points_rule
from .grid import wavelength_step
from .quadrature import gauss_ac1c2_rule, quasi_gauss_xyz_rule
from .sharpening import sharpened_rule
from .spectral_rule import SpectralRule, interpolation_matrix

__all__ = ["SpectralRule", "STRATEGIES", "LIGHT_AWARE", "strategy_names", "sampling_rule", "uniform_nodes",
           "uniform_rule", "riemann_rule", "fourier_terms", "fourier_rule", "pca_rule", "detect_spikes",
           "composite_rule"]


def _check_n(strategy: str, n, minimum: int = 1, maximum: int | None = None) -> int:
    """``n`` as an int in range, or a ValueError naming the strategy and the bounds."""
    if n is None or isinstance(n, bool):
        raise ValueError(f"{strategy} needs n, the number of coefficients (>= {minimum})")
    try:
        k = int(n)
    except (TypeError, ValueError):
        raise ValueError(f"{strategy}: n must be an integer, not {n!r}") from None
    if k != n or k < minimum or (maximum is not None and k > maximum):
        upper = f" and <= {maximum}" if maximum is not None else ""
        raise ValueError(f"{strategy}: n must be an integer >= {minimum}{upper}, not {n!r}")
    return k


def _grid(wavelengths) -> np.ndarray:
    wl = np.asarray(wavelengths, dtype=float)
    if wl.ndim != 1 or wl.size < 2 or not np.all(np.isfinite(wl)) or np.any(np.diff(wl) <= 0):
        raise ValueError("wavelengths must be a strictly increasing list of at least two finite values")
    return wl


def uniform_nodes(n: int, wavelengths: np.ndarray, placement: str = "centres") -> np.ndarray:
    """``n`` equally spaced point-sampling wavelengths over the grid's range.

    ``placement="centres"``: the centres of ``n`` equal sub-intervals.
    ``placement="endpoints"``: Kment's convention (2011, sec. 6.1: "any number
    of sample points includes start- and endpoints"), ``linspace(lo, hi, n)``.

    Examples
    --------
    >>> uniform_nodes(3, np.array([400.0, 700.0])).tolist()
    [450.0, 550.0, 650.0]
    >>> uniform_nodes(3, np.array([400.0, 700.0]), "endpoints").tolist()
    [400.0, 550.0, 700.0]
    """
    wl = _grid(wavelengths)
    lo, hi = float(wl[0]), float(wl[-1])
    if placement == "centres":
        return lo + (hi - lo) / n * (np.arange(n) + 0.5)
    if placement == "endpoints":
        return np.array([0.5 * (lo + hi)]) if n == 1 else np.linspace(lo, hi, n)
    raise ValueError(f"placement must be 'centres' or 'endpoints', not {placement!r}")


def uniform_rule(n: int | None, wavelengths: np.ndarray, filter: str | None = None,
                 extent: float | None = None, placement: str = "centres", edge: str = "zero",
                 cmf: str = "nodes", **filter_params) -> SpectralRule:
    """Point sampling at ``n`` equally spaced wavelengths (Kment 2011, sec. 5.4
    "Point sampling"; low-pass prefilter: sec. 4.4-4.5, Tables A.1, A.2, 7.1).

    Nodes sit at the centres of ``n`` equal sub-intervals of the grid's range
    (``placement="endpoints"``: Kment's nodes, both ends included). Without a
    filter the spectrum is read there by linear interpolation; with
    ``filter`` (one of :func:`models.filters.filter_names`) it is first
    low-passed (Kment's ideal sampling rate conversion,
    :func:`models.filters.lowpass_matrix`). It is rebuilt as the
    piecewise-linear curve through the nodes (constant beyond the end nodes).
    Products of spectra are products of samples, so the rule is
    multiplicative. Tristimulus values are ``sum_i E_i S_i cmf(node_i) w_i``
    (``cmf="nodes"``: the CMFs are point-sampled too, ``w_i`` the integral of
    node ``i``'s hat function) or the rebuilt curve integrated against the
    dense CMFs (``cmf="dense"``).

    Parameters
    ----------
    n : int
        Number of samples (>= 1, at most the number of grid wavelengths).
    wavelengths : ndarray, shape (N,)
        Dense grid (nm).
    filter : str, optional
        Low-pass filter applied before sampling (needs a regular grid).
    extent : float, optional
        Filter extent in dense samples (Kment: odd, 3 to 21); default
        :func:`models.filters.default_extent` for the node spacing.
    placement : {"centres", "endpoints"}
        Node placement, see :func:`uniform_nodes`.
    edge : {"zero", "renormalise"}
        How the filter treats the ends of the grid (Kment: zero outside).
    cmf : {"nodes", "dense"}
        How the colour-matching functions enter (see above). ``"nodes"``
        reproduces Kment's point-sampling figures (Tables 6.1, 6.2) far
        better than ``"dense"``: his PS16 under FL2/FL7/FL11 is 11.2, ours
        12.3 with ``"nodes"``.
    **filter_params
        ``alpha`` (gauss), ``b``, ``c`` (mitchell), ``tau`` (lanczos).

    Examples
    --------
    >>> wl = np.arange(380.0, 781.0, 5.0)
    >>> r = uniform_rule(16, wl, filter="mitchell", extent=19, b=-0.4, c=1.0)
    >>> r.n, r.multiplicative, r.diagnostics["filter"]
    (16, True, 'mitchell')
    """
    from .filters import lowpass_matrix

    wl = _grid(wavelengths)
    n = _check_n("uniform", n, 1, wl.size)
    nodes = uniform_nodes(n, wl, placement)
    width = float(nodes[1] - nodes[0]) if n > 1 else float(wl[-1] - wl[0])
    diagnostics = {"spacing_nm": width, "placement": placement, "filter": filter}
    if filter is None:
        if filter_params or extent is not None:
            raise ValueError("filter parameters (extent, alpha, b, c, tau) need filter=<name>")
        analysis = interpolation_matrix(nodes, wl)
    else:
        analysis = lowpass_matrix(nodes, wl, filter, extent=extent, spacing_nm=width, edge=edge,
                                  **filter_params)
        from .filters import default_extent
        diagnostics["extent"] = float(extent if extent is not None
                                      else default_extent(filter, width, float(wl[1] - wl[0])))
        diagnostics.update({k: float(v) for k, v in filter_params.items()})
    if n == 1:
        synthesis = np.ones((wl.size, 1))
    else:
        synthesis = interpolation_matrix(wl, nodes)
    node_weights = synthesis.T @ wavelength_step(wl)  # nm each node stands for (sums to the range)
    if cmf == "nodes":
        integration = node_weights[:, None] * interpolation_matrix(nodes, wl)
    elif cmf == "dense":
        integration = None
    else:
        raise ValueError(f"cmf must be 'nodes' or 'dense', not {cmf!r}")
    diagnostics["cmf"] = cmf
    return SpectralRule("uniform", wl, analysis, synthesis, nodes_nm=nodes, weights=node_weights,
                        multiplicative=True, diagnostics=diagnostics, integration=integration)


def _cell_edges(wl: np.ndarray) -> np.ndarray:
    """Edges of the cells each dense sample stands for (half-way to neighbours)."""
    e = np.empty(wl.size + 1)
    e[1:-1] = 0.5 * (wl[1:] + wl[:-1])
    e[0] = wl[0] - 0.5 * (wl[1] - wl[0])
    e[-1] = wl[-1] + 0.5 * (wl[-1] - wl[-2])
    return e


def _bin_overlap(bin_edges: np.ndarray, wl: np.ndarray) -> np.ndarray:
    """``(n, N)`` length (nm) of dense cell ``k`` that lies in bin ``j``."""
    c = _cell_edges(wl)
    lo = np.maximum(bin_edges[:-1, None], c[None, :-1])
    hi = np.minimum(bin_edges[1:, None], c[None, 1:])
    return np.clip(hi - lo, 0.0, None)


def riemann_rule(n: int | None, wavelengths: np.ndarray) -> SpectralRule:
    """Riemann sums: the mean of the spectrum over ``n`` equal wavelength bins
    (Kment 2011, sec. 5.4 "Riemann summations", eq. 5.3; Peercy 1993).

    The bins tile the range the dense samples stand for (each sample covers
    half-way to its neighbours), so the integral of the rebuilt, piecewise
    constant spectrum equals the dense sum ``sum_l s(l) dl`` exactly: the
    "area under the function" Kment credits for Riemann sums' robustness to
    spiky lights. Coefficients are bin means; products of spectra are
    element-wise products of the means (Kment: "realized in the same way as in
    methods utilizing point sampling"), so the rule is multiplicative, an
    approximation whose error is the within-bin covariance of the factors.

    Examples
    --------
    >>> wl = np.arange(400.0, 701.0, 10.0)
    >>> r = riemann_rule(4, wl)
    >>> s = np.linspace(0.1, 0.9, wl.size)
    >>> bool(np.isclose(r.reconstruct(r.coefficients(s)).sum(), s.sum()))
    True
    """
    wl = _grid(wavelengths)
    n = _check_n("riemann", n, 1, wl.size)
    c = _cell_edges(wl)
    edges = np.linspace(c[0], c[-1], n + 1)
    ov = _bin_overlap(edges, wl)                      # (n, N) nm
    analysis = ov / np.diff(edges)[:, None]           # bin means
    cell = np.diff(c)
    synthesis = (ov / cell[None, :]).T                # (N, n): fraction of each cell in each bin
    centres = 0.5 * (edges[1:] + edges[:-1])
    return SpectralRule("riemann", wl, analysis, synthesis, nodes_nm=centres, weights=np.diff(edges),
                        multiplicative=True,
                        diagnostics={"bin_width_nm": float(edges[1] - edges[0])})


def fourier_terms(n: int, wavelengths: np.ndarray) -> np.ndarray:
    """``(N, n)`` trigonometric terms ``1, cos x, sin x, cos 2x, sin 2x, ...``
    with ``x = 2 pi (lambda - lambda_0) / (lambda_N - lambda_0)`` (Kment 2011,
    eq. 4.6-4.9: ``a_0, a_k, b_k``; ``n = 5`` is ``a_0, a_1, b_1, a_2, b_2``)."""
    wl = _grid(wavelengths)
    x = 2 * np.pi * (wl - wl[0]) / (wl[-1] - wl[0])
    cols = [np.ones_like(wl)]
    k = 1
    while len(cols) < n:
        cols.append(np.cos(k * x))
        if len(cols) < n:
            cols.append(np.sin(k * x))
        k += 1
    return np.stack(cols, 1)


def _least_squares_rule(strategy: str, wl: np.ndarray, basis: np.ndarray, diagnostics: dict) -> SpectralRule:
    """Rule with ``synthesis = basis`` and least-squares analysis (``pinv``)."""
    sv = np.linalg.svd(basis, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")
    if not np.isfinite(cond) or cond > 1e12:
        raise ValueError(f"{strategy}: basis is rank deficient on this grid (condition {cond:.3g})")
    diagnostics = dict(diagnostics, basis_condition=cond)
    return SpectralRule(strategy, wl, np.linalg.pinv(basis), basis, diagnostics=diagnostics)


def fourier_rule(n: int | None, wavelengths: np.ndarray) -> SpectralRule:
    """Truncated Fourier series, minimal quadratic error (Kment 2011, sec. 4.3,
    eq. 4.7 and 4.9; Sun 2000).

    Coefficients are ``a_0, a_1, b_1, a_2, b_2, ...`` of one period across the
    grid's range (:func:`fourier_terms`), fitted by least squares on the dense
    grid. Products are formed on the dense grid (reconstruct, multiply,
    project: Sun et al. 1999 multiply in the point-sampled domain), so the
    rule is not multiplicative.

    Examples
    --------
    >>> wl = np.arange(380.0, 781.0, 5.0)
    >>> r = fourier_rule(5, wl)
    >>> s = 0.5 + 0.2 * np.cos(2 * np.pi * (wl - 380) / 400)
    >>> r.coefficients(s).round(6).tolist()
    [0.5, 0.2, 0.0, 0.0, 0.0]
    """
    wl = _grid(wavelengths)
    n = _check_n("fourier", n, 1, wl.size - 1)
    return _least_squares_rule("fourier", wl, fourier_terms(n, wl), {"terms": n})


def pca_rule(n: int | None, wavelengths: np.ndarray, training="all", centred: bool = False) -> SpectralRule:
    """Principal components of a training set (Kment 2011, sec. 5.4 "Linear
    methods"; Peercy 1993; Wandell 1985, eq. 6 and 11).

    Parameters
    ----------
    training : str or ndarray
        A reflectance set name (:func:`models.reflectance_set`) or spectra as
        rows on ``wavelengths``. Kment's caveat holds: the basis needs prior
        knowledge of the scene's spectra; a light is not in a reflectance basis,
        so evaluate with the light kept exact (``represent_light=False``).
    centred : bool
        False (default): basis through the origin (uncentred SVD).

    Examples
    --------
    >>> wl = np.arange(400.0, 701.0, 10.0)
    >>> pca_rule(6, wl).diagnostics["energy_captured"] > 0.99
    True
    """
    from .bases import pca_model, surface_pca_model
    from .reflectances import reflectance_set_names

    wl = _grid(wavelengths)
    if isinstance(training, str):
        if training not in reflectance_set_names():
            raise ValueError(f"pca: unknown training set {training!r}; accepted: {reflectance_set_names()}")
        n = _check_n("pca", n, 1, wl.size)
        try:
            model = surface_pca_model(n, wl, training, centred)  # cached per grid and set
        except ValueError as exc:
            raise ValueError(f"pca: {exc}") from None
        size = None
    else:
        samples = np.asarray(training, dtype=float)
        if samples.ndim != 2 or samples.shape[1] != wl.size or not np.all(np.isfinite(samples)):
            raise ValueError(f"pca: training must be finite spectra as rows of {wl.size} values")
        n = _check_n("pca", n, 1, min(samples.shape))
        model = pca_model(samples, n, wl, centred=centred)
        size = int(samples.shape[0])
    if centred:
        # the mean is an extra synthesis function: n coefficients = mean weight + n-1 components
        basis = np.column_stack([model.mean, model.basis[:, : n - 1]])
    else:
        basis = model.basis
    return _least_squares_rule("pca", wl, basis, {
        "energy_captured": float(np.sum(model.explained_variance)), "training_size": size})


# --- composite: smooth part plus spikes (Sun 2000; Kment's enhanced Riemann) ------

def detect_spikes(spectrum, wavelengths, threshold: float = 0.2, max_width_nm: float = 40.0,
                  min_peak: float = 0.05) -> list[np.ndarray]:
    """Narrow peaks of a spectrum found by relative slope (Deville et al. 1994,
    as Kment 2011 uses it, sec. 5.4 "Composite methods" and 6.1).

    A peak starts where the relative rise ``(s[i] - s[i-1]) / s[i-1]`` exceeds
    ``threshold`` (Kment: 0.2 for enhanced Riemann, 0.3 for Sun's composite)
    and climbs to its top; its samples are those reached from the top by steep
    relative steps, down the rise (``(s[k] - s[k-1]) / s[k-1] > threshold``)
    and down the fall (``(s[j] - s[j+1]) / s[j+1] > threshold``), the bases
    either side excluded. Peaks whose top is below ``min_peak`` times the
    spectrum's maximum are dropped (our addition: at 5 nm a 20 % relative
    slope also fires on the noise of near-zero tails, e.g. FL11 above 750 nm,
    which carries no colour but would cost storage). Rises with no steep fall (edges)
    and peaks wider than ``max_width_nm`` are smooth structure, not spikes.

    Returns
    -------
    list of ndarray
        Index groups (contiguous dense-grid indices) of the peaks.

    Examples
    --------
    >>> wl = np.arange(400.0, 451.0, 5.0)
    >>> s = np.ones(wl.size); s[4] = 6.0
    >>> [g.tolist() for g in detect_spikes(s, wl)]
    [[4]]
    """
    s = np.asarray(spectrum, dtype=float)
    wl = _grid(wavelengths)
    if s.shape != wl.shape or not np.all(np.isfinite(s)):
        raise ValueError("detect_spikes: spectrum must be finite and match the wavelengths")
    if not threshold > 0:
        raise ValueError("detect_spikes: threshold must be > 0")
    floor = 1e-6 * max(float(np.max(np.abs(s))), 1e-300)
    rel = lambda a, b: (a - b) / max(b, floor)  # noqa: E731
    peak_max = float(np.max(s))
    groups, i, N = [], 1, s.size
    while i < N:
        if rel(s[i], s[i - 1]) > threshold:
            top = i
            while top + 1 < N and s[top + 1] >= s[top]:
                top += 1
            left = top  # walk down the steep rise: left ends on the base before the peak
            while left - 1 >= i - 1 and rel(s[left], s[left - 1]) > threshold:
                left -= 1
            j = top  # walk down the steep fall: j ends on the base after the peak
            while j + 1 < N and rel(s[j], s[j + 1]) > threshold:
                j += 1
            if left < top and j > top:
                idx = np.arange(left + 1, j)
                if wl[idx[-1]] - wl[idx[0]] <= max_width_nm and s[top] >= min_peak * peak_max:
                    groups.append(idx)
            i = max(j, top) + 1
            continue
        i += 1
    return groups


def _spike_groups_for(light, wl, threshold, max_width_nm, min_peak):
    from .illuminants import illuminant

    lights = [light] if isinstance(light, str) or np.ndim(light) == 1 else list(light)
    mask = np.zeros(wl.size, dtype=bool)
    for e in lights:
        e = illuminant(e, wl) if isinstance(e, str) else np.asarray(e, dtype=float)
        for g in detect_spikes(e, wl, threshold, max_width_nm, min_peak):
            mask[g] = True
    # contiguous runs of the union
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return []
    return np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)


def composite_rule(n: int | None, wavelengths: np.ndarray, smooth: str = "riemann", light=None,
                   spikes_nm=None, threshold: float | None = None,
                   max_width_nm: float = 40.0, min_peak: float = 0.05) -> SpectralRule:
    """Smooth part plus spikes (Sun 2000, Sun et al. 1999: Fourier smooth part,
    Kment's "CS"; Kment 2011 sec. 5.5: Riemann smooth part, "enhanced Riemann
    summations", "RE").

    The spikes are the narrow emission lines of the scene's light(s), found
    with :func:`detect_spikes` (or given as ``spikes_nm``). Every spectrum is
    stored as ``n_smooth`` coefficients of its smooth part (the spectrum with
    the line samples replaced by a straight line between the samples either
    side) plus its values at the ``n_spikes`` line samples; ``n = n_smooth +
    n_spikes`` is the storage. A reflectance is thus sampled exactly where
    the light has lines, and the product keeps each line's energy times the
    reflectance there. With no lines the rule is its smooth rule (Kment: "it
    may revert to standard Riemann summations").

    Parameters
    ----------
    n : int
        Total coefficients (smooth + spikes); must leave ``n_smooth >= 1``.
    smooth : {"riemann", "fourier"}
        Smooth representation: Riemann sums (enhanced Riemann: the product of
        two spectra is element-wise, the rule is multiplicative) or Fourier
        (Sun's composite; products on the dense grid).
    light : str, ndarray or list, optional
        Light name(s) or spectra on ``wavelengths`` whose lines are kept.
    spikes_nm : sequence of float, optional
        Line wavelengths given directly (each snapped to the nearest sample).
    threshold : float, optional
        Relative slope for peak detection; default 0.2 (riemann) or 0.3
        (fourier), Kment sec. 6.1.
    max_width_nm, min_peak : float
        Passed to :func:`detect_spikes`.

    Examples
    --------
    >>> wl = np.arange(380.0, 781.0, 5.0)
    >>> r = composite_rule(20, wl, light="FL2")
    >>> r.diagnostics["n_spikes"] + r.diagnostics["n_smooth"] == r.n == 20
    True
    """
    wl = _grid(wavelengths)
    if smooth not in ("riemann", "fourier"):
        raise ValueError(f"composite: smooth must be 'riemann' or 'fourier', not {smooth!r}")
    thr = (0.2 if smooth == "riemann" else 0.3) if threshold is None else float(threshold)
    if spikes_nm is not None:
        sp = np.atleast_1d(np.asarray(spikes_nm, dtype=float))
        if sp.size and (not np.all(np.isfinite(sp)) or sp.min() < wl[0] or sp.max() > wl[-1]):
            raise ValueError(f"composite: spikes_nm must lie in [{wl[0]:g}, {wl[-1]:g}] nm")
        idx = np.unique(np.abs(wl[None, :] - sp[:, None]).argmin(axis=1)) if sp.size else np.array([], int)
        groups = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1) if idx.size else []
    elif light is not None:
        groups = _spike_groups_for(light, wl, thr, max_width_nm, min_peak)
    else:
        groups = []
    line_idx = np.concatenate(groups) if groups else np.array([], dtype=int)
    n_spikes = int(line_idx.size)
    if n_spikes and n is not None and not isinstance(n, bool) and isinstance(n, (int, np.integer)) \
            and n_spikes < wl.size and n < n_spikes + 1:
        raise ValueError(f"composite: n={n} cannot hold the light's {n_spikes} line samples plus a "
                         f"smooth part; need n >= {n_spikes + 1}")
    n = _check_n("composite", n, n_spikes + 1, wl.size)
    n_smooth = n - n_spikes
    base = riemann_rule(n_smooth, wl) if smooth == "riemann" else fourier_rule(n_smooth, wl)
    N = wl.size
    # P: spectrum -> its smooth part (line samples bridged by straight lines)
    P = np.eye(N)
    for g in groups:
        lo, hi = g[0] - 1, g[-1] + 1
        lo_ok, hi_ok = lo >= 0, hi < N
        for k in g:
            P[k] = 0.0
            if lo_ok and hi_ok:
                t = (wl[k] - wl[lo]) / (wl[hi] - wl[lo])
                P[k, lo], P[k, hi] = 1.0 - t, t
            elif lo_ok:
                P[k, lo] = 1.0
            elif hi_ok:
                P[k, hi] = 1.0
    pick = np.zeros((n_spikes, N))
    pick[np.arange(n_spikes), line_idx] = 1.0
    keep = np.ones(N)
    keep[line_idx] = 0.0
    smooth_analysis = base.analysis @ P
    if smooth == "riemann" and n_spikes:
        # bin means over the cells that are not lines, so that the rebuilt smooth
        # part keeps its area exactly (the lines carry theirs); a bin made of line
        # cells only falls back to the bridged smooth part
        c = _cell_edges(wl)
        edges = np.linspace(c[0], c[-1], n_smooth + 1)
        ov = _bin_overlap(edges, wl) * keep[None, :]
        width = ov.sum(axis=1)
        ok = width > 0
        smooth_analysis[ok] = ov[ok] / width[ok, None]
    analysis = np.vstack([smooth_analysis, pick])
    synthesis = np.hstack([base.synthesis * keep[:, None], pick.T])
    nodes = np.concatenate([base.nodes_nm if base.nodes_nm is not None else np.array([]), wl[line_idx]])
    return SpectralRule("composite", wl, analysis, synthesis,
                        nodes_nm=nodes if smooth == "riemann" else wl[line_idx],
                        multiplicative=(smooth == "riemann"),
                        diagnostics={"smooth": smooth, "n_smooth": n_smooth, "n_spikes": n_spikes,
                                     "spikes_nm": [float(v) for v in wl[line_idx]],
                                     "threshold": thr, **{f"smooth_{k}": v for k, v in base.diagnostics.items()}})


# --- the registry ------------------------------------------------------------------
#
# Every strategy, by name: a builder ``builder(n, wavelengths, **options)``
# returning a SpectralRule. The builders are imported above by name, so the
# registry is complete when this module is imported and nothing is loaded by
# name at run time.

STRATEGIES = {
    "uniform": uniform_rule,
    "riemann": riemann_rule,
    "fourier": fourier_rule,
    "pca": pca_rule,
    "composite": composite_rule,
    "sharpened": sharpened_rule,
    "gauss-ac1c2": gauss_ac1c2_rule,
    "quasi-gauss-xyz": quasi_gauss_xyz_rule,
    "wiener-points": wiener_points_rule,
}

#: Strategies whose rule is made for the light at hand (bands chosen for it).
#: They model surfaces only: a renderer keeps the light exact
#: (:func:`recovery.spectral.render_spectra`).
LIGHT_AWARE = frozenset({"wiener-points"})


def strategy_names(light_aware: bool = False) -> list[str]:
    """Names of the strategies, in registry order.

    By default the ones that make one rule for any light (those
    :func:`sampling_rule` compares on equal terms, e.g. in Kment's
    evaluation); ``light_aware=True`` adds those of :data:`LIGHT_AWARE`.
    """
    return [name for name in STRATEGIES if light_aware or name not in LIGHT_AWARE]


def sampling_rule(strategy: str, n: int | None = None, wavelengths=None, **options) -> SpectralRule:
    """Build the rule ``strategy`` with ``n`` coefficients on ``wavelengths``.

    Raises ``ValueError`` naming the accepted strategies for an unknown name.
    """
    from .grid import DEFAULT_WAVELENGTHS

    if strategy not in STRATEGIES:
        raise ValueError(f"unknown sampling strategy {strategy!r}; accepted: {', '.join(STRATEGIES)}")
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, dtype=float)
    return STRATEGIES[strategy](n, wl, **options)
