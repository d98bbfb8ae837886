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
# The same steps as the reference's loops, compiled by numba when it is
# installed (serial and without the GIL: strips run on threads), but run on
# the four colour-filter sub-planes like the numpy steps above: every inner
# loop walks one row of contiguous sub-plane values (unit stride, no branch),
# which the compiler turns into SIMD code; the reference's loops step over
# every other pixel of the full-resolution mosaic and stay scalar (3-4x
# slower here). The float32 operations and their order are the reference
# loops', pixel for pixel, so the result does not depend on the layout.
# Without numba the vectorised numpy steps above run instead (the same
# arithmetic up to float32 rounding: a test compares them).

def _nbr(A, py, px, dy, dx, i, nw):
    """Sub-plane row ``i`` of the site parity ``(py, px)``, columns ``_K:_K
    + nw``, moved by the full-resolution offset ``(dy, dx)``: the ``nw``
    values of ``A`` (``(4, h, w)``, one plane a parity ``2 * py + px``) at
    those neighbours (a contiguous view)."""
    sy = py + dy
    sx = px + dx
    j0 = _K + (sx >> 1)
    return A[(sy & 1) * 2 + (sx & 1), i + (sy >> 1), j0:j0 + nw]


def _mos(C, pat, py, px, dy, dx, i, nw):
    """:func:`_nbr` of the mosaic: each site's own colour in ``C`` (``(3,
    4, h, w)``: R, G, B of every parity)."""
    sy = py + dy
    sx = px + dx
    q = (sy & 1) * 2 + (sx & 1)
    j0 = _K + (sx >> 1)
    return C[pat[q], q, i + (sy >> 1), j0:j0 + nw]


