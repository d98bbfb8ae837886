"""Overlapping regions and the smooth light map.

References
----------
Wandell (1985) [docs/references.md#seed-002], Fig. 1 and 'A condition on spatial
variation': the image is analysed in overlapping regions, each with enough
surface variation; the light is assumed constant within a region; its scale
is fixed 'by consistency on overlaps' (the scalar :math:`\\alpha` of eq.
27-28 is not identified by the data inside one region).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import InsufficientSurfaceVariation
from .estimators import maloney_wandell_pixels
from .lighting import lighting_matrix
from .subspace import surface_weights

__all__ = ["tile_starts", "tile_regions", "region_count", "LightMap", "estimate_light_map",
           "overlap_log_scales", "bilinear"]


def tile_starts(length: int, size: int, overlap: float) -> np.ndarray:
    """Start offsets of tiles of ``size`` covering ``length`` with the given
    fractional ``overlap`` (0 <= overlap < 1); the last tile ends at ``length``."""
    if not 0 <= overlap < 1:
        raise ValueError(f"overlap must be in [0, 1), got {overlap}")
    size = max(1, min(int(size), length))
    step = max(1, int(round(size * (1 - overlap))))
    starts = list(range(0, length - size + 1, step))
    if starts[-1] != length - size:
        starts.append(length - size)
    return np.asarray(starts, dtype=int)


def tile_regions(shape: tuple[int, int], size: int, overlap: float = 0.5):
    """Regions as ``(row_starts, col_starts, size_r, size_c)``: the grid of
    overlapping square tiles (Fig. 1)."""
    h, w = shape[:2]
    sr, sc = min(size, h), min(size, w)
    return tile_starts(h, sr, overlap), tile_starts(w, sc, overlap), sr, sc


def bilinear(values: np.ndarray, centres_r: np.ndarray, centres_c: np.ndarray,
             rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Bilinear interpolation of ``values`` ``(gr, gc, K)`` given at the
    region centres, at points ``(rows, cols)``; constant beyond the outer
    centres. Returns ``(P, K)``."""
    gr, gc = values.shape[:2]
    fr = np.interp(rows, centres_r, np.arange(gr, dtype=float))
    fc = np.interp(cols, centres_c, np.arange(gc, dtype=float))
    r0 = np.floor(fr).astype(int)
    c0 = np.floor(fc).astype(int)
    r1 = np.minimum(r0 + 1, gr - 1)
    c1 = np.minimum(c0 + 1, gc - 1)
    tr = (fr - r0)[:, None]
    tc = (fc - c0)[:, None]
    return ((1 - tr) * (1 - tc) * values[r0, c0] + (1 - tr) * tc * values[r0, c1]
            + tr * (1 - tc) * values[r1, c0] + tr * tc * values[r1, c1])


@dataclass
class LightMap:
    """Light weights per region, consistent in scale, interpolable anywhere.

    Attributes
    ----------
    centres_r, centres_c : region centre coordinates (pixels)
    weights : (gr, gc, D(E)) light weights; rejected regions are filled
        from the nearest used region
    used : (gr, gc) bool, regions with enough surface variation
    fit_ratio, variation_ratio : (gr, gc) per-region diagnostics (NaN where
        rejected)
    light_basis : (N, D(E))
    """

    centres_r: np.ndarray
    centres_c: np.ndarray
    weights: np.ndarray
    used: np.ndarray
    fit_ratio: np.ndarray
    variation_ratio: np.ndarray
    light_basis: np.ndarray
    reasons: list = field(default_factory=list)

    def weights_at(self, rows, cols) -> np.ndarray:
        """Light weights at pixel coordinates, ``(P, D(E))``."""
        return bilinear(self.weights, self.centres_r, self.centres_c,
                        np.asarray(rows, float), np.asarray(cols, float))

    def spectra_at(self, rows, cols) -> np.ndarray:
        """Light spectra at pixel coordinates, ``(P, N)``."""
        return self.weights_at(rows, cols) @ self.light_basis.T


def region_count(shape: tuple[int, int], size: int, overlap: float = 0.5) -> int:
    """How many regions :func:`tile_regions` makes for an image of ``shape``:
    the literal light map's cost is linear in it (one eq. 30/35 solve per
    region, two eq. 36 solves per overlap)."""
    rs, cs, _, _ = tile_regions(shape, size, overlap)
    return int(rs.size * cs.size)


