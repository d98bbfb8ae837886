"""The metamer set of a camera response: every physical reflectance that gives it (issue 31, item 2).

Three sensors do not determine a reflectance. Under a light :math:`E` a
camera of sensitivities :math:`R_c` sees a surface :math:`r` as

.. math:: \\rho = A r, \\qquad A_{cn} = R_c(\\lambda_n) E(\\lambda_n) \\Delta\\lambda_n

(Wandell 1985, eq. 12 and 17, without a surface basis). Every reflectance
:math:`0 \\le r \\le 1` with :math:`A r = \\rho` is as consistent with the
response as any other: the *metamer set* of :math:`\\rho` (Finlayson &
Morovic 2005). Its extent at each wavelength,

.. math:: \\min / \\max\\ r(\\lambda_n) \\quad \\text{s.t.} \\quad
          |A r - \\rho| \\le t, \\quad 0 \\le r \\le 1,

is a pair of linear programmes per wavelength (``t`` the response's
tolerance per channel, its noise), and says which wavelengths of an estimate
the data pin down (a narrow range) and which only the prior fills in (a
range as wide as [0, 1]). Unlike the prior's band (:mod:`recovery.surface_prior`)
it assumes nothing about what surfaces are like, and it is not a probability:
every reflectance inside is possible, none outside is.

A response that no reflectance in [0, 1] reaches within ``t`` (brighter than
a perfect white under the light at the given exposure, or a colour outside
what the camera can see under it) has an empty metamer set: the range is
then that of the smallest widening of the tolerance that makes it non-empty,
and :attr:`MetamerRange.slack` says how much (in units of ``t``; 0 when the
response is physical). A large slack says the light, the exposure or the
camera is wrong for this surface: the estimate there cannot be trusted.

Solved with SciPy's HiGHS (``scipy.optimize.linprog``), about 1 ms per
programme: 2N + 1 per surface (N wavelengths), so some 60-80 ms per surface
at 31 wavelengths. Pure functions on arrays.

References
----------
Wandell (1985) [docs/references.md#seed-002], eq. 12 and 17.
G. D. Finlayson, P. Morovic, "Metamer sets", JOSA A 22(5), 810-819, 2005.
A. Logvinenko, B. Funt, C. Godau, "Metamer mismatching", IEEE Trans. Image
Processing 23(1), 34-43, 2014 (the object-colour solid; the set's extremes
are reflectances of 0 and 1 with few transitions).
Q. Huangfu, J. A. J. Hall, "Parallelizing the dual revised simplex method",
Mathematical Programming Computation 10, 119-142, 2018 (HiGHS).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["MetamerRange", "metamer_range", "METAMER_TOLERANCE_Z"]

#: The response's tolerance per channel, in standard deviations of its
#: noise (:func:`recovery.surface_prior._noise_var`'s model): 2, about 95 %
#: per channel under Gaussian noise.
METAMER_TOLERANCE_Z = 2.0


@dataclass(frozen=True)
class MetamerRange:
    """The extent of the metamer sets of ``P`` responses over ``N`` wavelengths.

    Attributes
    ----------
    lower, upper : (P, N)
        The least and greatest reflectance at each wavelength over all
        reflectances in [0, 1] that give the response within the tolerance
        (widened by ``slack`` where none does).
    slack : (P,)
        0 where the response is physical; otherwise the widening of the
        tolerance, in units of it, that the range needed (``1`` doubles it).
    tolerance : (P, C)
        The tolerance per channel the range was computed at (before ``slack``).
    """

    lower: np.ndarray
    upper: np.ndarray
    slack: np.ndarray
    tolerance: np.ndarray

    @property
    def physical(self) -> np.ndarray:
        """(P,) True where some reflectance in [0, 1] gives the response within the tolerance."""
        return self.slack <= 0.0

    @property
    def width(self) -> np.ndarray:
        """(P, N) ``upper - lower``: 0 where the data fix the reflectance, 1 where they say nothing."""
        return self.upper - self.lower


def _solve(c, A_ub, b_ub, bounds):
    from scipy.optimize import linprog

    r = linprog(c, A_ub=A_ub, b_ub=b_ub, bounds=bounds, method="highs")
    return r if r.status == 0 else None


def _one(A: np.ndarray, y: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    C, N = A.shape
    # the smallest widening s >= 0 of the tolerance with a reflectance in [0, 1]: |A r - y| <= t (1 + s)
    Aw = np.block([[A, -t[:, None]], [-A, -t[:, None]]])
    bw = np.concatenate([y + t, t - y])
    cw = np.zeros(N + 1)
    cw[-1] = 1.0
    sol = _solve(cw, Aw, bw, [(0.0, 1.0)] * N + [(0.0, None)])
    if sol is None:                                       # cannot happen for finite data: r = 0, s large is feasible
        return np.zeros(N), np.ones(N), float("inf")
    s = float(sol.x[-1])
    s = 0.0 if s <= 1e-9 else s * (1.0 + 1e-6) + 1e-9    # a hair more, so that the programmes below are feasible
    tt = t * (1.0 + s)
    A_ub = np.vstack([A, -A])
    b_ub = np.concatenate([y + tt, tt - y])
    lo, hi = np.zeros(N), np.ones(N)
    e = np.zeros(N)
    for n in range(N):
        e[:] = 0.0
        e[n] = 1.0
        a = _solve(e, A_ub, b_ub, (0.0, 1.0))
        b = _solve(-e, A_ub, b_ub, (0.0, 1.0))
        lo[n] = a.fun if a is not None else 0.0
        hi[n] = -b.fun if b is not None else 1.0
    return np.clip(lo, 0.0, 1.0), np.clip(np.maximum(hi, lo), 0.0, 1.0), s


def metamer_range(A, y, tolerance) -> MetamerRange:
    """The extent of the metamer set of each response at each wavelength.

    Parameters
    ----------
    A : (C, N) or (P, C, N)
        Lighting operator(s), :func:`recovery.surface_prior.lighting_operator`
        (one for every response, or one each: a light map).
    y : (C,) or (P, C)
        Responses on the scale of ``A r`` (a camera response divided by the
        exposure).
    tolerance : float or (C,) or (P, C)
        Half-width per channel of the box around each response (> 0: a
        response is never known exactly).

    Returns
    -------
    MetamerRange

    Raises
    ------
    ValueError
        On shapes that do not match, non-finite values or a tolerance <= 0.
    """
    y = np.atleast_2d(np.asarray(y, float))
    A = np.asarray(A, float)
    if A.ndim == 2:
        A = np.broadcast_to(A, (y.shape[0],) + A.shape)
    if A.ndim != 3 or A.shape[0] != y.shape[0] or A.shape[1] != y.shape[1]:
        raise ValueError(f"A {A.shape} does not match responses {y.shape}: (C, N) or (P, C, N) against (P, C)")
    t = np.broadcast_to(np.asarray(tolerance, float), y.shape).astype(float)
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(y)) and np.all(np.isfinite(t))):
        raise ValueError("metamer_range needs finite operators, responses and tolerances")
    if np.any(t <= 0):
        raise ValueError("the tolerance must be > 0 in every channel")
    P, N = y.shape[0], A.shape[2]
    lo, hi, s = np.zeros((P, N)), np.ones((P, N)), np.zeros(P)
    for p in range(P):
        lo[p], hi[p], s[p] = _one(A[p], y[p], t[p])
    return MetamerRange(lo, hi, s, t)
