"""The camera: spectral sensitivities on a wavelength grid.

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 12: :math:`\\rho_k = \\sum_n
E(\\lambda_n) S(\\lambda_n) R_k(\\lambda_n)` (here with :math:`\\Delta\\lambda`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from models import camera_sensitivities, canonical_camera_name, wavelength_step
from models.grid import DEFAULT_WAVELENGTHS

from .errors import InputError

__all__ = ["Camera", "DATA_RANGE_NM"]

#: The wavelengths (nm) the shipped spectra are measured on: colour-science's
#: illuminants (300 or 380 to 780 nm), the reflectance sets and the measured
#: cameras (380-780 nm). Outside it every light and surface is held at its end
#: value, so a camera must see at least ``C`` wavelengths inside it.
DATA_RANGE_NM = (380.0, 780.0)


@dataclass(frozen=True)
class Camera:
    """A camera with ``C >= 3`` channels.

    Parameters
    ----------
    wavelengths : (N,) array_like
        nm, finite and strictly increasing, at least ``C`` of them inside
        :data:`DATA_RANGE_NM` (380-780 nm, where the lights and surfaces are
        measured) (else :class:`InputError`).
    sensitivities : (N, C) array_like
        :math:`R_k(\\lambda_n)` as columns, relative: the largest magnitude
        must lie in 1e-100..1e100, and each channel must be nonzero somewhere
        in 380-780 nm.
    name : str
    source : str
        ``measured``, ``matrix-derived``, ``uploaded`` or ``generic``.
    color_matrix : (3, 3) array_like, optional
        The XYZ -> camera matrix the RAW file (DNG ColorMatrix) or LibRaw's
        table gives for the model, when known; the learnt estimator
        (:mod:`recovery.ffcc`) maps the camera to its canonical space with
        it (fitted from the sensitivities when absent).

    Examples
    --------
    >>> cam = Camera.named("Nikon 5100 (NPL)")
    >>> cam.channels, cam.wavelengths.size
    (3, 31)
    """

    wavelengths: np.ndarray
    sensitivities: np.ndarray
    name: str = "custom"
    source: str = "uploaded"
    notes: tuple = field(default=(), compare=False)
    color_matrix: np.ndarray | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        wl = np.asarray(self.wavelengths, dtype=np.float64)
        r = np.asarray(self.sensitivities, dtype=np.float64)
        if r.ndim != 2 or r.shape[0] != wl.size:
            raise InputError(f"sensitivities must be (N={wl.size}, C), got {r.shape}")
        if r.shape[1] < 3:
            raise InputError(f"a camera needs at least 3 channels, got {r.shape[1]}")
        if not np.all(np.isfinite(r)):
            raise InputError("sensitivities contain NaN or Inf")
        if np.any(np.abs(r).sum(axis=0) == 0):
            raise InputError("a channel has zero sensitivity at every wavelength")
        top = float(np.abs(r).max())
        if not 1e-100 <= top <= 1e100:
            # 1e-300 raised a bare LinAlgError, 1e300 gave NaN surface estimates (probe pyapi7)
            raise InputError(f"sensitivities peak at {top:.3g}: outside 1e-100..1e100 (they are relative; "
                             "scale them nearer 1)")
        if not np.all(np.isfinite(wl)):
            raise InputError("wavelengths contain NaN or Inf")
        try:
            wavelength_step(wl)  # validates an increasing grid of at least two
        except ValueError as e:      # the grid's own words, as the documented error (probe pyapi7)
            raise InputError(f"wavelengths: {e}") from None
        self._check_data_range(wl, r)
        object.__setattr__(self, "wavelengths", wl)
        object.__setattr__(self, "sensitivities", r)
        if self.color_matrix is not None:
            m = np.asarray(self.color_matrix, dtype=np.float64)
            if m.shape != (3, 3) or not np.all(np.isfinite(m)):
                raise InputError(f"color_matrix must be a finite 3 x 3 array, got {m.shape}")
            object.__setattr__(self, "color_matrix", m)

    @staticmethod
    def _check_data_range(wl: np.ndarray, r: np.ndarray) -> None:
        """At least C wavelengths in :data:`DATA_RANGE_NM`, each channel seeing
        some of it (probe round 8: a camera on 880-1200 nm raised a bare
        ValueError from the light prior, one of two wavelengths a bare
        ValueError from the surface model's PCA)."""
        lo, hi = DATA_RANGE_NM
        c = r.shape[1]
        if wl.size < c:
            raise InputError(f"a camera of {c} channels needs at least {c} wavelengths, got {wl.size}: "
                             f"with fewer its channels are linearly dependent")
        inside = (wl >= lo) & (wl <= hi)
        span = f"{wl[0]:g}-{wl[-1]:g} nm"
        if int(inside.sum()) < c:
            raise InputError(f"the camera's wavelengths ({span}) have {int(inside.sum())} inside {lo:g}-{hi:g} nm, "
                             f"where the lights and surfaces are measured; a camera of {c} channels needs at least "
                             f"{c} there (infrared or ultraviolet cameras are not modelled)")
        blind = [k + 1 for k in range(c) if not np.any(r[inside, k] != 0)]
        if blind:
            raise InputError(f"channel(s) {', '.join(map(str, blind))} are zero at every wavelength in {lo:g}-{hi:g} "
                             f"nm, where the lights and surfaces are measured (infrared or ultraviolet channels are "
                             f"not modelled)")

    @classmethod
    def named(cls, name: str, wavelengths=None) -> "Camera":
        """One of the measured cameras colour-science ships."""
        wl = DEFAULT_WAVELENGTHS if wavelengths is None else np.asarray(wavelengths, float)
        canon = canonical_camera_name(name)
        if canon is None:
            from models import camera_names

            raise KeyError(f"unknown camera {name!r}; accepted: {camera_names()}")
        return cls(wl, camera_sensitivities(canon, wl), canon, "measured")

    def on_grid(self, step: float, start: float | None = None, end: float | None = None) -> "Camera":
        """The same camera on a regular grid of ``step`` nm (box-averaged
        when coarser, interpolated when finer), same range by default."""
        from models.grid import resample, resample_box, wavelength_grid

        start = self.wavelengths[0] if start is None else start
        end = self.wavelengths[-1] if end is None else end
        wl = wavelength_grid(start, end, step)
        if wl.size == self.wavelengths.size and np.allclose(wl, self.wavelengths):
            return self
        coarser = step > float(np.min(np.diff(self.wavelengths))) * 1.01
        sens = (resample_box if coarser else resample)(self.wavelengths, self.sensitivities, wl)
        return Camera(wl, np.clip(sens, 0, None), self.name, self.source, self.notes, self.color_matrix)

    def with_color_matrix(self, color_matrix) -> "Camera":
        """The same camera, with the file's XYZ -> camera matrix attached."""
        if color_matrix is None:
            return self
        try:
            return Camera(self.wavelengths, self.sensitivities, self.name, self.source, self.notes, color_matrix)
        except InputError:
            return self        # a malformed matrix in a file does not make its camera unusable

    @property
    def channels(self) -> int:
        """C, the number of sensor classes."""
        return int(self.sensitivities.shape[1])

    @property
    def dlambda(self) -> np.ndarray:
        """Quadrature weights over wavelength."""
        return wavelength_step(self.wavelengths)

    def response(self, spectra: np.ndarray) -> np.ndarray:
        """Sensor responses to colour signals ``(..., N) -> (..., C)``
        (eq. 1/12 with :math:`\\Delta\\lambda`)."""
        return np.asarray(spectra, float) @ (self.sensitivities * self.dlambda[:, None])
