"""The one interface of every wavelength-sampling strategy: :class:`SpectralRule`.

A rule turns a spectrum on a dense wavelength grid into ``n`` coefficients
and back and integrates products of spectra against colour-matching
functions with those ``n`` numbers (see :mod:`models.sampling`, which builds
the rules and holds the registry of strategies). The strategy modules
(:mod:`models.sampling`, :mod:`models.sharpening`, :mod:`models.quadrature`,
:mod:`models.band_selection`) import this module, and :mod:`models.sampling`
imports them: no cycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .grid import wavelength_step

__all__ = ["SpectralRule", "interpolation_matrix"]


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
    integration : ndarray, shape (n, N), optional
        How the rule represents the colour-matching functions themselves:
        ``integration_weights(cmfs) = integration @ cmfs``. Point sampling
        reads the CMFs at its nodes and weights them by the node's share of
        the range (a renderer that stores every spectrum as samples, Kment
        2011 sec. 5.4). Default: the synthesis functions integrated against
        the CMFs on the dense grid.
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
    integration: np.ndarray | None = None

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
        if self.integration is not None:
            return self.integration @ np.asarray(cmfs, dtype=float)
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


def interpolation_matrix(points: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``(len(points), len(grid))`` rows that linearly interpolate grid values at points."""
    points = np.asarray(points, dtype=float)
    grid = np.asarray(grid, dtype=float)
    A = np.zeros((points.size, grid.size))
    j = np.clip(np.searchsorted(grid, points) - 1, 0, grid.size - 2)
    t = np.clip((points - grid[j]) / (grid[j + 1] - grid[j]), 0.0, 1.0)
    A[np.arange(points.size), j] = 1.0 - t
    A[np.arange(points.size), j + 1] += t
    return A
