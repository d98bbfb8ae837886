"""Edge-directed demosaicking of a 2x2 Bayer mosaic: Ratio Corrected
Demosaicing (RCD), vectorised on numpy.

RCD (Sanz Rodriguez 2017, v2.3, the default demosaic of RawTherapee and
darktable for Bayer sensors) interpolates green along the direction in which
the colour-difference signal has least high-pass energy, with each
neighbour's green corrected by the ratio of a low-pass of the mosaic at the
two sites, then red and blue by colour differences along the diagonals (at
the opposite colour's sites) and along the rows and columns (at green
sites), each direction's estimates weighted by inverse gradients.

The arithmetic is that of the reference C implementation (float32, mosaic
scaled to [0, 1]); here every step runs on the four colour-filter sub-planes
of the mosaic (each a contiguous array of one site of the 2x2 cell), so a
step that concerns only the red and blue sites touches only those. The
result at a pixel depends on the mosaic within :data:`MARGIN` pixels of it
only, and the same float32 operations run in the same order at every pixel:
a strip of rows demosaicked with its :data:`MARGIN` rows of context on
either side equals those rows of the whole image's demosaic bit for bit
(:func:`rcd_rows`). The image's edges are extended by mirror reflection
(without repeating the edge pixel, which keeps the filter phase).

References
----------
L. Sanz Rodriguez, "Ratio Corrected Demosaicing", v2.3 (2017), reference
implementation in RawTherapee (``rtengine/rcd_demosaic.cc``) and darktable
(``src/iop/demosaicing/rcd.c``); the algorithm as published there.
H. S. Malvar, L. He and R. Cutler, "High-quality linear interpolation for
demosaicing of Bayer-patterned color images", ICASSP 2004 (the gradient
correction idea that RCD's ratio correction refines).
"""

from __future__ import annotations

import threading

import numpy as np

__all__ = ["PATTERNS", "MARGIN", "rcd", "rcd_rows", "mosaic"]

#: The 2x2 Bayer cells: the colours of sites (0,0), (0,1), (1,0), (1,1).
PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")

#: Rows (and columns) of mosaic each side of a pixel given with it: its
#: value depends on fewer (RCD's steps reach 4 + 1 + 1 + 2 + 2 pixels; the
#: reference tiles with a border of 9); even, to keep the filter phase. The
#: tests check that strips of any height equal the whole image.
MARGIN = 12

_EPS = np.float32(1e-5)
_EPSSQ = np.float32(1e-10)
_K = 2          # inset (in sub-plane pixels) of every step's computed region


def mosaic(rgb: np.ndarray, pattern: str = "RGGB") -> np.ndarray:
    """The Bayer mosaic of an RGB image: at each site the channel its
    filter passes (``pattern``: the colours of the 2x2 cell's sites (0,0),
    (0,1), (1,0), (1,1), one of :data:`PATTERNS`)."""
    pattern = _check_pattern(pattern)
    out = np.empty(rgb.shape[:2], rgb.dtype)
    for (py, px), letter in zip(((0, 0), (0, 1), (1, 0), (1, 1)), pattern):
        out[py::2, px::2] = rgb[py::2, px::2, "RGB".index(letter)]
    return out


def _check_pattern(pattern: str) -> str:
    pattern = str(pattern).upper()
    if pattern not in PATTERNS:
        raise ValueError(f"pattern must be one of {list(PATTERNS)}, not {pattern!r}")
    return pattern


