"""Learnt illuminant estimation for any camera, from what its RAW says about it.

Real scenes are not Mondrians of measured reflectances: large walls,
shadows, highlights, skies and many near-neutral surfaces decide which
simple statistic of an image points at its light. Each classical estimator
is right for some scenes (gray world, shades of gray, max-RGB, gray edge of
first and second order, bright pixels, gray pixels); this estimator learns,
from real photographs with measured lights, how to combine them, in a space
where what is learnt on some cameras holds for others:

1. the camera's colour matrix (XYZ -> camera, from the DNG or LibRaw's
   table; fitted to measured sensitivities otherwise) maps its linear data
   to XYZ and on to one fixed *canonical* RGB, the Bradford cone space
   (a sharpened, camera-like space chosen before looking at any data, so
   no camera defines it), and a camera never seen is handled through its
   matrix (the linear form of CCMNet's idea, Kim et al. 2025);
2. the image is area-averaged to the resolution the model was trained at
   (64 x 64 cells, the development thumbnails), saturated and dark pixels
   left out, so a 24-megapixel RAW and a thumbnail give the same evidence;
3. each classical estimate is turned into a log-chroma
   ``(u, v) = (log g/r, log g/b)`` (a light change is a shift there, the
   diagonal model);
4. a small neural network (one hidden tanh layer; an ensemble of a few,
   trained from fixed seeds) maps those estimates, taken relative to the
   bright-pixel estimate, to the light's log-chroma: a learnt, nonlinear
   "corrected moments" (Finlayson 2013) over many moments;
5. the model is applied only within the evidence it was trained on: when
   the colour matrix sends more of the image out of the canonical gamut
   than it did for 99 % of the training images (a D65 matrix under tungsten
   light, :func:`canonical_analysis`), the reference estimate stands and
   the diagnostics say ``outside_training_range``;
6. the uncertainty is a Gaussian in log-chroma whose size grows with the
   disagreement of the classical estimates, with a calibration learnt on
   held-out benchmarks so that the reported 90 % region holds the true
   light about 90 % of the time.

Everything learnt ships in ``recovery/data/learned_illuminant.npz``, built
deterministically by ``python -m benchmarks.train_illuminant`` from the
development photographs (NUS 8-camera, Cube+ and INTEL-TAU field), with a
record of what it was trained on.

References
----------
Finlayson (2013), Corrected-moment illuminant estimation, ICCV.
Cheng, Prasad & Brown (2014), Illuminant estimation for color constancy:
why spatial-domain methods work and the role of the color distribution,
JOSA A 31(5) (bright pixels; the NUS 8-camera data).
Cheng, Price, Cohen & Brown (2015), Effective learning-based illuminant
estimation using simple features, CVPR.
Finlayson & Trezzi (2004) shades of gray; van de Weijer, Gevers & Gijsenij
(2007) gray edge; Qian et al. (2019) grey index (gray pixels).
Kim et al. (2025), CCMNet: cross-camera colour constancy with calibrated
colour correction matrices, ICCV.
Barron & Tsai (2017), Fast Fourier color constancy, CVPR (log-chroma).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np

from . import chroma_histogram as CH
from . import imfilters
from .camera import Camera
from .errors import InputError, InsufficientSurfaceVariation
from .estimators import gray_edge
from .resolution import area_resize

__all__ = ["LearnedModel", "LearnedResult", "FEATURE_NAMES", "load_model", "camera_color_matrix",
           "canonical_transform", "estimation_image", "features", "shared_maps", "window_maps", "window_features", "estimate_learned", "fit_robust_ridge",
           "model_inputs", "canonical_analysis", "locus_coordinates", "rgb_to_uv", "uv_to_rgb", "DEFAULT_MODEL_PATH", "CHI2_90"]

DEFAULT_MODEL_PATH = Path(__file__).with_name("data") / "learned_illuminant.npz"

#: chi-square quantile, 2 degrees of freedom, at 0.9: ``-2 log 0.1``
CHI2_90 = float(-2.0 * np.log(0.1))

#: XYZ -> canonical RGB: the Bradford cone fundamentals (Lam 1985), as in
#: colour-science's ``CHROMATIC_ADAPTATION_TRANSFORMS["Bradford"]``.
BRADFORD = np.array([[0.8951, 0.2664, -0.1614], [-0.7502, 1.7135, 0.0367], [0.0389, -0.0685, 1.0296]])

#: Cells of the analysis image (the development thumbnails are 64 x 64).
GRID = 64


# --------------------------------------------------------------------------- log-chroma
def rgb_to_uv(rgb) -> np.ndarray:
    """rgb (..., 3), positive -> log-chroma ``(log g/r, log g/b)``."""
    lg = np.log(np.asarray(rgb, float))
    return np.stack([lg[..., 1] - lg[..., 0], lg[..., 1] - lg[..., 2]], axis=-1)


def uv_to_rgb(uv) -> np.ndarray:
    """Log-chroma -> rgb with ``r + g + b = 1``."""
    uv = np.asarray(uv, float)
    rgb = np.stack([np.exp(-uv[..., 0]), np.ones(uv.shape[:-1]), np.exp(-uv[..., 1])], axis=-1)
    return rgb / rgb.sum(axis=-1, keepdims=True)


# --------------------------------------------------------------------------- the camera
def camera_color_matrix(camera: Camera) -> np.ndarray:
    """The camera's XYZ -> camera 3 x 3 matrix, scaled like a DNG
    ColorMatrix (D65 white maps to a largest channel of 1).

    The RAW's or LibRaw's (``camera.color_matrix``) when there is a usable
    one (finite, invertible, D65 giving a positive response); otherwise the least-squares fit ``R ~ cmfs @ M.T`` of the spectral
    sensitivities to the CIE 1931 colour-matching functions, weighted by
    D65 (the Luther approximation of a measured or uploaded camera).
    """
    if camera.channels != 3:
        raise InputError(f"the learnt estimator needs a 3-channel camera, got {camera.channels}")
    m = getattr(camera, "color_matrix", None)
    if m is not None:
        try:
            m = normalised_matrix(m)
            if abs(np.linalg.det(m)) > 1e-9:
                return m
        except InputError:
            pass          # an unusable matrix in the file: the sensitivities still describe the camera
    return normalised_matrix(_fitted_matrix(camera.wavelengths.tobytes(), camera.sensitivities.tobytes()))


def normalised_matrix(m) -> np.ndarray:
    """``m`` scaled so the D65 white (Y = 1) gives a largest channel of 1."""
    m = np.asarray(m, float)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise InputError("colour matrix must be a finite 3 x 3 array")
    top = float(np.max(m @ _D65_XYZ))
    if not top > 0:
        raise InputError("colour matrix maps D65 white to no positive camera response")
    return m / top


_D65_XYZ = np.array([0.95047, 1.0, 1.08883])


@lru_cache(maxsize=32)
def _fitted_matrix(wl_bytes: bytes, sens_bytes: bytes) -> np.ndarray:
    from models import illuminant, observer

    wl = np.frombuffer(wl_bytes)
    r = np.frombuffer(sens_bytes).reshape(wl.size, 3)
    cmfs = observer("CIE 1931 2 Degree Standard Observer", wl)
    d65 = illuminant("D65", wl)
    w = np.sqrt(d65 / d65.max())[:, None]
    mt, *_ = np.linalg.lstsq(cmfs * w, r * w, rcond=None)
    return mt.T


def canonical_transform(color_matrix, canonical) -> np.ndarray:
    """``K`` with ``canonical_rgb = K @ camera_rgb``: camera -> XYZ (the
    inverse colour matrix) -> canonical RGB."""
    m = normalised_matrix(color_matrix)
    if abs(np.linalg.det(m)) < 1e-9:
        raise InputError("colour matrix is singular")
    return np.asarray(canonical, float) @ np.linalg.inv(m)


# --------------------------------------------------------------------------- evidence
def estimation_image(image, mask=None, grid: int = GRID, min_valid: float = 0.5):
    """Area-average a linear image to ``grid x grid`` cells (the resolution
    the model learnt at, whatever the aspect ratio, as the development
    thumbnails were made), averaging only usable pixels; a cell with fewer
    than ``min_valid`` usable pixels is left out. Smaller images are kept as
    they are. Returns ``(cells (g, g, 3), usable (g, g))``."""
    img = np.asarray(image, np.float32)
    h, w = img.shape[:2]
    m = np.ones((h, w), bool) if mask is None else np.asarray(mask, bool)
    img = np.where(m[..., None] & np.isfinite(img), img, 0.0).astype(np.float32)
    if h <= grid and w <= grid:
        return img.astype(float), m.copy()
    gh, gw = min(grid, h), min(grid, w)
    s = area_resize(img, gw, gh)          # any number of channels (a multispectral camera too)
    frac = cv2.resize(m.astype(np.float32), (gw, gh), interpolation=cv2.INTER_AREA)
    ok = frac >= min_valid
    cells = np.where(ok[..., None], s / np.maximum(frac, 1e-12)[..., None], 0.0)
    return cells.astype(float), ok


def _edge(img: np.ndarray, ok: np.ndarray, p: float, sigma: float, order: int) -> np.ndarray:
    """Gray edge of the given order, NaN where the image has no edges."""
    try:
        return gray_edge(img, ok, p, sigma, order)
    except InsufficientSurfaceVariation:
        return np.full(3, np.nan)


def _gray_pixels(img: np.ndarray, m: np.ndarray, q: float) -> np.ndarray:
    """Mean of the pixels whose local log-contrast is most alike in the
    three channels (gray pixels; Yang et al. 2015, Qian et al. 2019)."""
    return _gray_pixels_many(img, m, (q,))[0]


def _contrast(img: np.ndarray) -> np.ndarray:
    """The gray pixels' local log-contrast of each channel."""
    lg = np.log(np.clip(img, 1e-4, None))
    return np.abs(imfilters.laplace(imfilters.gaussian_filter(lg, 0.5)))


