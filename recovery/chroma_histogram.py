"""Log-chroma histograms and a learnt convolutional light likelihood on them.

The learnt estimator's first stage (:mod:`recovery.learned`) combines a few
dozen global statistics of the image; two photographs with the same
statistics but a different spread of colours get the same answer. This
module looks at the whole distribution of the image's chromaticities, as
Barron's convolutional colour constancy does (Barron 2015; Barron & Tsai
2017, "FFCC"):

1. the canonical-space analysis cells (:func:`recovery.learned.canonical_analysis`)
   are binned by log-chroma ``(u, v) = (log g/r, log g/b)`` into a histogram
   on a torus of ``NU x NV`` bins of width :data:`STEP` (a pixel beyond the
   torus wraps round, Barron & Tsai's aliasing, harmless because the light
   is searched only inside one period), and so is the image of local absolute
   deviations (an edge image: the colours of the boundaries between surfaces);
2. a change of light is a shift of every pixel's log-chroma (the diagonal
   model), so the score of a candidate light is a convolution of each
   histogram with a learnt filter: ``H(L) = sum_c (X_c * F_c)(L) + B(L)``,
   computed with FFTs (eq. 6 of Barron & Tsai 2017), and ``softmax(H)`` is a
   likelihood over the lights;
3. it is fused with the first stage's calibrated Gaussian (its estimate and
   variance): the posterior ``softmax(H) * N(L; mu, var)`` on the grid, whose
   mean in a window about its mode is the estimate
   (:func:`fuse`). The first stage keeps the answer near what global
   statistics support; the histogram moves it where the distribution of
   colours says the light is.

The filters are fitted by minimising the cross-entropy of ``softmax(H)``
against the true light (a convex problem in ``F`` and ``B``, with squared
gradient and squared value penalties) in ``benchmarks.train_illuminant``,
and ship in the learnt model file beside the first stage.

References
----------
Barron (2015), Convolutional color constancy, ICCV.
Barron & Tsai (2017), Fast Fourier color constancy, CVPR.
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

__all__ = ["Grid", "DEFAULT_GRID", "histograms", "edge_image", "scores", "posterior_mean", "fuse",
           "bin_centres"]


class Grid(tuple):
    """``(step, u0, v0, nu, nv)``: the torus of light and pixel log-chroma
    bins, ``u0 + [0, nu) step`` by ``v0 + [0, nv) step``."""

    def __new__(cls, step, u0, v0, nu, nv):
        return super().__new__(cls, (float(step), float(u0), float(v0), int(nu), int(nv)))

    step = property(lambda s: s[0])
    u0 = property(lambda s: s[1])
    v0 = property(lambda s: s[2])
    nu = property(lambda s: s[3])
    nv = property(lambda s: s[4])

    @classmethod
    def from_array(cls, a) -> "Grid":
        a = np.asarray(a, float).ravel()
        return cls(a[0], a[1], a[2], int(round(a[3])), int(round(a[4])))


#: 1/32 log-chroma bins (Barron & Tsai's), 2 x 4 units: the development
#: photographs' lights span u in [-0.83, 0.30] and v in [-0.56, 2.9] in the
#: canonical space (v is wider: a warm light leaves the canonical blue small).
DEFAULT_GRID = Grid(1.0 / 32.0, -1.2, -0.8, 64, 128)


def bin_centres(grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """(nu,), (nv,) the log-chroma at the centre of each bin."""
    return (grid.u0 + (np.arange(grid.nu) + 0.5) * grid.step, grid.v0 + (np.arange(grid.nv) + 0.5) * grid.step)


def _log_chroma(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) positive -> (N, 2) ``(log g/r, log g/b)`` (as
    :func:`recovery.learned.rgb_to_uv`, which imports this module)."""
    lg = np.log(rgb)
    return np.stack([lg[:, 1] - lg[:, 0], lg[:, 1] - lg[:, 2]], -1)


def _hist(uv: np.ndarray, grid: Grid) -> np.ndarray:
    iu = np.floor((uv[:, 0] - grid.u0) / grid.step).astype(np.int64) % grid.nu
    iv = np.floor((uv[:, 1] - grid.v0) / grid.step).astype(np.int64) % grid.nv
    h = np.bincount(iu * grid.nv + iv, minlength=grid.nu * grid.nv).astype(float).reshape(grid.nu, grid.nv)
    s = h.sum()
    return h / s if s > 0 else h


