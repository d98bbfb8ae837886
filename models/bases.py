"""Linear models of lights and surfaces: PCA, Fourier, CIE daylight.

A linear model is a matrix whose columns are basis functions on a wavelength
grid (Wandell 1985, eq. 5-6 and 10-11): :math:`E(\\lambda) = \\mathbf{E}\\epsilon`,
:math:`S(\\lambda) = \\mathbf{S}\\sigma`. This module builds such matrices, fits
weights by least squares, reconstructs spectra and reports the error and
explained variance.

References
----------
Wandell (1985) [docs/references.md#seed-002]: eq. 5-11; section "Fourier Basis"
(Fig. 4b: DC plus sine/cosine pairs over 400-700 nm; Fig. 5: normalised
RMSE against number of terms); section "Principal Components Analysis"
(Cohen 1964 for Munsell chips; Judd, MacAdam & Wyszecki 1964 for daylight).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from .grid import DEFAULT_WAVELENGTHS

__all__ = [
    "LinearModel",
    "pca_model",
    "fourier_model",
    "fourier_basis",
    "daylight_model",
    "illuminant_pca_model",
    "surface_pca_model",
    "normalised_rmse",
]


@dataclass(frozen=True)
class LinearModel:
    """A linear model: ``spectrum = mean + basis @ weights``.

    Attributes
    ----------
    wavelengths : (N,) ndarray
    basis : (N, D) ndarray
        Basis functions as columns (Wandell's matrix **E** or **S**).
    mean : (N,) ndarray or None
        Only for mean-centred PCA; the Maloney-Wandell method needs models
        through the origin (``mean is None``), because the sensor equations
        are linear, not affine, in the weights (eq. 16-21).
    kind, name : str
    explained_variance : (D,) ndarray or None
        Fraction of the training set's second moment (through the origin)
        or variance (centred) each component accounts for.
    """

    wavelengths: np.ndarray
    basis: np.ndarray
    mean: np.ndarray | None = None
    kind: str = "custom"
    name: str = ""
    explained_variance: np.ndarray | None = field(default=None, repr=False)

    @property
    def dimension(self) -> int:
        """D(E) or D(S): the number of basis functions."""
        return int(self.basis.shape[1])

    def truncate(self, d: int) -> "LinearModel":
        """The first ``d`` basis functions."""
        if not 1 <= d <= self.dimension:
            raise ValueError(f"dimension must be in 1..{self.dimension}, not {d}")
        ev = None if self.explained_variance is None else self.explained_variance[:d]
        return LinearModel(self.wavelengths, self.basis[:, :d], self.mean, self.kind,
                           self.name, ev)

    def project(self, spectra: np.ndarray) -> np.ndarray:
        """Least-squares weights of ``spectra`` (``(N,)`` or ``(M, N)``)."""
        s = np.asarray(spectra, dtype=np.float64)
        x = s - self.mean if self.mean is not None else s
        w, *_ = np.linalg.lstsq(self.basis, x.T if x.ndim == 2 else x, rcond=None)
        return w.T if x.ndim == 2 else w

    def reconstruct(self, weights: np.ndarray) -> np.ndarray:
        """Spectra from weights (``(D,)`` or ``(M, D)``)."""
        w = np.asarray(weights, dtype=np.float64)
        s = w @ self.basis.T
        return s + self.mean if self.mean is not None else s

    def fit(self, spectra: np.ndarray) -> np.ndarray:
        """Best approximation of ``spectra`` inside the model."""
        return self.reconstruct(self.project(spectra))


def normalised_rmse(spectra: np.ndarray, approximations: np.ndarray) -> np.ndarray:
    """Wandell's Fig. 5 error: RMS error of the fit divided by the RMS of
    the spectrum (``||s - s_hat|| / ||s||`` per row)."""
    s = np.atleast_2d(np.asarray(spectra, float))
    a = np.atleast_2d(np.asarray(approximations, float))
    num = np.linalg.norm(s - a, axis=1)
    den = np.linalg.norm(s, axis=1)
    return np.divide(num, den, out=np.full_like(num, np.nan), where=den > 0)


def pca_model(samples: np.ndarray, dimension: int | None = None, wavelengths=None,
              centred: bool = False, name: str = "pca") -> LinearModel:
    """Principal components of ``samples`` (rows are spectra).

    ``centred=False`` gives the basis through the origin (the SVD of the raw
    sample matrix: the first component is the mean direction), which is what
    the lighting matrices of eq. 17-21 need. ``centred=True`` subtracts the
    mean first (classical PCA), kept for comparison.

    Examples
    --------
    >>> from models.reflectances import reflectance_set
    >>> m = pca_model(reflectance_set("colorchecker"), 3)
    >>> m.basis.shape, bool(m.explained_variance[0] > 0.8)
    ((31, 3), True)
    """
    x = np.asarray(samples, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError("samples must be (M, N)")
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    if x.shape[1] != wl.size:
        raise ValueError(f"samples have {x.shape[1]} columns for {wl.size} wavelengths")
    mean = x.mean(axis=0) if centred else None
    xc = x - mean if centred else x
    _, s, vt = np.linalg.svd(xc, full_matrices=False)
    energy = s**2 / np.sum(s**2)
    d = vt.shape[0] if dimension is None else int(dimension)
    if not 1 <= d <= vt.shape[0]:
        raise ValueError(f"dimension must be in 1..{vt.shape[0]}, not {d}")
    basis = vt[:d].T.copy()
    # sign convention: each component has a positive sum (first is positive)
    basis *= np.where(basis.sum(axis=0) < 0, -1.0, 1.0)
    return LinearModel(wl, basis, mean, "pca-centred" if centred else "pca", name, energy[:d])


def fourier_basis(wavelengths=None, dimension: int = 3) -> np.ndarray:
    """DC plus sine/cosine pairs over the range of ``wavelengths``, ``(N, D)``.

    Term 1 is constant; terms 2 and 3 are the sine and cosine of one cycle
    across the range (period = last minus first wavelength), terms 4 and 5
    two cycles, and so on (Wandell 1985, Fig. 4b). The functions are fixed
    functions of wavelength, so the model spans the same space whatever the
    sampling step; the columns are then orthonormalised in order
    (Gram-Schmidt by QR), which keeps that span and keeps term 1 constant.
    """
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    if dimension < 1:
        raise ValueError("dimension must be >= 1")
    if dimension > wl.size:
        raise ValueError(f"at most {wl.size} Fourier terms on {wl.size} wavelengths")
    period = wl[-1] - wl[0]
    t = (wl - wl[0]) / period
    cols = [np.ones_like(wl)]
    k = 1
    while len(cols) < dimension:
        cols.append(np.sin(2 * np.pi * k * t))
        if len(cols) < dimension:
            cols.append(np.cos(2 * np.pi * k * t))
        k += 1
    q, r = np.linalg.qr(np.stack(cols, 1))
    return q * np.sign(np.diag(r))[None, :]


def fourier_model(dimension: int = 3, wavelengths=None) -> LinearModel:
    """:func:`fourier_basis` as a :class:`LinearModel`."""
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return LinearModel(wl, fourier_basis(wl, dimension), None, "fourier", f"fourier-{dimension}")


def daylight_model(dimension: int = 3, wavelengths=None) -> LinearModel:
    """The CIE daylight basis S0, S1, S2 (first ``dimension`` of them)."""
    from .illuminants import daylight_basis

    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    if not 1 <= dimension <= 3:
        raise ValueError("the CIE daylight basis has 1 to 3 terms")
    return LinearModel(wl, daylight_basis(wl)[:, :dimension], None, "daylight",
                       f"cie-daylight-{dimension}")


def illuminant_pca_model(dimension: int = 3, wavelengths=None, names=None) -> LinearModel:
    """PCA (through the origin) of colour-science's illuminants, each first
    normalised to unit mean power."""
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return _illuminant_pca_cached(int(dimension), tuple(wl.tolist()), None if names is None else tuple(names))


def _frozen(m: LinearModel) -> LinearModel:
    for a in (m.wavelengths, m.basis, m.mean, m.explained_variance):
        if a is not None:
            a.flags.writeable = False
    return m


@lru_cache(maxsize=64)
def _illuminant_pca_cached(dimension, wl, names):
    from .illuminants import illuminants

    wl = np.asarray(wl)
    return _frozen(pca_model(illuminants(names, wl), dimension, wl, name=f"illuminant-pca-{dimension}"))


@lru_cache(maxsize=64)
def _surface_pca_cached(dimension, wl, set_name, centred):
    from .reflectances import reflectance_set

    wl = np.asarray(wl)
    return _frozen(pca_model(reflectance_set(set_name, wl), dimension, wl, centred=centred,
                             name=f"surface-pca-{set_name}-{dimension}"))


def surface_pca_model(dimension: int = 3, wavelengths=None, reflectance_set_name: str = "all",
                      centred: bool = False) -> LinearModel:
    """PCA of one of colour-science's reflectance sets (default: all).

    Cached per grid (the returned arrays are read-only)."""
    wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
    return _surface_pca_cached(int(dimension), tuple(wl.tolist()), reflectance_set_name, bool(centred))