def _gray_pixels_many(img: np.ndarray, m: np.ndarray, qs, contrast: np.ndarray | None = None) -> list[np.ndarray]:
    """:func:`_gray_pixels` for each fraction of ``qs``, the contrast map
    computed once (or given: a window's part of the whole image's)."""
    c = _contrast(img) if contrast is None else contrast
    mm = m & np.all(c > 1e-3, axis=-1)
    if mm.sum() < 10:
        return [img[m].mean(axis=0)] * len(qs)
    cc = c[mm]
    gi = np.std(cc / cc.sum(axis=1, keepdims=True), axis=1)
    sel = img[mm]
    out = []
    for q in qs:
        k = max(1, int(q * gi.size))
        out.append(sel[np.argpartition(gi, k - 1)[:k]].mean(axis=0))
    return out


def _percentile_sorted(srt: np.ndarray, q: float) -> np.ndarray:
    """``np.percentile(x, q, axis=0)`` (linear interpolation, numpy's own
    rounding) of ``srt``, the columns of ``x`` sorted."""
    v = q / 100.0 * (srt.shape[0] - 1)
    lo = int(np.floor(v))
    hi = min(lo + 1, srt.shape[0] - 1)
    t = v - lo
    a, b = srt[lo], srt[hi]
    d = b - a
    return b - d * (1.0 - t) if t >= 0.5 else a + d * t


#: The gray edges' (sigma, derivative order) pairs, and the erosions their masks need.
_EDGE_FILTERS = ((1, 1), (2, 1), (1, 2))


def _edge_magnitude(im: np.ndarray, sigma: float, order: int) -> np.ndarray:
    """Gaussian derivative magnitude of each channel of ``im``: the
    gradient's (order 1) or ``sqrt(gxx^2 + gyy^2 + 2 gxy^2)`` (order 2)."""
    if order == 1:
        gx = imfilters.gaussian_filter(im, sigma, (0, 1), "nearest")
        gy = imfilters.gaussian_filter(im, sigma, (1, 0), "nearest")
        mg = np.hypot(gx, gy)
    else:
        gxx = imfilters.gaussian_filter(im, sigma, (0, 2), "nearest")
        gyy = imfilters.gaussian_filter(im, sigma, (2, 0), "nearest")
        gxy = imfilters.gaussian_filter(im, sigma, (1, 1), "nearest")
        mg = np.sqrt(gxx ** 2 + gyy ** 2 + 2 * gxy ** 2)
    mg[mg < 1e-12] = 0.0
    return mg


