"""Spectral sharpening: products of spectra as products of coefficients.

Drew and Finlayson (2003) [docs/references.md#seed-003] take the principal components ``Q``
(``N x n``) of a representative set of spectra (lights, reflectances and the
colour signals they make) and transform them, ``Q~ = Q T``, so that each new
basis function is as narrow-band as the span allows: column ``k`` puts as
much of its energy as possible inside a band ``phi_k`` of the spectrum
(their eq. 10-13, the sharpening of Finlayson, Drew and Funt 1994). In the
sharp basis a spectrum ``C`` has coefficients ``c = Q~^T C`` and is rebuilt
as ``C^ = Q~^+ c`` with ``Q~^+ = Q~ (Q~^T Q~)^-1`` (eq. 20-24), and the
coefficients of a product of spectra are approximately the product of the
coefficients (eq. 5-9, 25-27):

    Q~^T diag(E) S ~= (Q~^T E) * (Q~^T S) / w ,   w = Q~^T 1 .

This module scales every sharp column to unit sum (``w = 1``), so the
diagonal model needs no division: relighting is ``c * e_new / e_old`` and a
``k``-bounce interreflection ``R^k E`` is ``r**k * e`` (their Fig. 2 and 6,
Tables 1-5).

The seed lists its 29 displayed equations without numbers; "eq. k" here
counts them in the seed's order (eq. 5-9 the diagonal product model, 10-14
sharpening, 15-19 relighting, 20-24 coefficients and reconstruction, 25-27
products, 28-29 sensor responses from coefficients).

The sharpening bands are not given in the paper's abstract; here they
partition the grid into ``n`` contiguous bands whose edges are chosen by
coordinate descent to minimise the product error on the training products
(``optimise=True``), starting from equal widths.

References
----------
Drew, M. S. and Finlayson, G. D. (2003). Multispectral processing without
spectra. JOSA A 20(7) [docs/references.md#seed-003]. Finlayson, G. D.,
Drew, M. S. and Funt, B. V. (1994). Spectral sharpening: sensor
transformations for improved color constancy. JOSA A 11, 1553-1563.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from .grid import DEFAULT_WAVELENGTHS, wavelength_step
from .spectral_rule import SpectralRule

__all__ = [
    "DEFAULT_N",
    "DEFAULT_TRAINING_LIGHTS",
    "RELIGHT_MIN_BAND",
    "SharpenedBasis",
    "training_spectra",
    "band_transform",
    "sharpened_basis",
    "sharpened_rule",
    "pca_product_rule",
    "relight",
    "multibounce",
    "product_errors",
]

#: Default number of sharp basis functions: the paper's "specialized
#: seven-dimensional basis" (Drew and Finlayson 2003, Table 4).
DEFAULT_N = 7

#: Lights of the default training set: colour-science's smooth CIE
#: illuminants (tungsten A, the B and C simulators, the D series, equal
#: energy). Spiky lights (the FL series) need more coefficients than a
#: sharpened basis of a few functions has; train on them explicitly.
DEFAULT_TRAINING_LIGHTS = ("A", "B", "C", "D50", "D55", "D60", "D65", "D75", "E")

#: :func:`relight` refuses a light whose coefficient in some band is below
#: this fraction of its largest: the ratio ``e' / e`` would multiply that
#: band's representation error by more than ``1 / RELIGHT_MIN_BAND``.
RELIGHT_MIN_BAND = 0.01


@dataclass(frozen=True)
class SharpenedBasis:
    """A sharpened PCA basis (Drew and Finlayson 2003, eq. 10-14, 20-24).

    Attributes
    ----------
    wavelengths : ndarray, shape (N,)
    basis : ndarray, shape (N, n)
        Sharp basis ``Q~ = Q T`` with each column scaled to unit sum, so the
        coefficients ``Q~^T C`` of a spectrum are weighted band averages and
        the constant spectrum 1 has coefficients 1 (``w = Q~^T 1 = 1``).
    pca : ndarray, shape (N, n)
        The orthonormal principal components ``Q`` it was made from.
    transform : ndarray, shape (n, n)
        ``T`` with ``basis = pca @ T`` (columns of unit norm before scaling).
    band_edges_nm : ndarray, shape (n + 1,)
        Edges of the sharpening bands ``phi_k`` (between grid samples).
    diagnostics : dict
        ``condition_transform`` (of ``T``), ``condition_basis`` (of ``Q~``),
        ``in_band_energy`` (per function, fraction of its energy inside its
        band), ``negative_lobe`` (per function, most negative value over the
        maximum), ``explained_energy`` (of the PCA), and the training product
        errors (see :func:`product_errors`).
    """

    wavelengths: np.ndarray
    basis: np.ndarray
    pca: np.ndarray
    transform: np.ndarray
    band_edges_nm: np.ndarray
    diagnostics: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of basis functions."""
        return int(self.basis.shape[1])