def _rcd_planes(M, pat, P, n, m, out, scale, rnd, ws):
    """RCD of the padded float32 block ``M`` (even sides; colours ``pat[(r
    & 1) * 2 + (c & 1)]``: 0 R, 1 G, 2 B); rows/columns ``P:P + n``, ``P:P
    + m`` (``P`` even) written to ``out`` (``n x m x 3``) times ``scale``,
    clipped to ``[0, scale]``, plus ``rnd`` (0.5: rounded when ``out`` is
    integer). ``ws``: a flat workspace of at least ``7 * M.size`` finite
    float32 (reused from block to block: new memory is the slow part).
    Every step is computed on the sub-plane region ``[_K, h - _K) x [_K, w
    - _K)`` and reads at most 2 sub-plane pixels (4 mosaic pixels) around it."""
    Hb, Wb = M.shape
    h = Hb // 2
    w = Wb // 2
    N = h * w
    K = _K
    nw = w - 2 * K
    eps = np.float32(1e-5)
    epssq = np.float32(1e-10)
    half = np.float32(0.5)
    quarter = np.float32(0.25)
    three = np.float32(3.0)
    six = np.float32(6.0)
    one = np.float32(1.0)
    zero = np.float32(0.0)
    C = ws[0:12 * N].reshape((3, 4, h, w))      # R, G, B at every parity
    Vh = ws[12 * N:16 * N].reshape((4, h, w))   # step 1, then step 4.0's P
    Hh = ws[16 * N:20 * N].reshape((4, h, w))   # step 1, then step 4.0's Q
    VH = ws[20 * N:24 * N].reshape((4, h, w))
    L = ws[24 * N:28 * N].reshape((4, h, w))    # step 2's low-pass, then step 4.1's PQ
    for q in range(4):
        py = q >> 1
        px = q & 1
        k = pat[q]
        for i in range(h):
            src = M[2 * i + py]
            dst = C[k, q, i]
            for j in range(w):
                dst[j] = src[2 * j + px]
    # Step 1: vertical and horizontal discrimination
    for q in range(4):
        py = q >> 1
        px = q & 1
        for i in range(K, h - K):
            c0 = _mos(C, pat, py, px, 0, 0, i, nw)
            a3 = _mos(C, pat, py, px, -3, 0, i, nw)
            a2 = _mos(C, pat, py, px, -2, 0, i, nw)
            a1 = _mos(C, pat, py, px, -1, 0, i, nw)
            b1 = _mos(C, pat, py, px, 1, 0, i, nw)
            b2 = _mos(C, pat, py, px, 2, 0, i, nw)
            b3 = _mos(C, pat, py, px, 3, 0, i, nw)
            o = Vh[q, i, K:K + nw]
            for j in range(nw):
                v = (a3[j] - a1[j] - b1[j] + b3[j]) - three * (a2[j] + b2[j]) + six * c0[j]
                o[j] = v * v
            a3 = _mos(C, pat, py, px, 0, -3, i, nw)
            a2 = _mos(C, pat, py, px, 0, -2, i, nw)
            a1 = _mos(C, pat, py, px, 0, -1, i, nw)
            b1 = _mos(C, pat, py, px, 0, 1, i, nw)
            b2 = _mos(C, pat, py, px, 0, 2, i, nw)
            b3 = _mos(C, pat, py, px, 0, 3, i, nw)
            o = Hh[q, i, K:K + nw]
            for j in range(nw):
                v = (a3[j] - a1[j] - b1[j] + b3[j]) - three * (a2[j] + b2[j]) + six * c0[j]
                o[j] = v * v
    for q in range(4):
        py = q >> 1
        px = q & 1
        for i in range(K, h - K):
            vn = _nbr(Vh, py, px, -1, 0, i, nw)
            vc = _nbr(Vh, py, px, 0, 0, i, nw)
            vs = _nbr(Vh, py, px, 1, 0, i, nw)
            hw = _nbr(Hh, py, px, 0, -1, i, nw)
            hc = _nbr(Hh, py, px, 0, 0, i, nw)
            he = _nbr(Hh, py, px, 0, 1, i, nw)
            o = VH[q, i, K:K + nw]
            for j in range(nw):
                sv = max(epssq, vn[j] + vc[j] + vs[j])
                sh = max(epssq, hw[j] + hc[j] + he[j])
                o[j] = sv / (sv + sh)
    # Step 2: low-pass at the red and blue sites
    for q in range(4):
        if pat[q] == 1:
            continue
        py = q >> 1
        px = q & 1
        for i in range(K, h - K):
            c0 = _mos(C, pat, py, px, 0, 0, i, nw)
            sn = _mos(C, pat, py, px, -1, 0, i, nw)
            ss = _mos(C, pat, py, px, 1, 0, i, nw)
            sw = _mos(C, pat, py, px, 0, -1, i, nw)
            se = _mos(C, pat, py, px, 0, 1, i, nw)
            dnw = _mos(C, pat, py, px, -1, -1, i, nw)
            dne = _mos(C, pat, py, px, -1, 1, i, nw)
            dsw = _mos(C, pat, py, px, 1, -1, i, nw)
            dse = _mos(C, pat, py, px, 1, 1, i, nw)
            o = L[q, i, K:K + nw]
            for j in range(nw):
                o[j] = c0[j] + half * (sn[j] + ss[j] + sw[j] + se[j]) \
                    + quarter * (dnw[j] + dne[j] + dsw[j] + dse[j])
    # Step 3: green at the red and blue sites
    for q in range(4):
        if pat[q] == 1:
            continue
        py = q >> 1
        px = q & 1
        for i in range(K, h - K):
            c0 = _mos(C, pat, py, px, 0, 0, i, nw)
            n1 = _mos(C, pat, py, px, -1, 0, i, nw)
            n2 = _mos(C, pat, py, px, -2, 0, i, nw)
            n3 = _mos(C, pat, py, px, -3, 0, i, nw)
            n4 = _mos(C, pat, py, px, -4, 0, i, nw)
            s1 = _mos(C, pat, py, px, 1, 0, i, nw)
            s2 = _mos(C, pat, py, px, 2, 0, i, nw)
            s3 = _mos(C, pat, py, px, 3, 0, i, nw)
            s4 = _mos(C, pat, py, px, 4, 0, i, nw)
            w1 = _mos(C, pat, py, px, 0, -1, i, nw)
            w2 = _mos(C, pat, py, px, 0, -2, i, nw)
            w3 = _mos(C, pat, py, px, 0, -3, i, nw)
            w4 = _mos(C, pat, py, px, 0, -4, i, nw)
            e1 = _mos(C, pat, py, px, 0, 1, i, nw)
            e2 = _mos(C, pat, py, px, 0, 2, i, nw)
            e3 = _mos(C, pat, py, px, 0, 3, i, nw)
            e4 = _mos(C, pat, py, px, 0, 4, i, nw)
            l0 = _nbr(L, py, px, 0, 0, i, nw)
            ln = _nbr(L, py, px, -2, 0, i, nw)
            ls = _nbr(L, py, px, 2, 0, i, nw)
            lw = _nbr(L, py, px, 0, -2, i, nw)
            le = _nbr(L, py, px, 0, 2, i, nw)
            vc = _nbr(VH, py, px, 0, 0, i, nw)
            vnw = _nbr(VH, py, px, -1, -1, i, nw)
            vne = _nbr(VH, py, px, -1, 1, i, nw)
            vsw = _nbr(VH, py, px, 1, -1, i, nw)
            vse = _nbr(VH, py, px, 1, 1, i, nw)
            o = C[1, q, i, K:K + nw]
            for j in range(nw):
                cc = c0[j]
                Ng = eps + abs(n1[j] - s1[j]) + abs(cc - n2[j]) + abs(n1[j] - n3[j]) + abs(n2[j] - n4[j])
                Sg = eps + abs(s1[j] - n1[j]) + abs(cc - s2[j]) + abs(s1[j] - s3[j]) + abs(s2[j] - s4[j])
                Wg = eps + abs(e1[j] - w1[j]) + abs(cc - w2[j]) + abs(w1[j] - w3[j]) + abs(w2[j] - w4[j])
                Eg = eps + abs(w1[j] - e1[j]) + abs(cc - e2[j]) + abs(e1[j] - e3[j]) + abs(e2[j] - e4[j])
                L0 = l0[j]
                Ne = n1[j] * ((L0 - ln[j]) / (L0 + ln[j] + eps) + one)
                Se = s1[j] * ((L0 - ls[j]) / (L0 + ls[j] + eps) + one)
                We = w1[j] * ((L0 - lw[j]) / (L0 + lw[j] + eps) + one)
                Ee = e1[j] * ((L0 - le[j]) / (L0 + le[j] + eps) + one)
                V = (Sg * Ne + Ng * Se) / (Ng + Sg)
                Hz = (Wg * Ee + Eg * We) / (Eg + Wg)
                cen = vc[j]
                hood = (vnw[j] + vne[j] + vsw[j] + vse[j]) * quarter
                d = hood if abs(half - cen) < abs(half - hood) else cen
                g = (Hz - V) * d + V
                o[j] = min(one, max(zero, g))
    # Step 4.0: the diagonal high-pass at the red and blue sites
    for q in range(4):
        if pat[q] == 1:
            continue
        py = q >> 1
        px = q & 1
        for i in range(K, h - K):
            c0 = _mos(C, pat, py, px, 0, 0, i, nw)
            a3 = _mos(C, pat, py, px, -3, -3, i, nw)
            a2 = _mos(C, pat, py, px, -2, -2, i, nw)
            a1 = _mos(C, pat, py, px, -1, -1, i, nw)
            b1 = _mos(C, pat, py, px, 1, 1, i, nw)
            b2 = _mos(C, pat, py, px, 2, 2, i, nw)
            b3 = _mos(C, pat, py, px, 3, 3, i, nw)
            o = Vh[q, i, K:K + nw]
            for j in range(nw):
                v = (a3[j] - a1[j] - b1[j] + b3[j]) - three * (a2[j] + b2[j]) + six * c0[j]
                o[j] = v * v
            a3 = _mos(C, pat, py, px, -3, 3, i, nw)
            a2 = _mos(C, pat, py, px, -2, 2, i, nw)
            a1 = _mos(C, pat, py, px, -1, 1, i, nw)
            b1 = _mos(C, pat, py, px, 1, -1, i, nw)
            b2 = _mos(C, pat, py, px, 2, -2, i, nw)
            b3 = _mos(C, pat, py, px, 3, -3, i, nw)
            o = Hh[q, i, K:K + nw]
            for j in range(nw):
                v = (a3[j] - a1[j] - b1[j] + b3[j]) - three * (a2[j] + b2[j]) + six * c0[j]
                o[j] = v * v
    # Step 4.1: diagonal discrimination (the low-pass's planes reused)
    for q in range(4):
        if pat[q] == 1:
            continue
        py = q >> 1
        px = q & 1
        for i in range(K, h - K):
            pa = _nbr(Vh, py, px, -1, -1, i, nw)
            pc = _nbr(Vh, py, px, 0, 0, i, nw)
            pb = _nbr(Vh, py, px, 1, 1, i, nw)
            qa = _nbr(Hh, py, px, -1, 1, i, nw)
            qc = _nbr(Hh, py, px, 0, 0, i, nw)
            qb = _nbr(Hh, py, px, 1, -1, i, nw)
            o = L[q, i, K:K + nw]
            for j in range(nw):
                ps = max(epssq, pa[j] + pc[j] + pb[j])
                qs = max(epssq, qa[j] + qc[j] + qb[j])
                o[j] = ps / (ps + qs)
    # Step 4.2: red at the blue sites, blue at the red sites
    for q in range(4):
        if pat[q] == 1:
            continue
        py = q >> 1
        px = q & 1
        x = 2 if pat[q] == 0 else 0                  # the colour missing there
        for i in range(K, h - K):
            g0 = _nbr(C[1], py, px, 0, 0, i, nw)
            gnw2 = _nbr(C[1], py, px, -2, -2, i, nw)
            gne2 = _nbr(C[1], py, px, -2, 2, i, nw)
            gsw2 = _nbr(C[1], py, px, 2, -2, i, nw)
            gse2 = _nbr(C[1], py, px, 2, 2, i, nw)
            gnw = _nbr(C[1], py, px, -1, -1, i, nw)
            gne = _nbr(C[1], py, px, -1, 1, i, nw)
            gsw = _nbr(C[1], py, px, 1, -1, i, nw)
            gse = _nbr(C[1], py, px, 1, 1, i, nw)
            X = C[x]
            xnw = _nbr(X, py, px, -1, -1, i, nw)
            xne = _nbr(X, py, px, -1, 1, i, nw)
            xsw = _nbr(X, py, px, 1, -1, i, nw)
            xse = _nbr(X, py, px, 1, 1, i, nw)
            xnw3 = _nbr(X, py, px, -3, -3, i, nw)
            xne3 = _nbr(X, py, px, -3, 3, i, nw)
            xsw3 = _nbr(X, py, px, 3, -3, i, nw)
            xse3 = _nbr(X, py, px, 3, 3, i, nw)
            pc = _nbr(L, py, px, 0, 0, i, nw)
            pnw = _nbr(L, py, px, -1, -1, i, nw)
            pne = _nbr(L, py, px, -1, 1, i, nw)
            psw = _nbr(L, py, px, 1, -1, i, nw)
            pse = _nbr(L, py, px, 1, 1, i, nw)
            o = X[q, i, K:K + nw]
            for j in range(nw):
                gg = g0[j]
                nw_ = xnw[j]
                ne = xne[j]
                sw = xsw[j]
                se = xse[j]
                Gnw = eps + abs(nw_ - se) + abs(nw_ - xnw3[j]) + abs(gg - gnw2[j])
                Gne = eps + abs(ne - sw) + abs(ne - xne3[j]) + abs(gg - gne2[j])
                Gsw = eps + abs(ne - sw) + abs(sw - xsw3[j]) + abs(gg - gsw2[j])
                Gse = eps + abs(nw_ - se) + abs(se - xse3[j]) + abs(gg - gse2[j])
                enw = nw_ - gnw[j]
                ene = ne - gne[j]
                esw = sw - gsw[j]
                ese = se - gse[j]
                Pe = (Gnw * ese + Gse * enw) / (Gnw + Gse)
                Qe = (Gne * esw + Gsw * ene) / (Gne + Gsw)
                cen = pc[j]
                hood = (pnw[j] + pne[j] + psw[j] + pse[j]) * quarter
                d = hood if abs(half - cen) < abs(half - hood) else cen
                o[j] = (Qe - Pe) * d + Pe + gg
    # Step 4.3: red and blue at the green sites
    for q in range(4):
        if pat[q] != 1:
            continue
        py = q >> 1
        px = q & 1
        for i in range(K, h - K):
            vc = _nbr(VH, py, px, 0, 0, i, nw)
            vnw = _nbr(VH, py, px, -1, -1, i, nw)
            vne = _nbr(VH, py, px, -1, 1, i, nw)
            vsw = _nbr(VH, py, px, 1, -1, i, nw)
            vse = _nbr(VH, py, px, 1, 1, i, nw)
            g0 = _nbr(C[1], py, px, 0, 0, i, nw)
            gn2 = _nbr(C[1], py, px, -2, 0, i, nw)
            gs2 = _nbr(C[1], py, px, 2, 0, i, nw)
            gw2 = _nbr(C[1], py, px, 0, -2, i, nw)
            ge2 = _nbr(C[1], py, px, 0, 2, i, nw)
            gn = _nbr(C[1], py, px, -1, 0, i, nw)
            gs = _nbr(C[1], py, px, 1, 0, i, nw)
            gw = _nbr(C[1], py, px, 0, -1, i, nw)
            ge = _nbr(C[1], py, px, 0, 1, i, nw)
            for x in (0, 2):
                X = C[x]
                xn = _nbr(X, py, px, -1, 0, i, nw)
                xs = _nbr(X, py, px, 1, 0, i, nw)
                xw = _nbr(X, py, px, 0, -1, i, nw)
                xe = _nbr(X, py, px, 0, 1, i, nw)
                xn3 = _nbr(X, py, px, -3, 0, i, nw)
                xs3 = _nbr(X, py, px, 3, 0, i, nw)
                xw3 = _nbr(X, py, px, 0, -3, i, nw)
                xe3 = _nbr(X, py, px, 0, 3, i, nw)
                o = X[q, i, K:K + nw]
                for j in range(nw):
                    cen = vc[j]
                    hood = (vnw[j] + vne[j] + vsw[j] + vse[j]) * quarter
                    d = hood if abs(half - cen) < abs(half - hood) else cen
                    gg = g0[j]
                    N1 = abs(gg - gn2[j]) + eps
                    S1 = abs(gg - gs2[j]) + eps
                    W1 = abs(gg - gw2[j]) + eps
                    E1 = abs(gg - ge2[j]) + eps
                    a = xn[j]
                    b = xs[j]
                    c = xw[j]
                    e = xe[j]
                    sn = abs(a - b)
                    ew = abs(c - e)
                    Ng = abs(a - xn3[j]) + N1 + sn
                    Sg = abs(b - xs3[j]) + S1 + sn
                    Wg = abs(c - xw3[j]) + W1 + ew
                    Eg = abs(e - xe3[j]) + E1 + ew
                    V = (Ng * (b - gs[j]) + Sg * (a - gn[j])) / (Ng + Sg)
                    Hz = (Eg * (c - gw[j]) + Wg * (e - ge[j])) / (Eg + Wg)
                    o[j] = (Hz - V) * d + V + gg
    # the rows and columns P.. of the block, interleaved, scaled and clipped
    j0 = P >> 1
    for r in range(n):
        py = r & 1
        i = (P + r) >> 1
        for px in range(2):
            q = py * 2 + px
            rr = C[0, q, i]
            gg = C[1, q, i]
            bb = C[2, q, i]
            for c in range(px, m, 2):
                j = j0 + (c >> 1)
                out[r, c, 0] = min(one, max(zero, rr[j])) * scale + rnd
                out[r, c, 1] = min(one, max(zero, gg[j])) * scale + rnd
                out[r, c, 2] = min(one, max(zero, bb[j])) * scale + rnd
    return out