def shared_maps(cells: np.ndarray, ok: np.ndarray) -> dict:
    """The filtered maps of a whole analysis image that :func:`features` of
    its windows share (:func:`window_maps` cuts a window's part): the gray
    edges' derivative magnitudes and eroded masks, and the gray pixels'
    contrast. A window then sees the image's edges at its borders rather
    than its own border's extension (the light map's windows,
    :func:`recovery.light_mixture.window_evidence`), and the filtering is
    done once instead of once per window."""
    img = np.clip(np.asarray(cells, float), 1e-6, None)
    scale = float(np.max(img)) or 1.0
    out = {"scale": scale, "contrast": _contrast(img)}
    for sigma, order in _EDGE_FILTERS:
        out[(sigma, order)] = _edge_magnitude(img / scale, sigma, order)
    for sigma in {sg for sg, _ in _EDGE_FILTERS}:
        e = max(1, int(np.ceil(2 * sigma)))
        out[("eroded", e)] = imfilters.binary_erosion(ok, e)
    return out


def window_maps(maps: dict, window) -> dict:
    """The part of :func:`shared_maps` under ``window`` (a pair of slices)."""
    return {k: (v[window] if isinstance(v, np.ndarray) else v) for k, v in maps.items()}


def _percentile_rows(n: int, q: float) -> tuple[int, int]:
    """The two rows of the sorted data :func:`_percentile_sorted` reads."""
    v = q / 100.0 * (n - 1)
    lo = int(np.floor(v))
    return lo, min(lo + 1, n - 1)


def _edges(img: np.ndarray, ok: np.ndarray, which=((1, 1, 1), (6, 1, 1), (6, 2, 1), (6, 1, 2)),
           shared: dict | None = None) -> dict:
    """:func:`recovery.estimators.gray_edge` for each ``(p, sigma, order)``
    of ``which`` (NaN where the image has no edges), the derivative
    magnitudes computed once per sigma and order and the three channels
    filtered together (van de Weijer, Gevers & Gijsenij 2007); with
    ``shared`` (:func:`window_maps`) the whole image's magnitudes and masks."""
    img = np.asarray(img, dtype=np.float64)
    scale = shared["scale"] if shared is not None else (float(np.max(img)) or 1.0)
    mags, masks, out = {}, {}, {}
    for p, sigma, order in which:
        if (sigma, order) not in mags:
            mg = shared[(sigma, order)] if shared is not None else _edge_magnitude(img / scale, sigma, order)
            e = max(1, int(np.ceil(2 * sigma)))
            if e not in masks:
                em = shared[("eroded", e)] if shared is not None else imfilters.binary_erosion(ok, e)
                masks[e] = em if em.any() else ok
            mags[(sigma, order)] = mg[masks[e]]
        px = mags[(sigma, order)]
        top = px.max() if px.size else 0.0
        if top > 0:
            r = px / top
            rp = r if p == 1 else (r * r) ** 3 if p == 6 else r ** p
            out[(p, sigma, order)] = scale * top * np.mean(rp, axis=0) ** (1.0 / p)
        else:
            out[(p, sigma, order)] = np.full(3, np.nan)
    return out


#: Below this RMS spread of the cells' log-chroma (about half a degree) the
#: scene is one surface colour, and no estimate can tell light from surface.
MIN_CHROMA_SPREAD = 0.01

#: The classical estimates the network combines, in order.
FEATURE_NAMES = ("gray-world", "sog-2", "sog-4", "sog-8", "sog-16", "max-rgb", "p99", "p95",
                 "gray-edge-1-p1", "gray-edge-1-p6", "gray-edge-1-p6-s2", "gray-edge-2-p6",
                 "bright-0.5%", "bright-1%", "bright-2%", "bright-5%", "bright-10%",
                 "gray-pixels-5%", "gray-pixels-20%")
#: The reference estimate the others are taken relative to.
REFERENCE = FEATURE_NAMES.index("bright-1%")


def features(cells: np.ndarray, ok: np.ndarray, shared: dict | None = None) -> np.ndarray:
    """(len(FEATURE_NAMES), 2) log-chroma of each classical estimate on the
    canonical-space analysis image ``cells`` with usable cells ``ok``; a
    window of a larger image may take that image's filtered maps
    (``shared``, :func:`window_maps` of :func:`shared_maps`) for its gray
    edges and gray pixels.

    Raises
    ------
    InsufficientSurfaceVariation
        Fewer than 16 usable cells.
    """
    img = np.clip(np.asarray(cells, float), 1e-6, None)
    px = img[ok]
    if px.shape[0] < 16:
        raise InsufficientSurfaceVariation(f"only {px.shape[0]} usable cells (of {ok.size}) after leaving out "
                                           "saturated, dark and out-of-gamut pixels")
    uv = rgb_to_uv(px)
    rms = float(np.sqrt(np.mean(np.sum((uv - uv.mean(axis=0)) ** 2, axis=1))))
    if rms < MIN_CHROMA_SPREAD:
        raise InsufficientSurfaceVariation(
            f"one colour: the usable cells' chromaticities spread by {rms:.2g} in log-chroma (under "
            f"{MIN_CHROMA_SPREAD}), so the light cannot be told from the surface")
    # The classical estimates of FEATURE_NAMES, with the work they share done
    # once (one scaling for the shades of gray, one filtering per gray-edge
    # sigma and order, one ordering of the brightness for the bright pixels,
    # one contrast map for the gray pixels): the same numbers as calling
    # recovery.estimators one by one, at a third of the cost (the 3 x 3
    # windows of recovery.light_mixture run this ten times per image).
    n = px.shape[0]
    top = px.max()
    r2 = (px / top) ** 2
    r4 = r2 * r2
    r8 = r4 * r4
    norms = np.stack([r2, r4, r8, r8 * r8]).mean(axis=1)              # Minkowski means, p = 2, 4, 8, 16
    sog = top * norms ** (1.0 / np.array([2.0, 4.0, 8.0, 16.0]))[:, None]
    srt = np.sort(px, axis=0)
    pct = [_percentile_sorted(srt, q) for q in (99.0, 95.0)]
    edges = _edges(img, ok, shared=shared)
    by_brightness = np.cumsum(px[np.argsort(px.sum(axis=1), kind="stable")[::-1]], axis=0)
    bright = [by_brightness[k - 1] / k for k in (max(1, int(q * n)) for q in (0.005, 0.01, 0.02, 0.05, 0.1))]
    est = [px.mean(axis=0), *sog, srt[-1], pct[0], pct[1],
           edges[(1, 1, 1)], edges[(6, 1, 1)], edges[(6, 2, 1)], edges[(6, 1, 2)],
           *bright, *_gray_pixels_many(img, ok, (0.05, 0.2), None if shared is None else shared["contrast"])]
    est = np.array(est)
    # an estimate that could not be made (no edges) stands in as the reference
    bad = ~np.all(np.isfinite(est) & (est > 0), axis=1)
    est[bad] = est[REFERENCE]
    return rgb_to_uv(est)