def _unit_rows(x: np.ndarray) -> np.ndarray:
    norm = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, norm, out=np.zeros_like(x), where=norm > 0)


def training_spectra(lights: np.ndarray, reflectances: np.ndarray, bounces: int = 2) -> np.ndarray:
    """Spectra the PCA is taken of: lights, reflectances and colour signals.

    Drew and Finlayson (2003, abstract and Table 4) take the principal
    components of "a representative set of spectra": here the lights, the
    reflectances and the colour signals ``E R^k`` for ``k = 1..bounces``
    (one and more interreflections, their Fig. 2 and 6). Every spectrum is
    scaled to unit norm so that neither the bright lights nor the dark
    surfaces dominate.

    Parameters
    ----------
    lights : ndarray, shape (L, N)
    reflectances : ndarray, shape (M, N)
    bounces : int
        Highest power of the reflectance in the colour signals.

    Returns
    -------
    ndarray, shape (L + M + bounces * L * M, N)
    """
    lights = np.atleast_2d(np.asarray(lights, dtype=float))
    reflectances = np.atleast_2d(np.asarray(reflectances, dtype=float))
    parts = [_unit_rows(lights), _unit_rows(reflectances)]
    for k in range(1, int(bounces) + 1):
        signals = (lights[:, None, :] * reflectances[None, :, :] ** k).reshape(-1, lights.shape[1])
        parts.append(_unit_rows(signals))
    return np.concatenate(parts)


def _band_vector(pca: np.ndarray, start: int, stop: int, positive: bool) -> tuple[np.ndarray, float, bool]:
    """Sharpening vector ``t`` for the band of samples ``start <= i < stop``.

    Unconstrained (Drew and Finlayson 2003, eq. 11-13): with ``Q`` orthonormal,
    minimising ``sum_{outside} (Q t)^2`` subject to ``|t| = 1`` gives the top
    eigenvector of ``Q_in^T Q_in``; its eigenvalue is the fraction of the
    energy inside the band. With ``positive`` (eq. 14, Drew and Finlayson
    2000): the same objective and normalisation with ``Q t >= 0``, solved by
    SLSQP from a feasible start (the eigenvector plus enough of the first,
    positive, principal component). Returns ``(t, in_band_fraction, ok)``;
    ``ok`` is False when the constrained solver did not converge (the best
    feasible point is returned).
    """
    q_in = pca[start:stop]
    a_in = q_in.T @ q_in
    vals, vecs = np.linalg.eigh(a_in)
    t = vecs[:, -1]
    if (pca @ t).sum() < 0:
        t = -t
    f = pca @ t
    if not positive or f.min() >= -1e-12 * np.abs(f).max():
        return t, float(vals[-1]), True
    from scipy.optimize import minimize

    n = pca.shape[1]
    a_out = np.eye(n) - a_in
    first = pca[:, 0]
    if first.min() <= 0:
        raise ValueError("positivity needs a first principal component that is positive everywhere")
    # feasible start: t + alpha e_1 with alpha making Q t >= 0 everywhere
    alpha = np.max(-f / first) * 1.01
    x0 = t.copy()
    x0[0] += alpha
    x0 /= np.linalg.norm(x0)
    res = minimize(lambda x: x @ a_out @ x, x0, jac=lambda x: 2 * a_out @ x, method="SLSQP",
                   constraints=[{"type": "eq", "fun": lambda x: x @ x - 1.0, "jac": lambda x: 2 * x},
                                {"type": "ineq", "fun": lambda x: pca @ x, "jac": lambda x: pca}],
                   options={"maxiter": 200, "ftol": 1e-12})
    x = res.x / np.linalg.norm(res.x)
    ok = bool(res.success) and (pca @ x).min() >= -1e-8 * np.abs(pca @ x).max()
    if not ok:
        x = x0
    return x, float(x @ a_in @ x), ok