def rcd(cfa: np.ndarray, pattern: str = "RGGB", white: float | None = None, rows: int = 256,
        threads: int = 1, implementation: str = "auto") -> np.ndarray:
    """The RCD demosaic of a whole Bayer mosaic.

    Parameters
    ----------
    cfa : (H, W) array
        The mosaic, black-subtracted; uint16 or float.
    pattern : str
        The 2x2 cell (:data:`PATTERNS`).
    white : float, optional
        The mosaic's value of saturation (default: 65535 for uint16, 1
        otherwise); the result is clipped to ``[0, white]``.
    rows : int
        Rows demosaicked at a time (even; the result does not depend on it).
    threads : int
        Strips demosaicked at once (numba's loops and numpy's operations on
        arrays release the GIL).
    implementation : str
        :func:`rcd_rows`'s.

    Returns
    -------
    (H, W, 3) array of ``cfa``'s dtype (uint16 rounded) or float32
        Linear RGB.
    """
    H, W = cfa.shape
    out = np.empty((H, W, 3), np.uint16 if cfa.dtype == np.uint16 else np.float32)
    rows = max(2, int(rows) + int(rows) % 2)
    tasks = list(range(0, H, rows))

    def one(r0):
        rcd_rows(cfa, pattern, r0, min(H, r0 + rows), white=white, out=out[r0:r0 + rows],
                 implementation=implementation)

    if threads > 1 and len(tasks) > 1:
        from concurrent.futures import ThreadPoolExecutor

        with ThreadPoolExecutor(threads) as pool:
            list(pool.map(one, tasks))
    else:
        for r0 in tasks:
            one(r0)
    return out


def rcd_rows(cfa: np.ndarray, pattern: str, r0: int, r1: int, white: float | None = None,
             out: np.ndarray | None = None, c0: int = 0, c1: int | None = None,
             implementation: str = "auto") -> np.ndarray:
    """Rows ``r0:r1`` (columns ``c0:c1``) of the RCD demosaic of the whole
    mosaic ``cfa`` (:func:`rcd`), from those rows and :data:`MARGIN` rows
    either side: equal to the same rows of :func:`rcd` bit for bit.
    ``out``: where to write them (``(r1 - r0, c1 - c0, 3)``).
    ``implementation``: ``"numba"`` (the compiled loops), ``"numpy"`` (the
    vectorised steps) or ``"auto"`` (numba when it is installed)."""
    pattern = _check_pattern(pattern)
    H, W = cfa.shape
    c1 = W if c1 is None else c1
    if not (0 <= r0 < r1 <= H and 0 <= c0 < c1 <= W):
        raise ValueError(f"rows {r0}:{r1}, columns {c0}:{c1} outside a {H}x{W} mosaic")
    if white is None:
        white = 65535.0 if cfa.dtype == np.uint16 else 1.0
    P = MARGIN
    s0, s1 = max(0, r0 - P), min(H, r1 + P)
    t0, t1 = max(0, c0 - P), min(W, c1 + P)
    block = cfa[s0:s1, t0:t1].astype(np.float32)
    block *= np.float32(1.0 / white)
    # mirror the image's own edges only (elsewhere the context is the mosaic's)
    top, left = P - (r0 - s0), P - (c0 - t0)
    bottom, right = P - (s1 - r1), P - (t1 - c1)
    # the padded block starts on the filter phase of row r0 - P, column c0 - P
    bottom += (block.shape[0] + top + bottom) % 2
    right += (block.shape[1] + left + right) % 2
    if top or bottom or left or right:
        block = np.pad(block, ((top, bottom), (left, right)), mode="reflect")
    # the cell's colours as seen from the block's (0, 0): mosaic site (r0 - P, c0 - P)
    shift = ((r0 - P) % 2, (c0 - P) % 2)
    letters = {(py, px): pattern[((py + shift[0]) % 2) * 2 + (px + shift[1]) % 2]
               for py in (0, 1) for px in (0, 1)}
    n, m = r1 - r0, c1 - c0
    if out is None:
        out = np.empty((n, m, 3), np.uint16 if cfa.dtype == np.uint16 else np.float32)
    kernel = _kernel() if implementation in ("auto", "numba") else None
    if implementation == "numba" and kernel is None:
        raise RuntimeError("numba is not installed")
    if kernel is not None:
        pat = np.array(["RGB".index(letters[(py, px)]) for py in (0, 1) for px in (0, 1)], np.int64)
        integer = out.dtype == np.uint16
        ws = _take_workspace(block.size)
        try:
            kernel(block, pat, P, n, m, out, np.float32(65535.0 if integer else white),
                   np.float32(0.5 if integer else 0.0), ws)
        finally:
            _give_workspace(ws)
        return out
    R, G, B = _rcd_core(block, letters)
    for ch, planes in enumerate((R, G, B)):
        for (py, px), plane in planes.items():
            # full-resolution rows P.. of the block: sub-plane rows from (P - py + 1) // 2
            i0, j0 = (P - py + 1) // 2, (P - px + 1) // 2
            oy, ox = 2 * i0 + py - P, 2 * j0 + px - P            # 0 or 1: the first output row/col of that parity
            ni, nj = len(range(oy, n, 2)), len(range(ox, m, 2))
            v = plane[i0:i0 + ni, j0:j0 + nj]
            dst = out[oy::2, ox::2, ch]
            if out.dtype == np.uint16:
                v = v * np.float32(65535.0)
                np.clip(v, 0, 65535, out=v)
                v += np.float32(0.5)
                dst[...] = v
            else:
                np.clip(v, 0, 1, out=dst)
                if white != 1.0:
                    dst *= np.float32(white)
    return out


