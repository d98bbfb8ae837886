"""The output follows the light map: a smooth field of per-pixel white
balances applied before the one correction matrix.

When the estimate carries a light map (:mod:`recovery.light_mixture`,
``spatial="auto"`` decided several lights, or ``spatial=true``), each pixel
is white-balanced by the light where it is, not by the scene's one light.
The correction of a pixel at ``x`` is the image's matrix ``M`` (made for the
scene's light ``l0``: DNG matrices, highlights, exposure, tone) times the
diagonal von Kries change from the light there to ``l0``,

.. math:: M(x) = M \\, \\mathrm{diag}(l_0 / l(x)),

a field of correction matrices (the design's "smooth field of matrices"),
each the product of the image's matrix and a diagonal that changes smoothly:
the gains are bilinear between the map's centres, constant beyond the outer
ones, so there are no seams between cells and no halos at them. The gains
are normalised so the green channel's is 1 (the exposure is the image's).
Applied to the 16-bit linear camera image in place, rows at a time (the
strip path of :mod:`service.strips` included), with saturation at 65535.

References
----------
Wandell (1985) [docs/references.md#seed-002], 'A condition on spatial
variation' (the light varies slowly across the image). von Kries (1902),
chromatic adaptation as channel gains; Finlayson, Drew & Funt (1994),
Spectral sharpening (the diagonal model in a camera's space).
"""

from __future__ import annotations

import threading

import numpy as np

__all__ = ["GainField", "gain_field"]


class GainField:
    """Per-channel gains at the map's centres, in full-image pixels.

    Parameters
    ----------
    gains : (gr, gc, 3) gains at the centres (green 1)
    centres_r, centres_c : (gr,), (gc,) centre rows and columns in the full
        (uncropped, oriented) image's pixels
    """

    def __init__(self, gains: np.ndarray, centres_r: np.ndarray, centres_c: np.ndarray):
        self.gains = np.asarray(gains, np.float32)
        self.cr = np.asarray(centres_r, float)
        self.cc = np.asarray(centres_c, float)
        self._cols = {}

    @property
    def range(self) -> tuple[float, float]:
        """The smallest and largest gain of the field."""
        return float(self.gains.min()), float(self.gains.max())

    def _columns(self, c0: int, W: int) -> np.ndarray:
        """(gr, W, 3) the gains interpolated along each centre row at columns
        ``c0 .. c0 + W - 1``."""
        key = (c0, W)
        if key not in self._cols:
            cols = np.arange(c0, c0 + W, dtype=float)
            gr, gc = self.gains.shape[:2]
            fc = np.interp(cols, self.cc, np.arange(gc, dtype=float))
            j0 = np.floor(fc).astype(int)
            j1 = np.minimum(j0 + 1, gc - 1)
            t = (fc - j0)[None, :, None].astype(np.float32)
            self._cols[key] = np.ascontiguousarray((1 - t) * self.gains[:, j0] + t * self.gains[:, j1])
        return self._cols[key]

    def _steps(self, c0: int, W: int) -> np.ndarray:
        """(gr - 1, W, 3) differences between consecutive centre rows of :meth:`_columns`."""
        key = ("d", c0, W)
        if key not in self._cols:
            colg = self._columns(c0, W)
            self._cols[key] = np.ascontiguousarray(colg[1:] - colg[:-1])
        return self._cols[key]

    def rows(self, r0: int, r1: int, c0: int, W: int, out: np.ndarray | None = None) -> np.ndarray:
        """(r1 - r0, W, 3) float32 gains of image rows ``r0 .. r1 - 1`` and
        columns ``c0 .. c0 + W - 1`` (written into ``out`` when given, a
        float32 buffer of at least that many rows).

        Between centre rows ``i`` and ``i + 1`` a row at fraction ``t`` gets
        ``g_i + t (g_{i+1} - g_i)``: one multiply and one add per value, in
        place, for each run of rows between the same two centres (the
        bilinear weights ``(1 - t) g_i + t g_{i+1}``, fewer passes)."""
        colg = self._columns(c0, W)
        gr = colg.shape[0]
        n = r1 - r0
        fr = np.interp(np.arange(r0, r1, dtype=float), self.cr, np.arange(gr, dtype=float))
        i0 = np.minimum(np.floor(fr).astype(int), gr - 1)
        t = (fr - i0).astype(np.float32)
        g = np.empty((n, W, 3), np.float32) if out is None else out[:n]
        steps = self._steps(c0, W) if gr > 1 else None
        cuts = np.concatenate([[0], np.flatnonzero(np.diff(i0)) + 1, [n]])
        for a, b in zip(cuts[:-1], cuts[1:]):
            k = int(i0[a])
            if k >= gr - 1 or not np.any(t[a:b]):
                g[a:b] = colg[k]
            else:
                np.multiply(t[a:b, None, None], steps[k][None], out=g[a:b])
                g[a:b] += colg[k]
        return g

    def apply(self, rgb16: np.ndarray, r0: int = 0, c0: int = 0, block: int = 128,
              threads: int = 1) -> np.ndarray:
        """Multiply ``rgb16`` (h, W, 3) uint16, rows ``r0 ..`` and columns
        ``c0 ..`` of the full image, by the gains, in place (saturating at
        65535), ``block`` rows at a time, on ``threads`` threads (OpenCV and
        numpy release the interpreter lock). Each pixel's value depends on
        its own row and column only, so any cut into blocks, strips or
        threads gives the same pixels."""
        import cv2

        h, W = rgb16.shape[:2]
        local = threading.local()                # one gains buffer per thread, reused block after block

        def one(a):
            b = min(h, a + block)
            part = rgb16[a:b]
            buf = getattr(local, "buf", None)
            if buf is None:
                buf = local.buf = np.empty((min(block, h), W, 3), np.float32)
            g = self.rows(r0 + a, r0 + b, c0, W, out=buf)
            if part.flags.c_contiguous:
                cv2.multiply(part, g, dst=part, dtype=cv2.CV_16U)
            else:
                part[...] = cv2.multiply(np.ascontiguousarray(part), g, dtype=cv2.CV_16U)

        starts = range(0, h, block)
        if threads > 1 and h > 2 * block:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(threads) as ex:
                list(ex.map(one, starts))
        else:
            for a in starts:
                one(a)
        return rgb16