def band_transform(pca: np.ndarray, edges: np.ndarray, positive: bool = False,
                   _cache: dict | None = None) -> tuple[np.ndarray, np.ndarray, bool]:
    """Sharpening transform of an orthonormal basis for given bands.

    For band ``k`` (grid samples ``edges[k] <= i < edges[k+1]``) the
    combination ``t_k`` of the columns of ``Q`` minimises the energy outside
    the band subject to unit total energy (Drew and Finlayson 2003,
    eq. 10-13; Finlayson, Drew and Funt 1994), optionally with the sharp
    function kept nonnegative (eq. 14). Signs are fixed so each sharp
    function has a positive sum.

    Parameters
    ----------
    pca : ndarray, shape (N, n)
        Orthonormal columns.
    edges : array_like of int, shape (n + 1,)
        Increasing sample indices, ``edges[0] = 0``, ``edges[-1] = N``.
    positive : bool
        Add the constraint ``Q t_k >= 0``.

    Returns
    -------
    T : ndarray, shape (n, n)
        Unit-norm columns ``t_k``.
    in_band : ndarray, shape (n,)
        Fraction of each sharp function's energy inside its band.
    converged : bool
        False when a positivity-constrained solve did not converge.
    """
    edges = np.asarray(edges, dtype=int)
    n = pca.shape[1]
    T = np.empty((n, n))
    in_band = np.empty(n)
    converged = True
    for k in range(n):
        key = (int(edges[k]), int(edges[k + 1]))
        if _cache is not None and key in _cache:
            t, frac, ok = _cache[key]
        else:
            t, frac, ok = _band_vector(pca, key[0], key[1], positive)
            if _cache is not None:
                _cache[key] = (t, frac, ok)
        T[:, k] = t
        in_band[k] = frac
        converged = converged and ok
    return T, in_band, converged