def _rcd_core(M: np.ndarray, letters: dict) -> tuple[dict, dict, dict]:
    """RCD on a float32 mosaic in [0, 1] of even size whose site ``(py,
    px)`` of the cell has colour ``letters[(py, px)]``: the R, G and B
    planes as dicts of the four sub-planes (valid :data:`MARGIN` pixels in
    from the edges)."""
    h, w = M.shape[0] // 2, M.shape[1] // 2
    K = _K
    par = [(0, 0), (0, 1), (1, 0), (1, 1)]
    S = {p: np.ascontiguousarray(M[p[0]::2, p[1]::2]) for p in par}
    greens = [p for p in par if letters[p] == "G"]
    rb = [p for p in par if letters[p] != "G"]
    inner = (slice(K, h - K), slice(K, w - K))

    def nb(A, p, dy, dx):
        """``A`` (a dict of sub-planes) at full-resolution offset (dy, dx)
        from the sites of parity ``p``, over the computed region."""
        qy, qx = p[0] + dy, p[1] + dx
        oy, ox = qy // 2, qx // 2
        return A[(qy % 2, qx % 2)][K + oy:h - K + oy, K + ox:w - K + ox]

    def new():
        return np.zeros((h, w), np.float32)

    f = np.float32
    # Step 1: the squared high-pass of the colour difference along columns
    # and rows, summed over three sites: vertical/horizontal discrimination
    Vh, Hh, VH = {}, {}, {}
    for p in par:
        for A, d in ((Vh, (1, 0)), (Hh, (0, 1))):
            def c(k):
                return nb(S, p, k * d[0], k * d[1])
            a = new()
            t = a[inner]
            np.subtract(c(-3), c(-1), out=t)
            t -= c(1)
            t += c(3)
            u = c(-2) + c(2)
            u *= f(3)
            t -= u
            t += f(6) * c(0)
            np.square(t, out=t)
            A[p] = a
    for p in par:
        v = nb(Vh, p, -1, 0) + nb(Vh, p, 0, 0)
        v += nb(Vh, p, 1, 0)
        np.maximum(v, _EPSSQ, out=v)
        hh = nb(Hh, p, 0, -1) + nb(Hh, p, 0, 0)
        hh += nb(Hh, p, 0, 1)
        np.maximum(hh, _EPSSQ, out=hh)
        a = new()
        hh += v
        np.divide(v, hh, out=a[inner])
        VH[p] = a
    del Vh, Hh

    # Step 2: a low-pass of the mosaic at the red and blue sites
    lpf = {}
    for p in rb:
        a = new()
        t = a[inner]
        np.add(nb(S, p, -1, 0), nb(S, p, 1, 0), out=t)
        t += nb(S, p, 0, -1)
        t += nb(S, p, 0, 1)
        t *= f(0.5)
        u = nb(S, p, -1, -1) + nb(S, p, -1, 1)
        u += nb(S, p, 1, -1)
        u += nb(S, p, 1, 1)
        u *= f(0.25)
        t += u
        t += nb(S, p, 0, 0)
        lpf[p] = a

    def disc(D, p):
        """The refined discrimination: the site's own or the mean of its
        four diagonal neighbours', whichever is further from 0.5."""
        centre = nb(D, p, 0, 0)
        hood = nb(D, p, -1, -1) + nb(D, p, -1, 1)
        hood += nb(D, p, 1, -1)
        hood += nb(D, p, 1, 1)
        hood *= f(0.25)
        return np.where(np.abs(f(0.5) - centre) < np.abs(f(0.5) - hood), hood, centre)

    # Step 3: green at the red and blue sites
    Gp = {p: S[p] for p in greens}
    for p in rb:
        c0 = nb(S, p, 0, 0)
        L0 = nb(lpf, p, 0, 0)
        est = {}
        grad = {}
        for name, (dy, dx) in (("N", (-1, 0)), ("S", (1, 0)), ("W", (0, -1)), ("E", (0, 1))):
            n1, n2, n3, n4 = (nb(S, p, k * dy, k * dx) for k in (1, 2, 3, 4))
            o1 = nb(S, p, -dy, -dx)
            g = np.abs(o1 - n1)
            g += np.abs(c0 - n2)
            g += np.abs(n1 - n3)
            g += np.abs(n2 - n4)
            g += _EPS
            grad[name] = g
            L2 = nb(lpf, p, 2 * dy, 2 * dx)
            r = L0 - L2
            den = L0 + L2
            den += _EPS
            r /= den
            r += f(1)
            r *= n1
            est[name] = r
        den = grad["N"] + grad["S"]
        V = grad["S"] * est["N"]
        V += grad["N"] * est["S"]
        V /= den
        den = grad["E"] + grad["W"]
        Hz = grad["W"] * est["E"]
        Hz += grad["E"] * est["W"]
        Hz /= den
        d = disc(VH, p)
        # d * H + (1 - d) * V = V + d * (H - V)
        Hz -= V
        Hz *= d
        Hz += V
        a = new()
        np.clip(Hz, 0, 1, out=a[inner])
        Gp[p] = a
    del lpf

    # Step 4.0-4.1: diagonal discrimination at the red and blue sites
    PQ = {}
    Ph, Qh = {}, {}
    for p in rb:
        for A, (sy, sx) in ((Ph, (1, 1)), (Qh, (1, -1))):
            def c(k):
                return nb(S, p, k * sy, k * sx)
            a = new()
            t = a[inner]
            np.subtract(c(-3), c(-1), out=t)
            t -= c(1)
            t += c(3)
            u = c(-2) + c(2)
            u *= f(3)
            t -= u
            t += f(6) * c(0)
            np.square(t, out=t)
            A[p] = a
    # the diagonal neighbours of a red or blue site are the other colour's sites
    for p in rb:
        ps = nb(Ph, p, -1, -1) + nb(Ph, p, 0, 0)
        ps += nb(Ph, p, 1, 1)
        np.maximum(ps, _EPSSQ, out=ps)
        qs = nb(Qh, p, -1, 1) + nb(Qh, p, 0, 0)
        qs += nb(Qh, p, 1, -1)
        np.maximum(qs, _EPSSQ, out=qs)
        a = new()
        qs += ps
        np.divide(ps, qs, out=a[inner])
        PQ[p] = a
    del Ph, Qh

    # Step 4.2: red at the blue sites and blue at the red sites
    other = {}
    for p in rb:
        g0 = nb(Gp, p, 0, 0)
        nw, ne, sw, se = (nb(S, p, dy, dx) for dy, dx in ((-1, -1), (-1, 1), (1, -1), (1, 1)))
        g_nw = np.abs(nw - se)
        g_nw += np.abs(nw - nb(S, p, -3, -3))
        g_nw += np.abs(g0 - nb(Gp, p, -2, -2))
        g_nw += _EPS
        g_ne = np.abs(ne - sw)
        g_ne += np.abs(ne - nb(S, p, -3, 3))
        g_ne += np.abs(g0 - nb(Gp, p, -2, 2))
        g_ne += _EPS
        g_sw = np.abs(ne - sw)
        g_sw += np.abs(sw - nb(S, p, 3, -3))
        g_sw += np.abs(g0 - nb(Gp, p, 2, -2))
        g_sw += _EPS
        g_se = np.abs(nw - se)
        g_se += np.abs(se - nb(S, p, 3, 3))
        g_se += np.abs(g0 - nb(Gp, p, 2, 2))
        g_se += _EPS
        e_nw = nw - nb(Gp, p, -1, -1)
        e_ne = ne - nb(Gp, p, -1, 1)
        e_sw = sw - nb(Gp, p, 1, -1)
        e_se = se - nb(Gp, p, 1, 1)
        Pe = g_nw * e_se
        Pe += g_se * e_nw
        g_nw += g_se
        Pe /= g_nw
        Qe = g_ne * e_sw
        Qe += g_sw * e_ne
        g_ne += g_sw
        Qe /= g_ne
        d = disc(PQ, p)
        # (1 - d) * P + d * Q = P + d * (Q - P)
        Qe -= Pe
        Qe *= d
        Qe += Pe
        Qe += g0
        a = new()
        a[inner] = Qe
        other[p] = a
    del PQ

    # the red and blue planes at the red and blue sites
    Rp, Bp = {}, {}
    for p in rb:
        (Rp if letters[p] == "R" else Bp)[p] = S[p]
        (Bp if letters[p] == "R" else Rp)[p] = other[p]

    # Step 4.3: red and blue at the green sites
    for p in greens:
        d = disc(VH, p)
        g0 = nb(Gp, p, 0, 0)
        n1 = np.abs(g0 - nb(Gp, p, -2, 0))
        n1 += _EPS
        s1 = np.abs(g0 - nb(Gp, p, 2, 0))
        s1 += _EPS
        w1 = np.abs(g0 - nb(Gp, p, 0, -2))
        w1 += _EPS
        e1 = np.abs(g0 - nb(Gp, p, 0, 2))
        e1 += _EPS
        gn, gs, gw, ge = (nb(Gp, p, dy, dx) for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)))
        for X in (Rp, Bp):
            xn, xs, xw, xe = (nb(X, p, dy, dx) for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)))
            sn = np.abs(xn - xs)
            ew = np.abs(xw - xe)
            Ng = np.abs(xn - nb(X, p, -3, 0))
            Ng += n1
            Ng += sn
            Sg = np.abs(xs - nb(X, p, 3, 0))
            Sg += s1
            Sg += sn
            Wg = np.abs(xw - nb(X, p, 0, -3))
            Wg += w1
            Wg += ew
            Eg = np.abs(xe - nb(X, p, 0, 3))
            Eg += e1
            Eg += ew
            Ne, Se, We, Ee = xn - gn, xs - gs, xw - gw, xe - ge
            V = Ng * Se
            V += Sg * Ne
            Ng += Sg
            V /= Ng
            Hz = Eg * We
            Hz += Wg * Ee
            Eg += Wg
            Hz /= Eg
            # (1 - d) * V + d * H
            Hz -= V
            Hz *= d
            Hz += V
            Hz += g0
            a = new()
            a[inner] = Hz
            X[p] = a
    return Rp, Gp, Bp