def edge_image(cells: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Local absolute deviation (Barron & Tsai 2017, sec. 3): per channel,
    the mean ``|x - neighbour|`` over the usable ones of the 8 neighbours;
    and where it is defined (a usable cell with a usable neighbour)."""
    c = np.asarray(cells, float)
    h, w = ok.shape
    acc = np.zeros_like(c)
    cnt = np.zeros((h, w))
    pad = np.pad(c, ((1, 1), (1, 1), (0, 0)))
    pok = np.pad(ok, 1)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                nb = pad[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx]
                both = pok[1 + dy:h + 1 + dy, 1 + dx:w + 1 + dx] & ok
                acc += np.where(both[..., None], np.abs(c - nb), 0.0)
                cnt += both
    return acc / np.maximum(cnt, 1.0)[..., None], ok & (cnt > 0)


def histograms(cells: np.ndarray, ok: np.ndarray, grid: Grid = DEFAULT_GRID) -> np.ndarray:
    """(2, nu, nv) normalised log-chroma histograms of the usable cells with
    positive channels and of their edge image (zero where there is none)."""
    c = np.asarray(cells, float)
    good = np.asarray(ok, bool) & np.all(c > 0, axis=-1)
    h0 = _hist(_log_chroma(c[good]), grid)
    e, eok = edge_image(c, good)
    eok &= np.all(e > 1e-9, axis=-1)
    if eok.any():
        h1 = _hist(_log_chroma(e[eok]), grid)
    else:
        h1 = np.zeros((grid.nu, grid.nv))
    return np.stack([h0, h1])


def scores(hist: np.ndarray, filters: np.ndarray, bias: np.ndarray) -> np.ndarray:
    """``H = sum_c X_c * F_c + B`` (circular convolution on the torus, by
    FFT; Barron & Tsai 2017, eq. 6) for (..., C, nu, nv) histograms."""
    hist = np.asarray(hist, float)
    shape = hist.shape[-2:]
    s = (sfft.rfft2(hist) * sfft.rfft2(np.asarray(filters, float))).sum(axis=-3)
    return sfft.irfft2(s, s=shape) + np.asarray(bias, float)


def posterior_mean(logp: np.ndarray, grid: Grid, window: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """(..., nu, nv) log-posterior on the torus -> (..., 2) the mean
    log-chroma in a ``(2 window + 1)^2`` window about the mode (taken on the
    torus, so a mode near the edge is not split), mapped into the grid's
    period, and (..., 2, 2) the covariance there."""
    lp = np.asarray(logp, float)
    flat = lp.reshape(-1, grid.nu, grid.nv)
    n = flat.shape[0]
    k = flat.reshape(n, -1).argmax(axis=1)
    ku, kv = k // grid.nv, k % grid.nv
    d = np.arange(-window, window + 1)
    iu = (ku[:, None] + d) % grid.nu
    iv = (kv[:, None] + d) % grid.nv
    win = flat[np.arange(n)[:, None, None], iu[:, :, None], iv[:, None, :]]
    win = np.exp(win - win.reshape(n, -1).max(axis=1)[:, None, None])
    win /= win.reshape(n, -1).sum(axis=1)[:, None, None]
    pu, pv = win.sum(axis=2), win.sum(axis=1)
    mu, mv = pu @ d, pv @ d
    cu = pu @ d ** 2 - mu ** 2
    cv = pv @ d ** 2 - mv ** 2
    cuv = np.einsum("nij,i,j->n", win, d, d) - mu * mv
    u = grid.u0 + np.mod((ku + mu + 0.5) * grid.step, grid.nu * grid.step)
    v = grid.v0 + np.mod((kv + mv + 0.5) * grid.step, grid.nv * grid.step)
    cov = np.stack([np.stack([cu, cuv], -1), np.stack([cuv, cv], -1)], -2) * grid.step ** 2
    return np.stack([u, v], -1).reshape(*lp.shape[:-2], 2), cov.reshape(*lp.shape[:-2], 2, 2)


def fuse(h: np.ndarray, uv: np.ndarray, var, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
    """The histogram likelihood ``softmax(h)`` (..., nu, nv) times the
    first stage's isotropic Gaussian ``N(uv, var)`` (..., 2), (...):
    its windowed mean and covariance (:func:`posterior_mean`). The Gaussian
    is measured from ``uv`` in the grid's coordinates (``uv`` inside the
    period; one outside it is compared with its image on the torus, and the
    answer is the image of the mean nearest ``uv``)."""
    uv = np.asarray(uv, float)
    var = np.asarray(var, float)
    cu, cv = bin_centres(grid)
    pu, pv = grid.nu * grid.step, grid.nv * grid.step
    du = cu - uv[..., 0:1]
    dv = cv - uv[..., 1:2]
    du = (du + pu / 2) % pu - pu / 2           # the nearest image on the torus
    dv = (dv + pv / 2) % pv - pv / 2
    g = -(du[..., :, None] ** 2 + dv[..., None, :] ** 2) / (2.0 * var[..., None, None])
    m, cov = posterior_mean(np.asarray(h, float) + g, grid)
    period = np.array([pu, pv])
    return uv + (m - uv + period / 2) % period - period / 2, cov