def _analysis_synthesis(basis_unit_sum: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Analysis ``Q~^T`` and synthesis ``Q~^+ = Q~ (Q~^T Q~)^-1`` (eq. 20-24)."""
    analysis = basis_unit_sum.T.copy()
    synthesis = np.linalg.pinv(analysis)
    return analysis, synthesis


def _product_relative_errors(analysis, synthesis, lights, reflectances, bounces=1, accumulate=False):
    """Relative RMS error of the diagonal model for ``E R^k`` (one per pair)."""
    e = lights @ analysis.T
    r = reflectances @ analysis.T
    if accumulate:
        coeff = sum(e[:, None, :] * r[None, :, :] ** k for k in range(1, bounces + 1))
        true = sum(lights[:, None, :] * reflectances[None, :, :] ** k for k in range(1, bounces + 1))
    else:
        coeff = e[:, None, :] * r[None, :, :] ** bounces
        true = lights[:, None, :] * reflectances[None, :, :] ** bounces
    est = coeff @ synthesis.T
    num = np.linalg.norm(est - true, axis=-1).ravel()
    den = np.linalg.norm(true, axis=-1).ravel()
    return num[den > 0] / den[den > 0]


def _sharp_from_edges(pca, edges, positive=False, cache=None):
    T, in_band, ok = band_transform(pca, edges, positive, cache)
    q = pca @ T
    w = q.sum(axis=0)
    return T, in_band, q, w, ok


def _optimise_edges(pca, lights, reflectances, edges, positive=False, cache=None, sweeps=6):
    """Coordinate descent on the band edges: each interior edge in turn moves
    to the position that minimises the mean squared one-bounce product
    error on the training pairs; stops when a sweep changes nothing."""
    n = pca.shape[1]

    def cost(e):
        _, _, q, w, _ = _sharp_from_edges(pca, e, positive, cache)
        if np.any(np.abs(w) < 1e-9 * np.abs(q).sum(axis=0).max()):
            return np.inf
        a, s = _analysis_synthesis(q / w)
        err = _product_relative_errors(a, s, lights, reflectances, 1)
        return float(np.mean(err**2))

    edges = list(int(v) for v in edges)
    best = cost(edges)
    for _ in range(sweeps):
        changed = False
        for i in range(1, n):
            for cand in range(edges[i - 1] + 1, edges[i + 1]):
                if cand == edges[i]:
                    continue
                trial = edges.copy()
                trial[i] = cand
                c = cost(trial)
                if c < best - 1e-15:
                    best, edges, changed = c, trial, True
        if not changed:
            break
    return np.asarray(edges, dtype=int)


def _check_n(n, limit: int, what: str) -> int:
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        if isinstance(n, float) and float(n).is_integer():
            n = int(n)
        else:
            raise ValueError(f"n must be a whole number of basis functions, not {n!r}")
    n = int(n)
    if not 1 <= n <= limit:
        raise ValueError(f"n = {n} is outside 1..{limit}: {what}")
    return n


def _default_training(wl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    from .illuminants import illuminants
    from .reflectances import reflectance_set

    return illuminants(DEFAULT_TRAINING_LIGHTS, wl), reflectance_set("all", wl)


def _edges_from_nm(band_edges_nm, wl: np.ndarray, n: int) -> np.ndarray:
    e_nm = np.asarray(band_edges_nm, dtype=float).ravel()
    if e_nm.size != n + 1 or not np.all(np.isfinite(e_nm)) or np.any(np.diff(e_nm) <= 0):
        raise ValueError(f"band_edges_nm must be {n + 1} increasing wavelengths (nm) for n = {n}")
    idx = np.searchsorted(wl, e_nm, side="left")
    idx[0], idx[-1] = 0, wl.size
    if np.any(np.diff(idx) <= 0):
        raise ValueError("band_edges_nm leave a band with no grid sample in it")
    return idx


def _edge_nm(wl: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Band edges in nm: half-way between the samples either side."""
    out = np.empty(idx.size)
    for j, i in enumerate(idx):
        if i <= 0:
            out[j] = wl[0] - (wl[1] - wl[0]) / 2
        elif i >= wl.size:
            out[j] = wl[-1] + (wl[-1] - wl[-2]) / 2
        else:
            out[j] = (wl[i - 1] + wl[i]) / 2
    return out


def sharpened_basis(n: int | None = None, wavelengths=None, training=None, *,
                    band_edges_nm=None, optimise: bool = True, bounces: int = 2,
                    positive: bool = False) -> SharpenedBasis:
    """Sharpened PCA basis of ``n`` functions (Drew and Finlayson 2003).

    1. ``Q``: the first ``n`` principal components (through the origin, the
       SVD of the paper's Fig. 1a) of :func:`training_spectra`.
    2. ``T``: :func:`band_transform` for ``n`` contiguous bands (eq. 10-13);
       with ``optimise`` the band edges minimise the one-bounce product
       error on the training pairs.
    3. ``Q~ = Q T``, each column scaled to unit sum (``w = Q~^T 1 = 1`` in
       eq. 6-9, so products need no division).

    Parameters
    ----------
    n : int, optional
        Number of basis functions, 1 to the rank of the training spectra
        (at most the number of wavelengths); default :data:`DEFAULT_N`.
    wavelengths : array_like, optional
        Grid in nm (default 400-700 nm at 10 nm).
    training : (lights, reflectances), optional
        Arrays ``(L, N)`` and ``(M, N)`` on ``wavelengths``. Default:
        :data:`DEFAULT_TRAINING_LIGHTS` and every reflectance set of
        :mod:`models.reflectances`.
    band_edges_nm : array_like, optional
        ``n + 1`` increasing band edges in nm; given, they are used as they
        are (no optimisation).
    optimise : bool
        Choose the band edges by coordinate descent (default True).
    bounces : int
        Highest reflectance power in the PCA training signals.
    positive : bool
        Keep every sharp function nonnegative (eq. 14; Drew and Finlayson
        2000): then the coefficients of a nonnegative spectrum are
        nonnegative and relighting never divides by a negative band.

    Returns
    -------
    SharpenedBasis

    Raises
    ------
    ValueError
        ``n`` not a whole number in the allowed range, training arrays of
        the wrong shape or not finite, a band with no sample, or a sharp
        function whose sum vanishes (no unit-sum scaling exists).

    Examples
    --------
    >>> b = sharpened_basis(3)
    >>> b.basis.shape, bool(abs(b.basis.sum(axis=0) - 1).max() < 1e-12)
    ((31, 3), True)
    """
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, dtype=float)
    wavelength_step(wl)  # validates: 1-D, at least two, strictly increasing
    n = _check_n(DEFAULT_N if n is None else n, wl.size,
                 "a sharpened basis has at most one function per wavelength")
    if training is None and band_edges_nm is None:
        return _default_basis(n, tuple(wl.tolist()), bool(optimise),
                              int(bounces), bool(positive))
    return _build_basis(n, wl, training, band_edges_nm, optimise, bounces,
                        positive)


