"""Bayesian illuminant estimation over physically plausible lights (prototype)."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy import ndimage

import models

from .camera import Camera
from .illuminant_prior import CandidateLights, default_candidates

__all__ = ["estimate_bayes", "chromaticity_model", "helmert"]


def helmert(c: int) -> np.ndarray:
    """Orthonormal basis of the sum-zero subspace of R^C, ``(C-1, C)``."""
    h = np.zeros((c - 1, c))
    for i in range(1, c):
        h[i - 1, :i] = 1.0
        h[i - 1, i] = -i
        h[i - 1] /= np.sqrt(i * (i + 1))
    return h


def _digest(*arrays) -> str:
    h = hashlib.sha1()
    for a in arrays:
        if isinstance(a, str):
            h.update(a.encode())
        else:
            a = np.ascontiguousarray(np.asarray(a, dtype=np.float64))
            h.update(str(a.shape).encode())
            h.update(a.tobytes())
    return h.hexdigest()


@dataclass
class ChromaticityModel:
    """Per camera + candidate set + surface set statistics."""

    H: np.ndarray                 # (d, C)
    A: np.ndarray                 # (d, d) whitening of the kernel
    light_rgb: np.ndarray         # (M, C)
    light_chroma: np.ndarray      # (M, C) rgb / sum
    light_z: np.ndarray           # (M, d)
    z_train: np.ndarray           # (M, n, d)
    w_train: np.ndarray           # (n,)
    grid_lo: np.ndarray | None
    grid_step: float
    log_table: np.ndarray | None  # (M, G1, G2) log density (d == 2)
    log_floor: float
    gw_mean: np.ndarray           # (M, d) expected mean z of surfaces minus light z
    gw_cov: np.ndarray            # (d, d) covariance of one surface's z about the mean
    build_ms: float


_MODELS: dict = {}


def _reflectance_array(reflectances, wl):
    if reflectances is None:
        reflectances = "all"
    if isinstance(reflectances, str):
        return models.reflectance_set(reflectances, wl)
    if isinstance(reflectances, (list, tuple)) and all(isinstance(s, str) for s in reflectances):
        return np.concatenate([models.reflectance_set(s, wl) for s in reflectances])
    r = np.atleast_2d(np.asarray(reflectances, float))
    if r.shape[1] != wl.size:
        raise ValueError(f"reflectances must be (n, {wl.size})")
    return r


def chromaticity_model(camera: Camera, candidates: CandidateLights, reflectances=None, *, bandwidth: float = 0.35,
                       noise: float = 0.02, n_mix: int = 600, mix_weight: float = 0.3, grid_step: float = 0.2,
                       outlier: float = 0.02, seed: int = 0) -> ChromaticityModel:
    wl = camera.wavelengths
    refl = np.clip(_reflectance_array(reflectances, wl), 1e-4, None)
    key = _digest(camera.sensitivities, wl, candidates.spectra, refl, np.array([bandwidth, noise, n_mix, mix_weight,
                                                                                 grid_step, outlier, seed]))
    if key in _MODELS:
        return _MODELS[key]
    t0 = time.perf_counter()
    C = camera.channels
    d = C - 1
    H = helmert(C)
    R = camera.sensitivities * camera.dlambda[:, None]
    E = candidates.spectra
    light_rgb = E @ R
    light_rgb = np.maximum(light_rgb, 1e-12 * light_rgb.max())
    n0 = refl.shape[0]
    rng = np.random.default_rng(seed)
    if n_mix > 0:
        ia = rng.integers(n0, size=n_mix)
        ib = rng.integers(n0, size=n_mix)
        al = rng.uniform(0, 1, size=(n_mix, 1))
        mix = al * refl[ia] + (1 - al) * refl[ib]
        train = np.concatenate([refl, mix])
        w = np.concatenate([np.full(n0, (1 - mix_weight) / n0), np.full(n_mix, mix_weight / n_mix)])
    else:
        train = refl
        w = np.full(n0, 1.0 / n0)
    rgb = np.einsum("mn,sn,nc->msc", E, train, R, optimize=True)
    rgb = np.maximum(rgb, 1e-9 * rgb.max())
    u = np.log(rgb) @ H.T                                               # (M, n, d)
    ul = np.log(light_rgb) @ H.T                                        # (M, d)
    mu = np.einsum("n,mnd->md", w, u)
    dev = u - mu[:, None, :]
    cov = np.einsum("n,mnd,mne->de", w, dev, dev) / E.shape[0]
    kc = bandwidth ** 2 * cov + noise ** 2 * np.eye(d)
    ev, evec = np.linalg.eigh(kc)
    A = (evec / np.sqrt(ev)) @ evec.T
    z = u @ A.T
    zl = ul @ A.T
    gw_mean = (mu - ul) @ A.T
    gw_cov = A @ cov @ A.T
    log_table = None
    lo = None
    log_floor = 0.0
    if d == 2:
        lo = z.reshape(-1, 2).min(0) - 5.0
        hi = z.reshape(-1, 2).max(0) + 5.0
        shape = np.ceil((hi - lo) / grid_step).astype(int) + 2
        M = E.shape[0]
        f = (z - lo) / grid_step
        i0 = np.floor(f).astype(int)
        fr = f - i0
        tab = np.zeros((M, shape[0] * shape[1]))
        base = np.arange(M)[:, None] * (shape[0] * shape[1])
        for dx in (0, 1):
            for dy in (0, 1):
                wx = fr[..., 0] if dx else 1 - fr[..., 0]
                wy = fr[..., 1] if dy else 1 - fr[..., 1]
                idx = base + (i0[..., 0] + dx) * shape[1] + (i0[..., 1] + dy)
                tab.ravel()[:] += np.bincount(idx.ravel(), (wx * wy * w[None, :]).ravel(), minlength=tab.size)
        tab = tab.reshape(M, shape[0], shape[1])
        tab = ndimage.gaussian_filter(tab, (0, 1.0 / grid_step, 1.0 / grid_step), mode="constant", truncate=5.0)
        tab /= tab.sum(axis=(1, 2), keepdims=True)
        dens = tab / grid_step ** 2
        area = shape[0] * shape[1] * grid_step ** 2
        log_floor = float(np.log(outlier / area))
        log_table = np.log((1 - outlier) * dens + outlier / area).astype(np.float32)
    model = ChromaticityModel(H, A, light_rgb, light_rgb / light_rgb.sum(1, keepdims=True), zl, z, w, lo, grid_step,
                              log_table, log_floor, gw_mean, gw_cov, (time.perf_counter() - t0) * 1000)
    _MODELS[key] = model
    return model


def _summarise(px: np.ndarray, model: ChromaticityModel, cell: float, min_count_frac: float):
    """Distinct chromaticities of the pixels: cells of side ``cell`` (kernel
    units) in whitened log-chromaticity; mean z and weight per cell."""
    u = np.log(px) @ model.H.T
    z = u @ model.A.T
    q = np.floor(z / cell).astype(np.int64)
    qmin = q.min(0)
    q -= qmin
    dims = q.max(0) + 1
    if np.prod(dims.astype(float)) < 5e6:
        key = np.ravel_multi_index(q.T, dims)
        cnt = np.bincount(key)
        nz = np.flatnonzero(cnt)
        inv = np.searchsorted(nz, key)
        cnt = cnt[nz]
    else:
        _, inv, cnt = np.unique(q, axis=0, return_inverse=True, return_counts=True)
        inv = inv.ravel()
    B = cnt.size
    zs = np.stack([np.bincount(inv, z[:, k], minlength=B) for k in range(z.shape[1])], 1) / cnt[:, None]
    c0 = max(2.0, min_count_frac * px.shape[0])
    wgt = np.minimum(1.0, cnt / c0)
    return zs, wgt, cnt


def _loglik(model: ChromaticityModel, zs: np.ndarray) -> np.ndarray:
    """(M, B) log density of each cell mean under each candidate."""
    if model.log_table is not None:
        tab = model.log_table
        f = (zs - model.grid_lo) / model.grid_step
        G = np.array(tab.shape[1:])
        f = np.clip(f, 0, G - 1.001)
        i0 = np.floor(f).astype(int)
        fr = f - i0
        out = 0.0
        for dx in (0, 1):
            for dy in (0, 1):
                wgt = (fr[:, 0] if dx else 1 - fr[:, 0]) * (fr[:, 1] if dy else 1 - fr[:, 1])
                out = out + tab[:, i0[:, 0] + dx, i0[:, 1] + dy] * wgt[None, :]
        return out
    d = zs.shape[1]
    zt = model.z_train
    d2 = (np.sum(zt ** 2, -1)[:, :, None] + np.sum(zs ** 2, -1)[None, None, :]
          - 2 * np.einsum("mnd,bd->mnb", zt, zs, optimize=True))
    dens = np.einsum("n,mnb->mb", model.w_train, np.exp(-0.5 * np.maximum(d2, 0))) / (2 * np.pi) ** (d / 2)
    return np.log(0.98 * dens + 1e-6)


def estimate_bayes(image_or_pixels, mask=None, camera: Camera | None = None, *, candidates: CandidateLights | None = None,
                   reflectances=None, white_level=None, dark_fraction: float = 0.02, cell: float = 0.5,
                   min_count_frac: float = 0.002, temperature: float = 1.0, gray_world_weight: float = 0.0,
                   model_kw: dict | None = None):
    t0 = time.perf_counter()
    x = np.asarray(image_or_pixels, dtype=np.float64)
    C = camera.channels
    px = x.reshape(-1, C)
    ok = np.all(np.isfinite(px), axis=1)
    if mask is not None:
        ok &= np.asarray(mask, bool).reshape(-1)
    px = px[ok]
    scale = px.max()
    px = px / scale
    keep = np.all(px > dark_fraction, axis=1)
    if white_level is not None:
        keep &= np.all(px * scale < 0.98 * white_level, axis=1)
    px = px[keep]
    cands = candidates or default_candidates(camera.wavelengths)
    model = chromaticity_model(camera, cands, reflectances, **(model_kw or {}))
    zs, wgt, cnt = _summarise(px, model, cell, min_count_frac)
    ll = _loglik(model, zs)                      # (M, B)
    L = ll @ wgt
    logpost = np.log(cands.prior) + temperature * L
    if gray_world_weight > 0:
        zbar = (wgt @ zs) / wgt.sum()
        neff = wgt.sum()
        r = zbar[None, :] - model.light_z - model.gw_mean
        S = model.gw_cov / max(neff, 1.0) + np.eye(zs.shape[1]) * 1e-3
        Si = np.linalg.inv(S)
        logpost = logpost - gray_world_weight * 0.5 * np.einsum("md,de,me->m", r, Si, r)
    logpost -= logpost.max()
    post = np.exp(logpost)
    post /= post.sum()
    chroma = post @ model.light_chroma
    return chroma, post, {"ms": (time.perf_counter() - t0) * 1000, "n_cells": int(zs.shape[0]),
                          "n_eff": float(wgt.sum()), "best": cands.names[int(np.argmax(post))]}