def gain_field(estimate, camera, factor: float, analysis_shape, full_shape) -> GainField | None:
    """The :class:`GainField` of an estimate's light map (None without one).

    Parameters
    ----------
    estimate : :class:`recovery.IlluminantEstimate` (``light_map``, ``rgb``)
    camera : the camera the estimate's spectra respond through
    factor : the analysis image's block factor (analysis pixel -> ``factor``
        full pixels)
    analysis_shape, full_shape : (rows, cols) of the analysis and full images
    """
    lm = getattr(estimate, "light_map", None)
    if lm is None:
        return None
    rr, cc = np.meshgrid(lm.centres_r, lm.centres_c, indexing="ij")
    rgb = np.asarray(camera.response(lm.spectra_at(rr.ravel(), cc.ravel())), float)
    if rgb.ndim != 2 or rgb.shape[1] != 3 or not np.all(np.isfinite(rgb)) or not np.all(rgb > 0):
        return None
    l0 = np.asarray(estimate.rgb, float)
    g = (l0[None, :] / rgb)
    g = g / g[:, 1:2]                                    # green 1: the exposure stays the image's
    if not np.all(np.isfinite(g)):
        return None
    eh, ew = analysis_shape[:2]
    H, W = full_shape[:2]
    # analysis pixel centre -> fraction of the image -> full-image pixel
    r_full = (lm.centres_r + 0.5) * factor / eh * H - 0.5
    c_full = (lm.centres_c + 0.5) * factor / ew * W - 0.5
    return GainField(g.reshape(rr.shape + (3,)), r_full, c_full)