def window_features(cells: np.ndarray, ok: np.ndarray, windows) -> tuple[np.ndarray, np.ndarray]:
    """:func:`features` of each window of one analysis image, the windows
    reading the whole image's filtered maps (:func:`shared_maps`): the same
    estimates (to rounding) as ``features(cells[w], ok[w],
    window_maps(shared_maps(cells, ok), w))`` for each window ``w``, at a
    fraction of the cost. What adds up over cells (the counts, the means,
    the Minkowski sums of the shades of gray and gray edges, the
    chromaticity spread) is mapped once over the whole image and summed over
    each window in one call; only what orders cells (percentiles, bright
    pixels, gray pixels) is done window by window. The Minkowski sums are
    taken of the cells over the whole image's maximum, not the window's:
    the same norm, other rounding.

    Parameters
    ----------
    cells : (h, w, 3) canonical-space analysis cells
    ok : (h, w) usable cells
    windows : sequence of (row slice, column slice)

    Returns
    -------
    feats : (len(windows), len(FEATURE_NAMES), 2), NaN where not valid
    valid : (len(windows),) bool: the windows :func:`features` would not
        refuse (16 usable cells, a chromaticity spread of
        :data:`MIN_CHROMA_SPREAD`)
    """
    img = np.clip(np.asarray(cells, float), 1e-6, None)
    ok = np.asarray(ok, bool)
    scale = float(np.max(img)) or 1.0                 # the gray edges' scaling, as shared_maps
    top = float(img[ok].max()) if ok.any() else 1.0   # the shades of gray's
    okf = ok[..., None].astype(float)
    rel = img * (okf / top)                           # 0 where not usable
    r2 = rel * rel
    r4 = r2 * r2
    r8 = r4 * r4
    uv = rgb_to_uv(img) * okf
    mag = {so: _edge_magnitude(img / scale, *so) for so in _EDGE_FILTERS}
    e2 = imfilters.binary_erosion(ok, 2)[..., None].astype(float)       # sigma 1's mask
    e4 = imfilters.binary_erosion(ok, 4)[..., None].astype(float)       # sigma 2's
    m11 = mag[(1, 1)]
    m11_6, m21_6, m12_6 = (m11 * m11) ** 3, (mag[(2, 1)] ** 2) ** 3, (mag[(1, 2)] ** 2) ** 3
    edge = np.concatenate([m11, m11_6, m12_6, m21_6], axis=-1)
    parts = [okf, img * okf, r2, r4, r8, r8 * r8, uv, (uv * uv).sum(axis=-1, keepdims=True),
             e2, e2 * edge[..., :9], e4, e4 * edge[..., 9:], okf * edge]
    at, pos = {}, 0
    for name, width in (("n", 1), ("sum", 3), ("p2", 3), ("p4", 3), ("p8", 3), ("p16", 3), ("uv", 2), ("uv2", 1),
                        ("n2", 1), ("g11", 3), ("g11_6", 3), ("g12_6", 3), ("n4", 1), ("g21_6", 3), ("o11", 3),
                        ("o11_6", 3), ("o12_6", 3), ("o21_6", 3)):
        at[name] = slice(pos, pos + width)
        pos += width
    A = np.concatenate(parts, axis=-1)
    c = _contrast(img)
    mm = ok & np.all(c > 1e-3, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        gi = np.std(c / c.sum(axis=-1, keepdims=True), axis=-1)
    feats = np.full((len(windows), len(FEATURE_NAMES), 2), np.nan)
    valid = np.zeros(len(windows), bool)
    for k, w in enumerate(windows):
        S = A[w].sum(axis=(0, 1))
        n = S[at["n"]][0]
        if n < 16:
            continue
        muv = S[at["uv"]] / n
        if np.sqrt(max(S[at["uv2"]][0] / n - float(muv @ muv), 0.0)) < MIN_CHROMA_SPREAD:
            continue
        gw = S[at["sum"]] / n
        sog = [top * (S[at[f"p{p}"]] / n) ** (1.0 / p) for p in (2, 4, 8, 16)]
        n2, n4 = S[at["n2"]][0], S[at["n4"]][0]
        g11 = (S[at["g11"]] / n2) if n2 > 0 else S[at["o11"]] / n
        g11_6 = (S[at["g11_6"]] / n2 if n2 > 0 else S[at["o11_6"]] / n) ** (1.0 / 6)
        g12_6 = (S[at["g12_6"]] / n2 if n2 > 0 else S[at["o12_6"]] / n) ** (1.0 / 6)
        g21_6 = (S[at["g21_6"]] / n4 if n4 > 0 else S[at["o21_6"]] / n) ** (1.0 / 6)
        px = img[w][ok[w]]
        npx = px.shape[0]
        # only the top of each ordering is read: partition there, sort only that
        ks = [max(1, int(f * npx)) for f in (0.005, 0.01, 0.02, 0.05, 0.1)]
        br = px.sum(axis=1)
        top_k = np.argpartition(br, npx - ks[-1])[npx - ks[-1]:] if ks[-1] < npx else np.arange(npx)
        cum = np.cumsum(px[top_k[np.argsort(br[top_k], kind="stable")[::-1]]], axis=0)
        bright = [cum[q - 1] / q for q in ks]
        need = sorted({npx - 1, *_percentile_rows(npx, 99.0), *_percentile_rows(npx, 95.0)})
        srt = np.partition(px, need, axis=0)
        m = mm[w]
        if m.sum() < 10:
            gray = [gw, gw]
        else:
            g, sel = gi[w][m], img[w][m]
            gray = []
            for f in (0.05, 0.2):
                q = max(1, int(f * g.size))
                gray.append(sel[np.argpartition(g, q - 1)[:q]].mean(axis=0))
        est = np.array([gw, *sog, srt[-1], _percentile_sorted(srt, 99.0), _percentile_sorted(srt, 95.0),
                        scale * g11, scale * g11_6, scale * g21_6, scale * g12_6, *bright, *gray])
        bad = ~np.all(np.isfinite(est) & (est > 0), axis=1)
        est[bad] = est[REFERENCE]
        feats[k] = rgb_to_uv(est)
        valid[k] = True
    return feats, valid


def canonical_cells(image, mask, color_matrix, canonical):
    """The analysis image of :func:`estimation_image`, in the canonical
    space; cells that leave the canonical gamut (a channel <= 0) are left
    out."""
    can, ok, K, _ = canonical_analysis(image, mask, color_matrix, canonical)
    return can, ok, K


def canonical_analysis(image, mask, color_matrix, canonical):
    """:func:`canonical_cells` and the *out-of-gamut fraction*: the share of
    the usable cells that the colour matrix sends out of the canonical
    gamut (a canonical channel <= 1e-4 of the brightest).

    A real colour, seen under a real light, has positive cone responses, so
    a large fraction means the matrix does not describe the camera under
    this light: typically a D65 matrix (LibRaw's table keeps only Adobe's
    ColorMatrix2) applied under tungsten light, where the camera's blue is
    small and a few per cent of matrix error drive the canonical blue below
    zero. The learnt model is not applied beyond the fractions it was
    trained on (:attr:`LearnedModel.gamut_limit`).
    """
    cells, ok = estimation_image(image, mask)
    K = canonical_transform(color_matrix, canonical)
    can = cells @ K.T
    top = float(can[ok].max()) if ok.any() else 0.0
    n = int(ok.sum())
    ok_can = ok & np.all(can > 1e-4 * max(top, 1e-300), axis=-1)
    frac = float(1.0 - ok_can.sum() / n) if n else 0.0
    return can, ok_can, K, frac


#: Neighbouring cells closer than this in every channel's log (3 %, three
#: times the 1 % noise of a synthetic scene) belong to one uniform patch.
PATCH_TOLERANCE = 0.03


def uniform_patch_fraction(cells: np.ndarray, ok: np.ndarray, tol: float = PATCH_TOLERANCE) -> float:
    """Fraction of the usable analysis cells whose eight neighbours are all
    usable and within ``tol`` of it in every channel's log: how much of the
    scene is flat patches of one colour and shading (a chart, a Mondrian),
    where the linear models of surfaces and lights hold. On the 7,524
    development photographs at most 0.18 (99 % of them under 0.06); on
    synthetic Mondrians of 4-32 surfaces 0.13-0.5 (90 % above 0.19)."""
    c = np.asarray(cells, float)
    h, w = ok.shape
    if h < 3 or w < 3:
        return 0.0
    lg = np.log(np.clip(c, 1e-6, None))
    mid = lg[1:-1, 1:-1]
    flat = ok[1:-1, 1:-1].copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy or dx:
                nb = lg[1 + dy:h - 1 + dy, 1 + dx:w - 1 + dx]
                flat &= ok[1 + dy:h - 1 + dy, 1 + dx:w - 1 + dx] & np.all(np.abs(nb - mid) < tol, axis=-1)
    n = int(ok.sum())
    return float(flat.sum() / n) if n else 0.0


# --------------------------------------------------------------------------- the model
@dataclass(frozen=True)
class LearnedModel:
    """Learnt parameters (see :func:`fit_robust_ridge`).

    Attributes
    ----------
    canonical : (3, 3) XYZ -> canonical RGB
    mean, scale : (D,) standardisation of the inputs (:func:`model_inputs`)
    expansion : (3,) ``[H, seed, absolute]``: the size and seed of the fixed
        random tanh expansion (:func:`random_expansion`: drawn from a seeded
        generator, not learnt, so not stored), and whether the inputs
        include the reference's absolute place among the lights
        (:func:`model_inputs`)
    coef : (D + H + 1, 2) the learnt linear map from the expanded inputs to
        the light's log-chroma offset from the reference estimate
    locus_uv, locus_mired : (J, 2), (J,) the Planckian and CIE daylight
        locus in canonical log-chroma (``canonical @ xyz`` of each light:
        through the camera's own matrix, where a light of that colour sits
        in any camera's raw space), with the reciprocal colour temperature
    sigma : (3,) uncertainty law: ``s^2 = exp(sigma[0]) * (spread^2 + exp(sigma[1])) ** sigma[2]``
        the isotropic variance (log-chroma^2) of the light for an input
        spread (see :func:`_spread`); calibrated on held-out benchmarks
    confidence_coef : (2,) ``P(error < 3 deg) = 1 / (1 + exp(-(c0 + c1 log radius90_deg)))``,
        fitted by logistic regression on held-out benchmarks
    gamut_limit : (1,) the largest out-of-gamut fraction
        (:func:`canonical_analysis`) the model is applied at: the 99th
        percentile of its training images' (``inf``: no limit, a model
        saved before there was one). Beyond it the colour matrix does not
        describe the camera under this light, the evidence is outside what
        the model learnt from, and the reference estimate stands.
    outside_calibration : (3,) ``[variance, P(error < 3 deg), radius90_deg]``
        of the reference estimate where it stands (beyond :attr:`gamut_limit`),
        over the training images beyond the limit: the 90th percentile of
        its squared log-chroma error divided by :data:`CHI2_90` (so the
        Gaussian's 90 % region holds the light for 90 % of them), the
        fraction of them it got within 3 degrees (Laplace's rule,
        ``(k + 1) / (n + 2)``), and the 90th percentile of its angular
        error in camera RGB (the reported radius: under a D65 matrix in
        tungsten light the canonical blue is small, so a log-chroma region
        is far wider in angle than the errors are). The reference has no learnt parameters, so
        its errors on the training images are held-out errors. NaN (a model
        saved before there was one, or fewer than 10 such images): the
        model's own uncertainty law is used there too.
    hist_grid : (5,) the histogram stage's torus (:class:`recovery.chroma_histogram.Grid`),
        empty for a model without that stage
    hist_filters, hist_bias : (C, nu, nv), (nu, nv) its learnt filters and
        bias (:func:`recovery.chroma_histogram.scores`); the estimate is the
        first stage's fused with their likelihood (:func:`recovery.chroma_histogram.fuse`)
    hist_var_scale : (1,) the first stage's variance is multiplied by it in the fusion
    info : dict, what it was trained on and how
    """

    canonical: np.ndarray
    mean: np.ndarray
    scale: np.ndarray
    expansion: np.ndarray
    coef: np.ndarray
    locus_uv: np.ndarray
    locus_mired: np.ndarray
    sigma: np.ndarray
    confidence_coef: np.ndarray = field(default_factory=lambda: np.array([np.nan, np.nan]))
    gamut_limit: np.ndarray = field(default_factory=lambda: np.array([np.inf]))
    outside_calibration: np.ndarray = field(default_factory=lambda: np.array([np.nan, np.nan, np.nan]))
    hist_grid: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hist_filters: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 0)))
    hist_bias: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    hist_var_scale: np.ndarray = field(default_factory=lambda: np.array([1.0]))
    info: dict = field(default_factory=dict, compare=False)
    #: the confidence and flag fitted with the model (:class:`recovery.confidence.FlagModel`;
    #: not in the ``.npz``: the shipped one is ``recovery/data/learned_confidence.json``)
    flag: object = field(default=None, compare=False, repr=False)

    _ARRAYS = ("canonical", "mean", "scale", "expansion", "coef", "locus_uv", "locus_mired", "sigma",
               "confidence_coef", "gamut_limit", "outside_calibration", "hist_grid", "hist_filters", "hist_bias",
               "hist_var_scale")
    #: what a model saved before a field existed gets for it
    _DEFAULTS = {"gamut_limit": (np.inf,), "outside_calibration": (np.nan, np.nan, np.nan),
                 "hist_grid": np.zeros(0), "hist_filters": np.zeros((0, 0, 0)), "hist_bias": np.zeros((0, 0)),
                 "hist_var_scale": (1.0,)}

    @property
    def has_histogram(self) -> bool:
        """Whether the model has the histogram stage (:mod:`recovery.chroma_histogram`)."""
        return np.asarray(self.hist_grid).size == 5 and np.asarray(self.hist_filters).size > 0

    def fuse_histogram(self, cells, ok, uv, var) -> np.ndarray:
        """The first stage's estimate ``uv`` (2,) of variance ``var`` fused
        with the histogram likelihood of the canonical cells (the estimate
        unchanged for a model without that stage)."""
        if not self.has_histogram:
            return np.asarray(uv, float)
        grid = CH.Grid.from_array(self.hist_grid)
        h = CH.scores(CH.histograms(cells, ok, grid), self.hist_filters, self.hist_bias)
        return CH.fuse(h, uv, var * self.var_scale, grid)[0]

    @property
    def var_scale(self) -> float:
        """The factor on the first stage's variance in the fusion (chosen by
        inner leave-one-benchmark-out: the two stages read the same image,
        so their product may count its evidence twice)."""
        return float(np.asarray(self.hist_var_scale, float).ravel()[0])

    def save(self, path) -> None:
        np.savez_compressed(path, info=json.dumps(self.info, sort_keys=True),
                            **{k: np.asarray(getattr(self, k), np.float64) for k in self._ARRAYS})

    def inputs(self, feats: np.ndarray) -> np.ndarray:
        """(..., F, 2) classical estimates -> (..., D) model inputs."""
        return model_inputs(feats, self.locus_uv, self.locus_mired, bool(self.expansion[2]))

    def predict(self, x: np.ndarray, gamut_fraction=None) -> np.ndarray:
        """(N, D) inputs -> (N, 2) light log-chroma offsets from the
        reference estimate; zero (the reference stands) for an image whose
        out-of-gamut fraction (N,) exceeds :attr:`gamut_limit`."""
        pw, pb = random_expansion(len(self.mean), int(self.expansion[0]), int(self.expansion[1]))
        off = expand(np.atleast_2d(x), self.mean, self.scale, pw, pb) @ self.coef
        if gamut_fraction is not None:
            off = np.where(self.outside(gamut_fraction)[:, None], 0.0, off)
        return off

    def outside(self, gamut_fraction) -> np.ndarray:
        """(N,) bool: beyond the out-of-gamut fractions the model was trained on."""
        return np.atleast_1d(np.asarray(gamut_fraction, float)) > float(np.asarray(self.gamut_limit).ravel()[0])

    @property
    def calibrated_outside(self) -> bool:
        """Whether :attr:`outside_calibration` holds a calibration."""
        oc = np.asarray(self.outside_calibration, float).ravel()
        return oc.size == 3 and bool(np.all(np.isfinite(oc)))

    def uncertainty(self, spread, outside) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
        """(N,) log-chroma variances for evidence spreads (N,), and (N,)
        confidences and 90 % radii (degrees) where the reference stands
        (``outside``) and the model has a calibration for it (NaN elsewhere;
        None without one): the uncertainty law of
        :func:`variance_from_spread`, or :attr:`outside_calibration` beyond
        the gamut limit."""
        var = np.asarray(variance_from_spread(np.atleast_1d(spread), self.sigma), float)
        if not self.calibrated_outside:
            return var, None, None
        oc = np.asarray(self.outside_calibration, float).ravel()
        out = np.atleast_1d(np.asarray(outside, bool))
        return np.where(out, oc[0], var), np.where(out, oc[1], np.nan), np.where(out, oc[2], np.nan)