@lru_cache(maxsize=64)
def _default_basis(n, wl, optimise, bounces, positive):
    return _build_basis(n, np.asarray(wl), None, None, optimise, bounces, positive)


def _build_basis(n, wl, training, band_edges_nm, optimise, bounces, positive) -> SharpenedBasis:
    N = wl.size
    if training is None:
        lights, refl = _default_training(wl)
    else:
        try:
            lights, refl = training
        except (TypeError, ValueError):
            raise ValueError("training must be a pair (lights (L, N), reflectances (M, N))") from None
        lights = np.atleast_2d(np.asarray(lights, dtype=float))
        refl = np.atleast_2d(np.asarray(refl, dtype=float))
        for name, arr in (("lights", lights), ("reflectances", refl)):
            if arr.ndim != 2 or arr.shape[1] != N:
                raise ValueError(f"training {name} must be (K, {N}) on the {N} wavelengths, "
                                 f"not {arr.shape}")
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"training {name} contain NaN or Inf")
    spectra = training_spectra(lights, refl, bounces)
    _, sv, vt = np.linalg.svd(spectra, full_matrices=False)
    rank = int(np.sum(sv > sv[0] * max(spectra.shape) * np.finfo(float).eps)) if sv.size else 0
    n = _check_n(n, rank, f"the training spectra have rank {rank} on {N} wavelengths")
    pca = vt[:n].T
    pca = pca * np.where(pca.sum(axis=0) < 0, -1.0, 1.0)
    if band_edges_nm is not None:
        edges = _edges_from_nm(band_edges_nm, wl, n)
    else:
        edges = np.round(np.linspace(0, N, n + 1)).astype(int)
    cache: dict = {}
    if band_edges_nm is None and optimise and 1 < n < N:
        edges = _optimise_edges(pca, lights, refl, edges, positive, cache)
    T, in_band, q, w, converged = _sharp_from_edges(pca, edges, positive, cache)
    scale = np.abs(q).sum(axis=0)
    if np.any(np.abs(w) < 1e-9 * scale.max()):
        k = int(np.argmin(np.abs(w) / scale))
        raise ValueError(f"sharp basis function {k} sums to zero: it cannot be scaled so the "
                         "constant spectrum has coefficient 1; choose other bands")
    basis = q / w
    analysis, synthesis = _analysis_synthesis(basis)
    err1 = _product_relative_errors(analysis, synthesis, lights, refl, 1)
    err2 = _product_relative_errors(analysis, synthesis, lights, refl, 2)
    # best the n-dimensional span can do: project the exact product
    true = (lights[:, None, :] * refl[None, :, :]).reshape(-1, N)
    proj = true @ pca @ pca.T
    den = np.linalg.norm(true, axis=1)
    floor = np.linalg.norm(proj - true, axis=1)[den > 0] / den[den > 0]
    energy = sv**2 / np.sum(sv**2)
    diagnostics = {
        "n": n,
        "training_lights": int(lights.shape[0]),
        "training_reflectances": int(refl.shape[0]),
        "band_edges_nm": _edge_nm(wl, edges).tolist(),
        "positive": bool(positive),
        "positivity_converged": bool(converged),
        "condition_transform": float(np.linalg.cond(T)),
        "condition_basis": float(np.linalg.cond(basis)),
        "in_band_energy": in_band.tolist(),
        "negative_lobe": (basis.min(axis=0) / basis.max(axis=0)).tolist(),
        "explained_energy": float(energy[:n].sum()),
        "product_error_median": float(np.median(err1)),
        "product_error_p90": float(np.percentile(err1, 90)),
        "product_error_rms": float(np.sqrt(np.mean(err1**2))),
        "two_bounce_error_median": float(np.median(err2)),
        "projection_error_median": float(np.median(floor)),
        "product_error_note": "relative RMS spectral error of E*R (and E*R^2) from coefficient "
                              "products, over the training pairs; projection_error is the best "
                              "the same span allows",
    }
    return SharpenedBasis(wl, basis, pca, T, _edge_nm(wl, edges), diagnostics)