_KERNEL = {}
#: workspaces of :func:`_rcd_planes` not in use, kept for the next strip
#: (new memory is the slow part on a busy machine): at most :data:`_SPARE`
#: (one per core here: a 6000-pixel-wide strip of 128 rows holds 26 MB)
_FREE: list = []
_FREE_LOCK = threading.Lock()
_SPARE = 2


def _take_workspace(size: int) -> np.ndarray:
    """A workspace of :func:`_rcd_planes` for a block of ``size`` pixels: at
    least ``7 * size`` float32, zeros when new (so every value in it is
    finite), reused."""
    with _FREE_LOCK:
        for k, ws in enumerate(_FREE):
            if ws.size >= 7 * size:
                return _FREE.pop(k)
    return np.zeros(7 * size, np.float32)


def _give_workspace(ws: np.ndarray) -> None:
    with _FREE_LOCK:
        if len(_FREE) < _SPARE:
            _FREE.append(ws)


_KERNEL_LOCK = threading.Lock()


def _kernel():
    """The compiled :func:`_rcd_planes` (numba, cached on disk), or ``None``
    when numba is not installed. Compiled once per process, whichever thread
    asks first (the strips of one image ask from several)."""
    with _KERNEL_LOCK:
        if "k" not in _KERNEL:
            try:
                import numba
            except ImportError:
                _KERNEL["k"] = None
            else:
                global _nbr, _mos
                if not hasattr(_nbr, "py_func"):
                    _nbr = numba.njit(nogil=True, cache=True)(_nbr)
                    _mos = numba.njit(nogil=True, cache=True)(_mos)
                _KERNEL["k"] = numba.njit(nogil=True, cache=True, error_model="numpy")(_rcd_planes)
        return _KERNEL["k"]