@lru_cache(maxsize=4)
def load_model(path: str | None = None) -> LearnedModel:
    """The shipped model (or one saved by :meth:`LearnedModel.save`)."""
    p = Path(path) if path else DEFAULT_MODEL_PATH
    if not p.exists():
        raise InputError(f"no learnt illuminant model at {p} (rebuild it: python -m benchmarks.train_illuminant)")
    with np.load(p, allow_pickle=False) as z:
        if "coef" not in z.files:
            raise InputError(f"{p} is a model of an older format (rebuild it: python -m benchmarks.train_illuminant)")
        defaults = LearnedModel._DEFAULTS
        return LearnedModel(*(z[k] if k in z.files else np.array(defaults[k]) for k in LearnedModel._ARRAYS),
                            info=json.loads(str(z["info"])))


def locus_coordinates(uv: np.ndarray, locus_uv: np.ndarray, locus_mired: np.ndarray) -> np.ndarray:
    """(..., 2) canonical log-chroma -> (..., 2): the reciprocal colour
    temperature of the nearest locus point (in units of 100 mired) and the
    signed distance off the locus (log-chroma): where a chromaticity sits
    among the physical lights, the same for every camera through its
    matrix."""
    uv = np.asarray(uv, float)
    flat = uv.reshape(-1, 2)
    d2 = ((flat[:, None, :] - locus_uv[None]) ** 2).sum(-1)
    j = d2.argmin(axis=1)
    tang = np.gradient(locus_uv, axis=0)[j]
    tang = tang / np.linalg.norm(tang, axis=1, keepdims=True)
    off = flat - locus_uv[j]
    perp = off[:, 0] * tang[:, 1] - off[:, 1] * tang[:, 0]
    return np.stack([locus_mired[j] / 100.0, perp], axis=-1).reshape(uv.shape)


