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

References
----------
Meyer, G. W. (1988). Wavelength selection for synthetic image generation.
CVGIP 41 (seed 000). Kment, T. (2011). Spectral data representation techniques
for realistic image synthesis. TU Wien (seed 001). Drew, M. S. and Finlayson,
G. D. (2003). Multispectral processing without spectra. JOSA A 20(7) (seed 003).
Borges, C. F. (1992). Optimal spectral sampling for color imaging. SPIE 1670
(seed 004).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .grid import wavelength_step

__all__ = ["SpectralRule"]


@dataclass(frozen=True)
class SpectralRule:
    """A spectral representation with ``n`` numbers per spectrum.

    Parameters
    ----------
    strategy : str
        Name of the strategy (``"uniform"``, ``"riemann"``, ``"fourier"``,
        ``"pca"``, ``"sharpened"``, ``"composite"``, ``"gauss-ac1c2"``,
        ``"quasi-gauss-xyz"``).
    wavelengths : ndarray, shape (N,)
        Dense grid (nm) on which input spectra are given.
    analysis : ndarray, shape (n, N)
        Spectrum to coefficients: ``c = s @ analysis.T``.
    synthesis : ndarray, shape (N, n)
        Coefficients to spectrum: ``s ~= c @ synthesis.T``.
    nodes_nm : ndarray, shape (n,), optional
        Sample wavelengths for point and quadrature rules.
    weights : ndarray, shape (n,) or (n, k), optional
        Quadrature weights. When given with ``k`` columns they are used as the
        integration weights of the rule directly (the rule integrates against
        its own weight functions, e.g. xbar, ybar, zbar for Borges).
    multiplicative : bool
        True when the coefficients of a product of two spectra are the
        product of their coefficients (point rules; sharpened bases,
        Drew and Finlayson 2003, eq. 1-4).
    defined : bool
        False when the rule does not exist as asked, e.g. a Gaussian
        quadrature order whose nodes leave the interval (Meyer 1988, Table 1a).
    reason : str, optional
        Why the rule is undefined.
    diagnostics : dict
        Conditioning and other numbers a user should see.
    """

    strategy: str
    wavelengths: np.ndarray
    analysis: np.ndarray
    synthesis: np.ndarray
    nodes_nm: np.ndarray | None = None
    weights: np.ndarray | None = None
    multiplicative: bool = False
    defined: bool = True
    reason: str | None = None
    diagnostics: dict = field(default_factory=dict)

    @property
    def n(self) -> int:
        """Number of coefficients per spectrum."""
        return int(self.analysis.shape[0])

    def coefficients(self, spectra: np.ndarray) -> np.ndarray:
        """Coefficients of ``spectra`` (..., N) -> (..., n)."""
        return np.asarray(spectra, dtype=float) @ self.analysis.T

    def reconstruct(self, coefficients: np.ndarray) -> np.ndarray:
        """Spectra from coefficients (..., n) -> (..., N)."""
        return np.asarray(coefficients, dtype=float) @ self.synthesis.T

    def product(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """Coefficients of the product of two spectra given by coefficients.

        Multiplicative rules multiply coefficients (Drew and Finlayson 2003,
        eq. 4); the others reconstruct, multiply on the dense grid and project
        back.
        """
        a = np.asarray(a, dtype=float)
        b = np.asarray(b, dtype=float)
        if self.multiplicative:
            return a * b
        return self.coefficients(self.reconstruct(a) * self.reconstruct(b))

    def integration_weights(self, cmfs: np.ndarray) -> np.ndarray:
        """``(n, k)`` weights so that ``sum_l s(l) cmf_k(l) dl ~= c @ W``.

        Quadrature rules with their own per-channel weights return them;
        other rules integrate their synthesis functions against the
        colour-matching functions on the dense grid.
        """
        if self.weights is not None and np.ndim(self.weights) == 2:
            return np.asarray(self.weights, dtype=float)
        dl = wavelength_step(self.wavelengths)
        return self.synthesis.T @ (np.asarray(cmfs, dtype=float) * dl[:, None])

    def tristimulus_matrix(self, light: np.ndarray, cmfs: np.ndarray,
                           represent_light: bool = True) -> np.ndarray:
        """``(n, k)`` matrix ``M`` with ``T ~= coefficients(S) @ M``.

        Parameters
        ----------
        light : ndarray, shape (N,)
            Light on the dense grid.
        cmfs : ndarray, shape (N, k)
            Colour-matching functions on the dense grid.
        represent_light : bool
            True (the setting of Meyer, Borges and Kment): the light is held
            in the same representation as the surface and the product formed
            from coefficients. False: the light is kept exact and folded into
            the matrix, so only the surface is approximated.
        """
        light = np.asarray(light, dtype=float)
        cmfs = np.asarray(cmfs, dtype=float)
        if not represent_light:
            dl = wavelength_step(self.wavelengths)
            return self.synthesis.T @ (cmfs * (light * dl)[:, None])
        if self.multiplicative:
            return self.coefficients(light)[:, None] * self.integration_weights(cmfs)
        # Product of the represented light with each synthesis function,
        # integrated on the dense grid.
        e = self.reconstruct(self.coefficients(light))
        dl = wavelength_step(self.wavelengths)
        return self.synthesis.T @ (cmfs * (e * dl)[:, None])


# --- strategies -----------------------------------------------------------------
#
# Every strategy is built by a function ``builder(n, wavelengths, **options)``
# returning a SpectralRule. The table names the module and function, imported on
# first use so that models.sampling does not depend on the modules that use it.

STRATEGIES = {
    "uniform": ("models.sampling", "uniform_rule"),
    "riemann": ("models.sampling", "riemann_rule"),
    "fourier": ("models.sampling", "fourier_rule"),
    "pca": ("models.sampling", "pca_rule"),
    "composite": ("models.sampling", "composite_rule"),
    "sharpened": ("models.sharpening", "sharpened_rule"),
    "gauss-ac1c2": ("models.quadrature", "gauss_ac1c2_rule"),
    "quasi-gauss-xyz": ("models.quadrature", "quasi_gauss_xyz_rule"),
}


def strategy_names() -> list[str]:
    """Names accepted by :func:`sampling_rule`."""
    return list(STRATEGIES)


def sampling_rule(strategy: str, n: int | None = None, wavelengths=None, **options) -> SpectralRule:
    """Build the rule ``strategy`` with ``n`` coefficients on ``wavelengths``.

    Raises ``ValueError`` naming the accepted strategies for an unknown name.
    """
    import importlib

    from .grid import DEFAULT_WAVELENGTHS

    if strategy not in STRATEGIES:
        raise ValueError(f"unknown sampling strategy {strategy!r}; accepted: {', '.join(STRATEGIES)}")
    module, name = STRATEGIES[strategy]
    builder = getattr(importlib.import_module(module), name)
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, dtype=float)
    return builder(n, wl, **options)