# --- the compiled kernel ----------------------------------------------------
#
# The same steps pixel by pixel (the reference's loops), compiled by numba
# when it is installed (serial and without the GIL: strips run on threads).
# Without numba the vectorised numpy steps above run instead (the same
# arithmetic up to float32 rounding: a test compares them).

def _rcd_loops(M, pat, P, n, m, out, scale, rnd, ws):
    """RCD of the padded float32 block ``M`` (colours ``pat[(r & 1) * 2 +
    (c & 1)]``: 0 R, 1 G, 2 B); rows/columns ``P:P + n``, ``P:P + m``
    written to ``out`` (``n x m x 3``) times ``scale``, clipped to
    ``[0, scale]``, plus ``rnd`` (0.5: rounded when ``out`` is integer).
    ``ws``: a workspace of 8 finite float32 rows of at least ``M.size``
    (reused from block to block: new memory is the slow part)."""
    H, W = M.shape
    eps = np.float32(1e-5)
    epssq = np.float32(1e-10)
    half = np.float32(0.5)
    quarter = np.float32(0.25)
    three = np.float32(3.0)
    six = np.float32(6.0)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    N = H * W
    Vh = ws[0, :N].reshape((H, W))
    Hh = ws[1, :N].reshape((H, W))
    VH = ws[2, :N].reshape((H, W))
    lpf = ws[3, :N].reshape((H, W))
    PQ = ws[4, :N].reshape((H, W))
    rgb0 = ws[5, :N].reshape((H, W))
    rgb1 = ws[6, :N].reshape((H, W))
    rgb2 = ws[7, :N].reshape((H, W))
    for r in range(H):
        for c in range(W):
            k = pat[(r & 1) * 2 + (c & 1)]
            if k == 0:
                rgb0[r, c] = M[r, c]
            elif k == 1:
                rgb1[r, c] = M[r, c]
            else:
                rgb2[r, c] = M[r, c]
    # Step 1: vertical and horizontal discrimination
    for r in range(3, H - 3):
        for c in range(3, W - 3):
            v = (M[r - 3, c] - M[r - 1, c] - M[r + 1, c] + M[r + 3, c]) - three * (M[r - 2, c] + M[r + 2, c]) \
                + six * M[r, c]
            Vh[r, c] = v * v
            h = (M[r, c - 3] - M[r, c - 1] - M[r, c + 1] + M[r, c + 3]) - three * (M[r, c - 2] + M[r, c + 2]) \
                + six * M[r, c]
            Hh[r, c] = h * h
    for r in range(4, H - 4):
        for c in range(4, W - 4):
            vs = max(epssq, Vh[r - 1, c] + Vh[r, c] + Vh[r + 1, c])
            hs = max(epssq, Hh[r, c - 1] + Hh[r, c] + Hh[r, c + 1])
            VH[r, c] = vs / (vs + hs)
    # Step 2: low-pass at the red and blue sites
    for r in range(1, H - 1):
        for c in range(1 + _rb_col(pat, r + 1), W - 1, 2):
                lpf[r, c] = M[r, c] + half * (M[r - 1, c] + M[r + 1, c] + M[r, c - 1] + M[r, c + 1]) \
                    + quarter * (M[r - 1, c - 1] + M[r - 1, c + 1] + M[r + 1, c - 1] + M[r + 1, c + 1])
    # Step 3: green at the red and blue sites
    for r in range(4, H - 4):
        for c in range(4 + _rb_col(pat, r), W - 4, 2):
            c0 = M[r, c]
            Ng = eps + abs(M[r - 1, c] - M[r + 1, c]) + abs(c0 - M[r - 2, c]) + abs(M[r - 1, c] - M[r - 3, c]) \
                + abs(M[r - 2, c] - M[r - 4, c])
            Sg = eps + abs(M[r + 1, c] - M[r - 1, c]) + abs(c0 - M[r + 2, c]) + abs(M[r + 1, c] - M[r + 3, c]) \
                + abs(M[r + 2, c] - M[r + 4, c])
            Wg = eps + abs(M[r, c + 1] - M[r, c - 1]) + abs(c0 - M[r, c - 2]) + abs(M[r, c - 1] - M[r, c - 3]) \
                + abs(M[r, c - 2] - M[r, c - 4])
            Eg = eps + abs(M[r, c - 1] - M[r, c + 1]) + abs(c0 - M[r, c + 2]) + abs(M[r, c + 1] - M[r, c + 3]) \
                + abs(M[r, c + 2] - M[r, c + 4])
            L0 = lpf[r, c]
            Ne = M[r - 1, c] * ((L0 - lpf[r - 2, c]) / (L0 + lpf[r - 2, c] + eps) + one)
            Se = M[r + 1, c] * ((L0 - lpf[r + 2, c]) / (L0 + lpf[r + 2, c] + eps) + one)
            We = M[r, c - 1] * ((L0 - lpf[r, c - 2]) / (L0 + lpf[r, c - 2] + eps) + one)
            Ee = M[r, c + 1] * ((L0 - lpf[r, c + 2]) / (L0 + lpf[r, c + 2] + eps) + one)
            V = (Sg * Ne + Ng * Se) / (Ng + Sg)
            Hz = (Wg * Ee + Eg * We) / (Eg + Wg)
            cen = VH[r, c]
            hood = (VH[r - 1, c - 1] + VH[r - 1, c + 1] + VH[r + 1, c - 1] + VH[r + 1, c + 1]) * quarter
            d = hood if abs(half - cen) < abs(half - hood) else cen
            g = (Hz - V) * d + V
            rgb1[r, c] = min(one, max(zero, g))
    # Step 4.0-4.1: diagonal discrimination at the red and blue sites
    for r in range(3, H - 3):
        for c in range(3 + _rb_col(pat, r + 1), W - 3, 2):
            p = (M[r - 3, c - 3] - M[r - 1, c - 1] - M[r + 1, c + 1] + M[r + 3, c + 3]) \
                - three * (M[r - 2, c - 2] + M[r + 2, c + 2]) + six * M[r, c]
            Vh[r, c] = p * p
            q = (M[r - 3, c + 3] - M[r - 1, c + 1] - M[r + 1, c - 1] + M[r + 3, c - 3]) \
                - three * (M[r - 2, c + 2] + M[r + 2, c - 2]) + six * M[r, c]
            Hh[r, c] = q * q
    for r in range(4, H - 4):
        for c in range(4 + _rb_col(pat, r), W - 4, 2):
            ps = max(epssq, Vh[r - 1, c - 1] + Vh[r, c] + Vh[r + 1, c + 1])
            qs = max(epssq, Hh[r - 1, c + 1] + Hh[r, c] + Hh[r + 1, c - 1])
            PQ[r, c] = ps / (ps + qs)
    # Step 4.2: red at the blue sites, blue at the red sites
    for r in range(4, H - 4):
        c4 = 4 + _rb_col(pat, r)
        X = rgb2 if pat[(r & 1) * 2 + (c4 & 1)] == 0 else rgb0     # the colour missing there
        for c in range(c4, W - 4, 2):
            g0 = rgb1[r, c]
            nw = X[r - 1, c - 1]
            ne = X[r - 1, c + 1]
            sw = X[r + 1, c - 1]
            se = X[r + 1, c + 1]
            gnw = eps + abs(nw - se) + abs(nw - X[r - 3, c - 3]) + abs(g0 - rgb1[r - 2, c - 2])
            gne = eps + abs(ne - sw) + abs(ne - X[r - 3, c + 3]) + abs(g0 - rgb1[r - 2, c + 2])
            gsw = eps + abs(ne - sw) + abs(sw - X[r + 3, c - 3]) + abs(g0 - rgb1[r + 2, c - 2])
            gse = eps + abs(nw - se) + abs(se - X[r + 3, c + 3]) + abs(g0 - rgb1[r + 2, c + 2])
            enw = nw - rgb1[r - 1, c - 1]
            ene = ne - rgb1[r - 1, c + 1]
            esw = sw - rgb1[r + 1, c - 1]
            ese = se - rgb1[r + 1, c + 1]
            Pe = (gnw * ese + gse * enw) / (gnw + gse)
            Qe = (gne * esw + gsw * ene) / (gne + gsw)
            cen = PQ[r, c]
            hood = (PQ[r - 1, c - 1] + PQ[r - 1, c + 1] + PQ[r + 1, c - 1] + PQ[r + 1, c + 1]) * quarter
            d = hood if abs(half - cen) < abs(half - hood) else cen
            X[r, c] = (Qe - Pe) * d + Pe + g0
    # Step 4.3: red and blue at the green sites
    for r in range(4, H - 4):
        for c in range(4 + 1 - _rb_col(pat, r), W - 4, 2):
            cen = VH[r, c]
            hood = (VH[r - 1, c - 1] + VH[r - 1, c + 1] + VH[r + 1, c - 1] + VH[r + 1, c + 1]) * quarter
            d = hood if abs(half - cen) < abs(half - hood) else cen
            g0 = rgb1[r, c]
            n1 = abs(g0 - rgb1[r - 2, c]) + eps
            s1 = abs(g0 - rgb1[r + 2, c]) + eps
            w1 = abs(g0 - rgb1[r, c - 2]) + eps
            e1 = abs(g0 - rgb1[r, c + 2]) + eps
            for X in (rgb0, rgb2):
                xn = X[r - 1, c]
                xs = X[r + 1, c]
                xw = X[r, c - 1]
                xe = X[r, c + 1]
                sn = abs(xn - xs)
                ew = abs(xw - xe)
                Ng = abs(xn - X[r - 3, c]) + n1 + sn
                Sg = abs(xs - X[r + 3, c]) + s1 + sn
                Wg = abs(xw - X[r, c - 3]) + w1 + ew
                Eg = abs(xe - X[r, c + 3]) + e1 + ew
                V = (Ng * (xs - rgb1[r + 1, c]) + Sg * (xn - rgb1[r - 1, c])) / (Ng + Sg)
                Hz = (Eg * (xw - rgb1[r, c - 1]) + Wg * (xe - rgb1[r, c + 1])) / (Eg + Wg)
                X[r, c] = (Hz - V) * d + V + g0
    for i in range(n):
        for j in range(m):
            out[i, j, 0] = min(one, max(zero, rgb0[P + i, P + j])) * scale + rnd
            out[i, j, 1] = min(one, max(zero, rgb1[P + i, P + j])) * scale + rnd
            out[i, j, 2] = min(one, max(zero, rgb2[P + i, P + j])) * scale + rnd
    return out