def model_inputs(feats: np.ndarray, locus_uv: np.ndarray, locus_mired: np.ndarray,
                 absolute: bool = False) -> np.ndarray:
    """(..., F, 2) estimates -> (..., 2 (F - 1)) inputs: each estimate
    relative to the reference (bright pixels): what a light change leaves
    unchanged, the scene's evidence, so the model's answer moves with the
    light whatever the benchmark's mix of lights. With ``absolute`` also the
    reference itself and its place among the physical lights
    (:func:`locus_coordinates`), a learnt prior on lights: measured on
    leave-one-benchmark-out it gains 0.08 degrees of mean error but makes
    the estimate 8 times as sensitive to an error of the colour matrix
    (median 0.8 against 0.1 degrees for a 3 % error), so the shipped model
    leaves it out."""
    f = np.asarray(feats, float)
    ref = f[..., REFERENCE, :]
    rel = np.delete(f - ref[..., None, :], REFERENCE, axis=-2).reshape(*f.shape[:-2], -1)
    if not absolute:
        return rel
    return np.concatenate([rel, ref, locus_coordinates(ref, locus_uv, locus_mired)], axis=-1)


def expand(x: np.ndarray, mean: np.ndarray, scale: np.ndarray, proj_w: np.ndarray, proj_b: np.ndarray) -> np.ndarray:
    """Standardised inputs, their fixed random tanh features and a constant."""
    z = (np.asarray(x, float) - mean) / scale
    return np.concatenate([z, np.tanh(z @ proj_w + proj_b), np.ones((z.shape[0], 1))], axis=1)


