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

A response that no reflectance in [0, 1] reaches within ``t`` has an empty
metamer set, for one of two reasons. It may be brighter than a perfect white
of its colour at the given exposure: the reflectance scale is only relative
(an exposure chosen from the scene puts a white card above 1), so the range
is that of its dimmest copy that fits, multiplied back, and
:attr:`MetamerRange.scale` says by how much (1 when it fits). Or its colour
may be out of reach under the light (a colour the camera cannot see under
it): the range is then that of the smallest widening of the tolerance that
makes it non-empty, and :attr:`MetamerRange.slack` says how much (in units
of ``t``; 0 when the colour is in reach): the light or the camera is wrong
for this surface, and the estimate there cannot be trusted.

Solved with SciPy's HiGHS (``scipy.optimize.linprog``), about 1 ms per
programme: 2N + 2 per surface (N wavelengths), so some 80-90 ms per surface
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

__all__ = ["MetamerRange", "SurfaceModel", "metamer_range", "surface_model", "METAMER_TOLERANCE_Z"]

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
        0 where the response's colour is within reach; otherwise the widening
        of the tolerance, in units of it, that the range needed (``1``
        doubles it): a colour no reflectance gives under this light and
        camera, so the light or the camera is wrong there.
    tolerance : (P, C)
        The tolerance per channel the range was computed at (before ``slack``).
    scale : (P,)
        1 where the response fits under a perfect white at this exposure;
        otherwise how many times brighter it is than the brightest
        reflectance of its colour (the reflectance scale is relative: an
        exposure, not a light, puts a white card at 1.2): the range is then
        that of its dimmest copy that fits, multiplied back by ``scale``, so
        ``upper`` may exceed 1 (up to ``scale``).
    """

    lower: np.ndarray
    upper: np.ndarray
    slack: np.ndarray
    tolerance: np.ndarray
    scale: np.ndarray

    @property
    def physical(self) -> np.ndarray:
        """(P,) True where some reflectance in [0, 1] gives the response within the tolerance."""
        return (self.slack <= 0.0) & (self.scale <= 1.0)

    @property
    def width(self) -> np.ndarray:
        """(P, N) ``upper - lower``: 0 where the data fix the reflectance, ``scale`` where they say nothing."""
        return self.upper - self.lower


def _solve(c, A_ub, b_ub, bounds):
    from scipy.optimize import linprog

    r = linprog(c, A_ub=A_ub, b_ub=b_ub, bounds=bounds, method="highs")
    return r if r.status == 0 else None


def _brightest(A: np.ndarray, y: np.ndarray, t: np.ndarray) -> float:
    """The largest k in [0, 1] for which some reflectance in [0, 1] gives ``k y`` within ``k t``: 1 when
    ``y`` is reachable as it is, under 1 when only a dimmer copy of it is (brighter than the brightest
    reflectance of its colour at this exposure), 0 when no copy is (a colour out of reach)."""
    N = A.shape[1]
    # variables (r, k): A r - k (y + t) <= 0, -A r + k (y - t) <= 0; maximise k
    A_ub = np.block([[A, -(y + t)[:, None]], [-A, (y - t)[:, None]]])
    c = np.zeros(N + 1)
    c[-1] = -1.0
    sol = _solve(c, A_ub, np.zeros(2 * A.shape[0]), [(0.0, 1.0)] * N + [(0.0, 1.0)])
    return 0.0 if sol is None else float(sol.x[-1])


def _one(A: np.ndarray, y: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, float]:
    C, N = A.shape
    k = _brightest(A, y, t)
    if k >= 1.0 - 1e-9:
        k = 1.0
    elif k > 1e-6:                          # a reachable colour, too bright: its dimmest copy that fits
        k = k * (1.0 - 1e-6)
    else:                                   # no copy fits: the colour itself is out of reach
        k = 1.0
    y, t = y * k, t * k
    # the smallest widening s >= 0 of the tolerance with a reflectance in [0, 1]: |A r - y| <= t (1 + s)
    Aw = np.block([[A, -t[:, None]], [-A, -t[:, None]]])
    bw = np.concatenate([y + t, t - y])
    cw = np.zeros(N + 1)
    cw[-1] = 1.0
    sol = _solve(cw, Aw, bw, [(0.0, 1.0)] * N + [(0.0, None)])
    if sol is None:                                       # cannot happen for finite data: r = 0, s large is feasible
        return np.zeros(N), np.ones(N) / k, float("inf"), 1.0 / k
    s = float(sol.x[-1])
    s = 0.0 if s <= 1e-6 else s * (1.0 + 1e-6) + 1e-9    # a hair more, so that the programmes below are feasible
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
    lo, hi = np.clip(lo, 0.0, 1.0), np.clip(np.maximum(hi, lo), 0.0, 1.0)
    return lo / k, hi / k, s, 1.0 / k


@dataclass(frozen=True)
class SurfaceModel:
    """Reflectances like measured ones: ``r = B w + e`` with ``|e| <= residual`` at every wavelength and
    ``0 <= r <= 1`` (``B`` the first ``D`` terms of measured reflectances, ``residual`` what measured
    reflectances leave outside them). The metamer set within it is Finlayson & Morovic's (2005), who
    bound reflectances to a linear model of measured surfaces; the residual keeps surfaces the model
    leaves out (:func:`surface_model`).

    Attributes
    ----------
    basis : (N, D)
    residual : (N,)
        The largest departure from the model allowed at each wavelength (>= 0).
    """

    basis: np.ndarray
    residual: np.ndarray


def surface_model(reflectances, dims: int, quantile: float = 1.0) -> SurfaceModel:
    """A :class:`SurfaceModel` from measured reflectances ``(M, N)``: the first ``dims`` right singular
    vectors of the reflectances (not centred, so that a model reflectance times a number is one too:
    Wandell 1985, eq. 11's basis), and at each wavelength the ``quantile`` of the reflectances'
    absolute residual outside them (1: the largest).

    Raises
    ------
    ValueError
        On fewer reflectances than ``dims``, ``dims`` < 1, non-finite values or a quantile outside [0, 1].
    """
    R = np.asarray(reflectances, float)
    if R.ndim != 2 or not np.all(np.isfinite(R)):
        raise ValueError(f"surface_model needs finite reflectances (M, N), got shape {R.shape}")
    if not 1 <= int(dims) <= min(R.shape):
        raise ValueError(f"dims must be in 1..{min(R.shape)} for {R.shape[0]} reflectances of {R.shape[1]} "
                         f"wavelengths, got {dims}")
    if not 0.0 <= float(quantile) <= 1.0:
        raise ValueError(f"quantile must be in [0, 1], got {quantile}")
    B = np.linalg.svd(R, full_matrices=False)[2][: int(dims)].T
    res = np.abs(R - (R @ B) @ B.T)
    return SurfaceModel(B, np.quantile(res, float(quantile), axis=0))


def _one_model(A: np.ndarray, y: np.ndarray, t: np.ndarray, model: SurfaceModel):
    """:func:`_one` within a :class:`SurfaceModel`: variables ``x = (w, e)``, ``r = [B I] x``."""
    C, N = A.shape
    B, eps = np.asarray(model.basis, float), np.asarray(model.residual, float)
    D = B.shape[1]
    M = np.hstack([B, np.eye(N)])                       # r = M x
    AM = A @ M
    xb = [(None, None)] * D + [(-float(e), float(e)) for e in eps]
    rows_r = np.vstack([M, -M])                         # 0 <= r <= 1
    b_r = np.concatenate([np.ones(N), np.zeros(N)])
    z = np.zeros((2 * N, 1))
    # the brightest copy k y that some model reflectance gives within k t
    A_ub = np.vstack([np.hstack([AM, -(y + t)[:, None]]), np.hstack([-AM, (y - t)[:, None]]), np.hstack([rows_r, z])])
    c = np.zeros(D + N + 1)
    c[-1] = -1.0
    sol = _solve(c, A_ub, np.concatenate([np.zeros(2 * C), b_r]), xb + [(0.0, 1.0)])
    k = 0.0 if sol is None else float(sol.x[-1])
    if k >= 1.0 - 1e-9:
        k = 1.0
    elif k > 1e-6:
        k = k * (1.0 - 1e-6)
    else:
        k = 1.0
    y, t = y * k, t * k
    # the smallest widening s of the tolerance with a model reflectance
    A_ub = np.vstack([np.hstack([AM, -t[:, None]]), np.hstack([-AM, -t[:, None]]), np.hstack([rows_r, z])])
    c = np.zeros(D + N + 1)
    c[-1] = 1.0
    sol = _solve(c, A_ub, np.concatenate([y + t, t - y, b_r]), xb + [(0.0, None)])
    if sol is None:                                     # r = 0 with a large s is always feasible
        return np.zeros(N), np.ones(N) / k, float("inf"), 1.0 / k
    s = float(sol.x[-1])
    s = 0.0 if s <= 1e-6 else s * (1.0 + 1e-6) + 1e-9
    tt = t * (1.0 + s)
    A_ub = np.vstack([AM, -AM, rows_r])
    b_ub = np.concatenate([y + tt, tt - y, b_r])
    lo, hi = np.zeros(N), np.ones(N)
    for n in range(N):
        a = _solve(M[n], A_ub, b_ub, xb)
        b = _solve(-M[n], A_ub, b_ub, xb)
        lo[n] = a.fun if a is not None else 0.0
        hi[n] = -b.fun if b is not None else 1.0
    lo, hi = np.clip(lo, 0.0, 1.0), np.clip(np.maximum(hi, lo), 0.0, 1.0)
    return lo / k, hi / k, s, 1.0 / k


def metamer_range(A, y, tolerance, model: SurfaceModel | None = None) -> MetamerRange:
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
    model : SurfaceModel, optional
        Only reflectances of this model of measured surfaces (Finlayson &
        Morovic 2005): a narrower set that says what surfaces *like measured
        ones* allow. Default: every reflectance in [0, 1].

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
    if model is not None and (np.shape(model.basis)[0] != N or np.shape(model.residual) != (N,)):
        raise ValueError(f"the surface model is on {np.shape(model.basis)[0]} wavelengths, the operators on {N}")
    lo, hi, s, scale = np.zeros((P, N)), np.ones((P, N)), np.zeros(P), np.ones(P)
    for p in range(P):
        lo[p], hi[p], s[p], scale[p] = (_one(A[p], y[p], t[p]) if model is None
                                        else _one_model(A[p], y[p], t[p], model))
    return MetamerRange(lo, hi, s, t, scale)