def sharpened_rule(n: int | None = None, wavelengths=None, **options) -> SpectralRule:
    """The ``"sharpened"`` strategy: a multiplicative :class:`SpectralRule`.

    Analysis ``c = Q~^T s`` (band-weighted averages, eq. 20-21), synthesis
    ``Q~^+ = Q~ (Q~^T Q~)^-1`` (eq. 22-24); both together are the orthogonal
    projection onto the sharpened span. ``multiplicative=True``: the
    product of two spectra is the elementwise product of their coefficients
    (eq. 25-27), which :meth:`SpectralRule.product` and
    :meth:`SpectralRule.tristimulus_matrix` use.

    Parameters
    ----------
    n : int, optional
        Number of coefficients (default :data:`DEFAULT_N`).
    wavelengths : array_like, optional
    **options
        ``training``, ``band_edges_nm``, ``optimise``, ``bounces``, ``positive`` as in
        :func:`sharpened_basis`.

    Examples
    --------
    >>> rule = sharpened_rule(5)
    >>> rule.n, rule.multiplicative, rule.strategy
    (5, True, 'sharpened')
    >>> bool(np.allclose(rule.coefficients(np.ones(31)), 1.0))
    True
    """
    allowed = {"training", "band_edges_nm", "optimise", "bounces", "positive"}
    unknown = set(options) - allowed
    if unknown:
        raise ValueError(f"unknown option(s) for the sharpened strategy: {sorted(unknown)}; "
                         f"accepted: {sorted(allowed)}")
    b = sharpened_basis(n, wavelengths, **options)
    analysis, synthesis = _analysis_synthesis(b.basis)
    centres = (b.basis * b.wavelengths[:, None]).sum(axis=0)  # unit-sum columns: centroids
    diagnostics = dict(b.diagnostics)
    diagnostics["centroids_nm"] = centres.tolist()
    # not a point rule: no nodes_nm (the centroids are in the diagnostics, for display)
    return SpectralRule("sharpened", b.wavelengths, analysis, synthesis, nodes_nm=None,
                        multiplicative=True, diagnostics=diagnostics)


def pca_product_rule(n: int | None = None, wavelengths=None, training=None, bounces: int = 2) -> SpectralRule:
    """The unsharpened comparison: the same PCA span with the same diagonal
    product model (eq. 6-9 with ``w = Q^T 1``), i.e. ``T = I``.

    The first principal component is positive; the others change sign and
    some have ``w_k`` near zero, which is why the diagonal model fails
    without sharpening (Drew and Finlayson 2003, Fig. 1a against 1b).
    ``diagnostics["w"]`` lists the sums.
    """
    b = sharpened_basis(n, wavelengths, training, optimise=False, bounces=bounces)
    q = b.pca
    w = q.sum(axis=0)
    analysis = (q / w).T
    synthesis = np.linalg.pinv(analysis)
    return SpectralRule("pca-diagonal", b.wavelengths, analysis, synthesis, multiplicative=True,
                        diagnostics={"w": w.tolist(), "condition_basis": float(np.linalg.cond(q / w))})


def _as_coefficients(x, rule: SpectralRule, what: str) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    if x.shape[-1] == rule.wavelengths.size and x.shape[-1] != rule.n:
        return rule.coefficients(x)
    if x.shape[-1] != rule.n:
        raise ValueError(f"{what} must end in {rule.n} coefficients or {rule.wavelengths.size} "
                         f"spectral samples, not shape {x.shape}")
    return x


def _weak_bands(light, rule: SpectralRule) -> list[tuple[float, float]]:
    """Sharpening bands in which a light given as a spectrum has a mean power
    below :data:`RELIGHT_MIN_BAND` of its strongest band. A sharp function
    leaks a little outside its band, so a light that is dark inside a band
    can still get a small positive coefficient there from its neighbours;
    this catches it."""
    light = np.asarray(light, dtype=float)
    edges = rule.diagnostics.get("band_edges_nm")
    if light.shape != rule.wavelengths.shape or light.size == rule.n or edges is None:
        return []
    means = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (rule.wavelengths > lo) & (rule.wavelengths < hi)
        means.append(light[inside].mean() if inside.any() else np.inf)
    means = np.asarray(means)
    top = np.max(means[np.isfinite(means)])
    return [(edges[k], edges[k + 1]) for k in np.flatnonzero(means <= RELIGHT_MIN_BAND * top)]