def _spread(feats: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Disagreement of the evidence: RMS distance of the classical
    estimates from the estimate (log-chroma)."""
    f = np.asarray(feats, float)
    return np.sqrt(np.mean(np.sum((f - np.asarray(uv)[..., None, :]) ** 2, axis=-1), axis=-1))


def variance_from_spread(spread, sigma) -> np.ndarray:
    """Isotropic log-chroma variance of the light for an evidence spread."""
    return np.exp(sigma[0]) * (np.asarray(spread, float) ** 2 + np.exp(sigma[1])) ** sigma[2]


@dataclass
class LearnedResult:
    """Outcome of :func:`estimate_learned`: ``rgb`` the light in *camera*
    RGB (sum 1); ``uv`` its canonical log-chroma and ``cov`` the calibrated
    covariance; ``radius90_deg`` the angular radius of the reported 90 %
    region in camera RGB; ``confidence`` the probability of an error below
    3 degrees: from the shipped confidence law (:mod:`recovery.confidence`,
    ``diagnostics["flag_inputs"]`` its evidence, ``["flag_threshold"]`` the
    flag's threshold) or, without one, from the 90 % radius
    (``diagnostics["radius_confidence"]`` keeps that one either way)."""

    rgb: np.ndarray
    uv: np.ndarray
    cov: np.ndarray
    radius90_deg: float
    confidence: float
    n_cells: int
    diagnostics: dict = field(default_factory=dict)


def input_distance(model: LearnedModel, feats: np.ndarray) -> np.ndarray:
    """(N,) mean squared standardised model input (the model's own
    standardisation of its training photographs): how far outside its
    training an image's evidence lies."""
    z = (model.inputs(np.asarray(feats, float).reshape(-1, len(FEATURE_NAMES), 2)) - model.mean) / model.scale
    return np.mean(z ** 2, axis=1)


def estimate_learned(image, mask, color_matrix, model: LearnedModel | None = None, flag=None) -> LearnedResult:
    """Estimate the light of a linear camera image with the learnt model.

    Parameters
    ----------
    image : (H, W, 3) linear camera RGB (any scale, black level removed)
    mask : (H, W) bool usable pixels (not saturated, not dark), or None
    color_matrix : (3, 3) XYZ -> camera (:func:`camera_color_matrix`)
    model : default the shipped one
    flag : :class:`recovery.confidence.FlagModel`, default the shipped one;
        the confidence is its calibrated P(error < 3 deg) (without one: the
        model's own law of the 90 % radius) and ``low_confidence`` its flag

    Raises
    ------
    InsufficientSurfaceVariation
        Too few usable cells.
    """
    model = model or load_model()
    img = np.asarray(image, float)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise InputError(f"the learnt estimator needs an (H, W, 3) image, got {img.shape}")
    can, ok, K, gamut = canonical_analysis(img, mask, color_matrix, model.canonical)
    f = features(can, ok)
    outside = bool(model.outside(gamut)[0])
    uv = model.predict(model.inputs(f), np.array([gamut]))[0] + f[REFERENCE]
    spread = float(_spread(f, uv))
    var, conf_outside, radius_outside = model.uncertainty(spread, outside)
    var = float(var[0])
    cov = np.eye(2) * var
    first = uv
    if not outside:              # the histogram stage (the first stage's spread law still gives the variance)
        uv = model.fuse_histogram(can, ok, uv, var)
    cam = np.linalg.solve(K, uv_to_rgb(uv))
    if not np.all(cam > 0):
        cam = np.clip(cam, 1e-6, None)
    cam = cam / cam.sum()
    if conf_outside is not None and outside:      # the reference's own record beyond the limit
        radius, conf = float(radius_outside[0]), float(conf_outside[0])
    else:
        radius = radius90(uv, var, K)
        conf = confidence(radius, model.confidence_coef)
    patches = uniform_patch_fraction(can @ np.linalg.inv(K).T, ok)
    from .confidence import confidence_inputs, load_flag_model, region_estimates

    flag = (model.flag or load_flag_model()) if flag is None else flag
    flag_info = {"radius_confidence": conf}
    if flag is not None:
        cells = int(np.prod(ok.shape))
        x = confidence_inputs(f[None], first[None], region_estimates(can, ok)[None], input_distance(model, f),
                              [gamut], [ok.sum() / max(cells, 1)], [patches], REFERENCE, model.locus_uv,
                              model.locus_mired)
        conf = float(flag.confidence(x)[0])
        flag_info.update({"flag_threshold": flag.threshold,
                          "flag_inputs": {n: float(v) for n, v in zip(flag.names, x[0])}})
    return LearnedResult(cam, uv, cov, float(radius), conf, int(ok.sum()),
                         {**flag_info, "evidence_spread": spread, "uniform_patch_fraction": patches,
                          "out_of_gamut_fraction": gamut, "outside_training_range": outside,
                          "histogram_shift_deg": (_angle(cam, np.linalg.solve(K, uv_to_rgb(first)))
                                                  if model.has_histogram and not outside else None),
                          "estimates": {n: [float(a), float(b)] for n, (a, b) in zip(FEATURE_NAMES, f)}})


def radius90(uv, var: float, K: np.ndarray) -> float:
    """Angular radius (degrees, camera RGB) of the 90 % region of an
    isotropic log-chroma Gaussian of variance ``var`` about ``uv``: the
    largest angle to its edge along the two log-chroma axes, through the
    canonical transform ``K``."""
    cam = np.linalg.solve(K, uv_to_rgb(uv))
    r = np.sqrt(var * CHI2_90)
    return max(_angle(cam, np.linalg.solve(K, uv_to_rgb(np.asarray(uv) + d)))
               for d in ([r, 0], [0, r], [-r, 0], [0, -r]))


def confidence(radius: float, coef) -> float:
    """P(error < 3 degrees) for a 90 % radius: the calibrated logistic law
    of the model, or (a model without one) the Gaussian's own probability."""
    coef = np.asarray(coef, float)
    if np.all(np.isfinite(coef)):
        return float(1.0 / (1.0 + np.exp(-(coef[0] + coef[1] * np.log(max(radius, 1e-6))))))
    sigma_deg = radius / np.sqrt(CHI2_90)
    return float(1.0 - np.exp(-9.0 / (2.0 * sigma_deg ** 2))) if sigma_deg > 0 else 1.0


def fit_confidence(radius: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Logistic regression of ``ok`` (error under 3 degrees) on ``log
    radius`` (maximum likelihood, Newton's method from zero: deterministic)."""
    x = np.c_[np.ones(len(radius)), np.log(np.maximum(np.asarray(radius, float), 1e-6))]
    y = np.asarray(ok, float)
    c = np.zeros(2)
    for _ in range(50):
        p = 1.0 / (1.0 + np.exp(-(x @ c)))
        g = x.T @ (y - p)
        h = (x * (p * (1 - p))[:, None]).T @ x + 1e-9 * np.eye(2)
        step = np.linalg.solve(h, g)
        c = c + step
        if np.abs(step).max() < 1e-10:
            break
    return c


def _angle(a, b) -> float:
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    return float(np.degrees(2 * np.arctan2(np.linalg.norm(a - b), np.linalg.norm(a + b))))


# --------------------------------------------------------------------------- learning
@lru_cache(maxsize=8)
def random_expansion(d: int, hidden: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The fixed random tanh features (weights N(0, 1/d), offsets U(-1, 1))
    from a seeded generator: the same on every machine (numpy's PCG64 and
    its normal sampler are specified bit for bit)."""
    rng = np.random.default_rng(seed)
    w, b = rng.normal(0.0, 1.0 / np.sqrt(d), (d, hidden)), rng.uniform(-1.0, 1.0, hidden)
    w.flags.writeable = False
    b.flags.writeable = False
    return w, b


def fit_robust_ridge(x: np.ndarray, y: np.ndarray, weights: np.ndarray | None = None, *, hidden: int = 300,
                     ridge: float = 0.1, delta: float = 0.02, seed: int = 0, tol: float = 1e-9,
                     maxiter: int = 500):
    """Fit the light's log-chroma offset as a linear function of the inputs
    and their fixed random tanh features, minimising the weighted mean of
    ``sqrt(|r|^2 + delta^2)`` (a smooth Euclidean error in log-chroma, robust
    to the few images whose label is far off) plus ``ridge |B|^2``.

    The problem is convex in ``B`` (the features are fixed), so its minimum
    is unique, and iteratively reweighted least squares (each step a
    closed-form solve, a majorise-minimise step, so the objective never
    rises) converges to it whatever the order of the sums: iterated until
    the relative decrease of the objective is under ``tol``, far above
    rounding noise and far below anything an estimate would show. The
    random features are drawn from a seeded generator (:func:`random_expansion`).

    Returns
    -------
    mean, scale, coef, info (iterations, final objective)
    """
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    n, d = x.shape
    w = np.ones(n) if weights is None else np.asarray(weights, np.float64)
    w = w / w.sum()
    mean = x.mean(axis=0)
    scale = x.std(axis=0) + 1e-9
    proj_w, proj_b = random_expansion(d, int(hidden), seed)
    Z = expand(x, mean, scale, proj_w, proj_b)
    P = float(ridge) * np.diag(np.r_[np.ones(Z.shape[1] - 1), 0.0])     # the constant is not penalised

    def objective(B):
        r = np.sqrt(((Z @ B - y) ** 2).sum(axis=1) + delta ** 2)
        return float((w * r).sum() + ridge * (B[:-1] ** 2).sum()), r

    u = w / delta
    prev = np.inf
    for it in range(1, maxiter + 1):
        Zs = Z * np.sqrt(u)[:, None]        # Z^T diag(u) Z as Zs^T Zs: numpy's symmetric product, half the work
        B = np.linalg.solve(Zs.T @ Zs + 2.0 * P, Z.T @ (u[:, None] * y))
        obj, r = objective(B)
        if prev - obj <= tol * abs(obj):
            break
        prev = obj
        u = w / r
    return mean, scale, B, {"iterations": it, "objective": obj}


def fit_uncertainty(spread: np.ndarray, err2: np.ndarray, coverage: float = 0.9) -> np.ndarray:
    """Calibrate :func:`variance_from_spread` on held-out residuals: fit
    ``log err^2 ~ a + c log(spread^2 + b)`` by least squares over a grid of
    ``b``, then scale so that ``err^2 / s^2 <= CHI2_90`` for a ``coverage``
    fraction of the images (the Gaussian's 90 % region holds the truth for
    90 % of held-out images)."""
    spread = np.asarray(spread, float)
    err2 = np.maximum(np.asarray(err2, float), 1e-12)
    best = None
    for logb in np.linspace(-12, -4, 17):
        xx = np.log(spread ** 2 + np.exp(logb))
        A = np.c_[np.ones_like(xx), xx]
        coef, *_ = np.linalg.lstsq(A, np.log(err2), rcond=None)
        r = np.log(err2) - A @ coef
        if best is None or (r ** 2).sum() < best[0]:
            best = ((r ** 2).sum(), logb, coef)
    _, logb, (a, c) = best
    c = float(np.clip(c, 0.0, 2.0))
    sig = np.array([a, logb, c])
    ratio = err2 / variance_from_spread(spread, sig)
    sig[0] += np.log(np.quantile(ratio, coverage) / CHI2_90)
    return sig