def _interpolation_matrix(points: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``(len(points), len(grid))`` rows that linearly interpolate grid values at points."""
    points = np.asarray(points, dtype=float)
    grid = np.asarray(grid, dtype=float)
    A = np.zeros((points.size, grid.size))
    j = np.clip(np.searchsorted(grid, points) - 1, 0, grid.size - 2)
    t = np.clip((points - grid[j]) / (grid[j + 1] - grid[j]), 0.0, 1.0)
    A[np.arange(points.size), j] = 1.0 - t
    A[np.arange(points.size), j + 1] += t
    return A


def uniform_rule(n: int | None, wavelengths: np.ndarray) -> SpectralRule:
    """Point sampling at ``n`` equally spaced wavelengths (Kment 2011, sec. 3.1).

    Nodes sit at the centres of ``n`` equal sub-intervals of the grid's range;
    the spectrum is read there by linear interpolation and rebuilt as the
    piecewise-linear curve through the nodes (constant beyond the end nodes).
    Products of spectra are products of samples, so the rule is multiplicative.
    """
    wl = np.asarray(wavelengths, dtype=float)
    if n is None or int(n) < 1:
        raise ValueError("uniform sampling needs n >= 1")
    n = int(n)
    lo, hi = wl[0], wl[-1]
    width = (hi - lo) / n
    nodes = lo + width * (np.arange(n) + 0.5)
    analysis = _interpolation_matrix(nodes, wl)
    if n == 1:
        synthesis = np.ones((wl.size, 1))
    else:
        synthesis = _interpolation_matrix(wl, nodes)
    return SpectralRule("uniform", wl, analysis, synthesis, nodes_nm=nodes, multiplicative=True,
                        diagnostics={"spacing_nm": float(width)})