def relight(coefficients, from_light, to_light, rule: SpectralRule) -> np.ndarray:
    """Colour-signal coefficients under another light: a diagonal map.

    ``C = E S`` has coefficients ``c = e * s`` in a multiplicative rule,
    so under ``E'`` the signal has ``c' = c * e' / e`` (Drew and Finlayson
    2003, eq. 15-19: illuminant change is diagonal in the sharp basis).

    Parameters
    ----------
    coefficients : array_like, shape (..., n)
        Colour-signal coefficients under ``from_light``.
    from_light, to_light : array_like
        Lights as spectra ``(N,)`` on ``rule.wavelengths`` or as
        coefficients ``(n,)``.
    rule : SpectralRule
        A multiplicative rule (e.g. :func:`sharpened_rule`).

    Raises
    ------
    ValueError
        The rule is not multiplicative, or a coefficient of ``from_light``
        is below :data:`RELIGHT_MIN_BAND` times its largest (dividing by it
        would amplify the representation error more than 100-fold).
    """
    if not rule.multiplicative:
        raise ValueError(f"relighting by a diagonal needs a multiplicative rule, not {rule.strategy!r}")
    c = _as_coefficients(coefficients, rule, "coefficients")
    e0 = _as_coefficients(from_light, rule, "from_light")
    e1 = _as_coefficients(to_light, rule, "to_light")
    weak = _weak_bands(from_light, rule)
    if weak:
        lo, hi = weak[0]
        raise ValueError(f"from_light has (almost) no power in the band {lo:.0f}-{hi:.0f} nm (under "
                         f"{RELIGHT_MIN_BAND:.0%} of its strongest band): the signal there cannot be "
                         "relit")
    if np.any(~np.isfinite(e0)) or np.any(e0 <= RELIGHT_MIN_BAND * np.max(np.abs(e0))):
        k = int(np.argmin(e0)) if np.all(np.isfinite(e0)) else -1
        raise ValueError(f"from_light has a coefficient at or below zero (band {k}: under "
                         f"{RELIGHT_MIN_BAND:.0%} of its strongest band): it puts (almost) no power "
                         "there, so the signal in that band cannot be relit")
    return c * (e1 / e0)


def multibounce(reflectance, light, bounces: int, rule: SpectralRule, accumulate: bool = False) -> np.ndarray:
    """Coefficients of ``R^k E`` (light after ``k`` reflections), or of
    ``sum_{j=1..k} R^j E`` with ``accumulate`` (Drew and Finlayson 2003,
    Fig. 2 and 6, Tables 1-5: "accumulating the signal over bounces").

    Each bounce is one elementwise product of coefficients (eq. 25-27).

    Parameters
    ----------
    reflectance, light : array_like
        Spectra ``(..., N)`` on ``rule.wavelengths`` or coefficients ``(..., n)``.
    bounces : int
        ``k >= 1``.
    rule : SpectralRule
        A multiplicative rule.
    """
    if not rule.multiplicative:
        raise ValueError(f"products of coefficients need a multiplicative rule, not {rule.strategy!r}")
    if isinstance(bounces, bool) or int(bounces) != bounces or bounces < 1:
        raise ValueError(f"bounces must be a whole number >= 1, not {bounces!r}")
    r = _as_coefficients(reflectance, rule, "reflectance")
    signal = _as_coefficients(light, rule, "light")
    total = np.zeros(np.broadcast_shapes(r.shape, signal.shape))
    for _ in range(int(bounces)):
        signal = signal * r
        total = total + signal
    return total if accumulate else signal


def product_errors(rule: SpectralRule, lights, reflectances, bounces: int = 1,
                   accumulate: bool = False) -> np.ndarray:
    """Relative RMS spectral error ``||C^ - C|| / ||C||`` of the coefficient
    products for every light-reflectance pair, ``C = E R^k`` (or the sum
    over ``k = 1..bounces`` with ``accumulate``), as the paper's Table 3
    (rms whole-spectrum errors). Pairs with ``C = 0`` are left out."""
    lights = np.atleast_2d(np.asarray(lights, dtype=float))
    refl = np.atleast_2d(np.asarray(reflectances, dtype=float))
    return _product_relative_errors(rule.analysis, rule.synthesis, lights, refl, int(bounces), accumulate)