def overlap_log_scales(r: np.ndarray, s: np.ndarray, d: np.ndarray, n: int) -> np.ndarray:
    """The regions' log scales :math:`x = \\log\\alpha` made consistent on
    overlaps: the minimum-norm least-squares solution of

    .. math:: x_{r_k} - x_{s_k} = d_k \\ (k = 1..m), \\qquad \\tfrac{1}{n}\\textstyle\\sum_i x_i = 0,

    the system of step 2 of :func:`estimate_light_map` (one row per overlap
    of regions ``r[k]`` and ``s[k]``, ``d[k] = log(|sigma_r| / |sigma_s|)``
    from eq. 36 in both regions, and the gauge row fixing the free common
    scale of eq. 27-28), solved sparsely.

    The equations are the incidence matrix :math:`B` of the overlap graph;
    :math:`B^T B` is its Laplacian :math:`L`, whose null space is spanned by
    the indicator vectors of its connected components. The least-squares
    solutions of :math:`Bx = d` are :math:`z + \\sum_k c_k 1_{C_k}`, with
    :math:`z` the one of zero mean on every component; the gauge row is then
    met exactly when :math:`\\sum_k c_k |C_k| = 0`, and the norm
    :math:`\\|z\\|^2 + \\sum_k c_k^2 |C_k|` is least at :math:`c = 0`. So the
    answer is :math:`z`: on each component, :math:`L x = B^T d` with one node
    grounded (the reduced Laplacian of a connected graph is positive
    definite), then the component's mean removed. Memory and time grow with
    the number of overlaps (sparse LU of a planar grid graph), where the
    dense ``lstsq`` of the same system took ``(m + 1) x n`` floats and
    :math:`O(m n^2)` time; the answer is the same (``lstsq`` returns the
    minimum-norm solution too), to rounding.

    Parameters
    ----------
    r, s : (m,) int, the two regions of each overlap equation (``r != s``)
    d : (m,) float, the equations' right-hand sides
    n : number of regions (unknowns)

    Returns
    -------
    (n,) float, the log scales; regions in no overlap equation get 0.

    References
    ----------
    Wandell (1985) [docs/references.md#seed-002], Fig. 1 and eq. 27-28, 36
    (the scale fixed by consistency on overlaps); Golub & Van Loan,
    *Matrix Computations* (4th ed., 2013), sec. 5.5 (minimum-norm least
    squares); Chung, *Spectral Graph Theory* (1997), ch. 1 (the Laplacian's
    null space and its connected components).
    """
    from scipy import sparse                       # imported when needed, as scipy.ndimage below
    from scipy.sparse import csgraph
    from scipy.sparse.linalg import spsolve

    r, s, d = np.asarray(r, int), np.asarray(s, int), np.asarray(d, float)
    x = np.zeros(int(n))
    if n == 0 or r.size == 0:
        return x
    m = r.size
    rows = np.arange(m)
    B = sparse.csr_matrix((np.r_[np.ones(m), -np.ones(m)], (np.r_[rows, rows], np.r_[r, s])), shape=(m, n))
    L = (B.T @ B).tocsr()
    b = B.T @ d
    _, labels = csgraph.connected_components(L, directed=False)
    free = np.ones(n, bool)
    free[np.unique(labels, return_index=True)[1]] = False     # one grounded node per component
    if free.any():
        x[free] = np.atleast_1d(spsolve(L[free][:, free].tocsc(), b[free]))
    x -= (np.bincount(labels, x) / np.bincount(labels))[labels]
    return x


def _region_pixels(image, mask, r0, c0, sr, sc):
    block = image[r0:r0 + sr, c0:c0 + sc]
    m = mask[r0:r0 + sr, c0:c0 + sc]
    return block[m].astype(np.float64)