def _rb_col(pat, r):
    """0 or 1: the first column of row ``r`` holding a red or blue site."""
    return 0 if pat[(r & 1) * 2] != 1 else 1


_KERNEL = {}
#: workspaces of :func:`_rcd_loops` not in use, kept for the next strip
#: (new memory is the slow part on a busy machine): at most :data:`_SPARE`
#: (one per core here: a 6000-pixel-wide strip of 128 rows holds 29 MB)
_FREE: list = []
_FREE_LOCK = threading.Lock()
_SPARE = 2


def _take_workspace(size: int) -> np.ndarray:
    """A workspace of :func:`_rcd_loops`: 8 rows of at least ``size``
    float32, zeros when new (so every value in it is finite), reused."""
    with _FREE_LOCK:
        for k, ws in enumerate(_FREE):
            if ws.shape[1] >= size:
                return _FREE.pop(k)
    return np.zeros((8, size), np.float32)


def _give_workspace(ws: np.ndarray) -> None:
    with _FREE_LOCK:
        if len(_FREE) < _SPARE:
            _FREE.append(ws)


_KERNEL_LOCK = threading.Lock()


def _kernel():
    """The compiled :func:`_rcd_loops` (numba, cached on disk), or ``None``
    when numba is not installed. Compiled once per process, whichever thread
    asks first (the strips of one image ask from several)."""
    with _KERNEL_LOCK:
        if "k" not in _KERNEL:
            try:
                import numba
            except ImportError:
                _KERNEL["k"] = None
            else:
                global _rb_col
                if not hasattr(_rb_col, "py_func"):
                    _rb_col = numba.njit(cache=True)(_rb_col)
                _KERNEL["k"] = numba.njit(nogil=True, cache=True)(_rcd_loops)
        return _KERNEL["k"]