def estimate_light_map(image: np.ndarray, mask: np.ndarray, tensor: np.ndarray,
                       light_basis: np.ndarray, surface_dim: int, size: int, overlap: float = 0.5,
                       min_variation: float = 0.02, min_pixels: int = 16,
                       overlap_samples: int = 2048) -> tuple[LightMap, dict]:
    """Per-region Maloney-Wandell estimates made consistent on overlaps.

    1. Tile the image (Fig. 1); in each tile with at least ``min_pixels``
       usable pixels and ``s_D(S)/s_1 > min_variation`` solve eq. 30 and 35.
    2. Fix the free scale :math:`\\alpha_r` of every region's light so that the
       surfaces recovered in the overlap of neighbouring regions agree
       (eq. 36 in both regions; least squares on :math:`\\log\\alpha`).
    3. Fill rejected regions from the nearest used one; interpolate
       bilinearly between region centres (:meth:`LightMap.weights_at`).
    """
    h, w, _ = image.shape
    rs, cs, sr, sc = tile_regions((h, w), size, overlap)
    gr, gc = rs.size, cs.size
    d_e = tensor.shape[0]
    weights = np.full((gr, gc, d_e), np.nan)
    fit = np.full((gr, gc), np.nan)
    var = np.full((gr, gc), np.nan)
    used = np.zeros((gr, gc), bool)
    reasons = []
    for a, r0 in enumerate(rs):
        for b, c0 in enumerate(cs):
            px = _region_pixels(image, mask, r0, c0, sr, sc)
            if px.shape[0] < min_pixels:
                reasons.append(f"region ({a},{b}): {px.shape[0]} usable pixels < {min_pixels}")
                continue
            try:
                res = maloney_wandell_pixels(px, tensor, light_basis, surface_dim, min_variation)
            except InsufficientSurfaceVariation as e:
                reasons.append(f"region ({a},{b}): {e}")
                continue
            weights[a, b] = res.weights
            fit[a, b] = res.fit_ratio
            var[a, b] = res.variation_ratio
            used[a, b] = True
    if not used.any():
        raise InsufficientSurfaceVariation(
            f"no region of {sr}x{sc} pixels has enough surface variation "
            f"(need s_D(S)/s_1 > {min_variation} and >= {min_pixels} usable pixels)")

    # --- scale consistency on overlaps: log a_r - log a_s = log(|sig_r| / |sig_s|)
    idx = -np.ones((gr, gc), int)
    idx[used] = np.arange(used.sum())
    pair_r, pair_s, rhs = [], [], []
    rng = np.random.default_rng(0)
    for a in range(gr):
        for b in range(gc):
            if not used[a, b]:
                continue
            for a2, b2 in ((a + 1, b), (a, b + 1)):
                if a2 >= gr or b2 >= gc or not used[a2, b2]:
                    continue
                r_lo, r_hi = max(rs[a], rs[a2]), min(rs[a] + sr, rs[a2] + sr)
                c_lo, c_hi = max(cs[b], cs[b2]), min(cs[b] + sc, cs[b2] + sc)
                if r_hi <= r_lo or c_hi <= c_lo:
                    continue
                px = image[r_lo:r_hi, c_lo:c_hi][mask[r_lo:r_hi, c_lo:c_hi]].astype(float)
                if px.shape[0] == 0:
                    continue
                if px.shape[0] > overlap_samples:
                    px = px[rng.choice(px.shape[0], overlap_samples, replace=False)]
                s1, _ = surface_weights(lighting_matrix(weights[a, b], tensor), px)
                s2, _ = surface_weights(lighting_matrix(weights[a2, b2], tensor), px)
                n1, n2 = np.linalg.norm(s1), np.linalg.norm(s2)
                if n1 > 0 and n2 > 0 and np.isfinite(n1 + n2):
                    pair_r.append(idx[a, b])
                    pair_s.append(idx[a2, b2])
                    rhs.append(np.log(n1 / n2))
    n_used = int(used.sum())
    log_alpha = overlap_log_scales(np.asarray(pair_r, int), np.asarray(pair_s, int), np.asarray(rhs, float),
                                   n_used)
    weights[used] *= np.exp(log_alpha)[:, None]

    # --- fill rejected regions from the nearest used region
    if not used.all():
        from scipy import ndimage      # imported when needed: 0.1-0.2 s

        _, (ir, ic) = ndimage.distance_transform_edt(~used, return_indices=True)
        weights = weights[ir, ic]
    centres_r = rs + (sr - 1) / 2.0
    centres_c = cs + (sc - 1) / 2.0
    lm = LightMap(centres_r, centres_c, weights, used, fit, var, np.asarray(light_basis, float), reasons)
    diag = {
        "regions_total": int(gr * gc),
        "regions_used": n_used,
        "regions_rejected": int(gr * gc - n_used),
        "region_size": [int(sr), int(sc)],
        "region_overlap": float(overlap),
        "region_fit_ratio_median": float(np.nanmedian(fit)),
        "region_fit_ratio_max": float(np.nanmax(fit)),
        "overlap_equations": len(rhs),
    }
    return lm, diag
