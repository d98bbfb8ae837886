"""Two lights in one photograph, on relit real photographs: the light map
and the one-or-several decision of :mod:`recovery.light_mixture`, beside
one light by each estimator, scored per pixel.

There are no real two-light photographs in the development data, so they
are made physically from the real ones (issue 27): each development
photograph (64 x 64 linear camera RGB, ``../shared/data/real``) is divided
by its measured light (the von Kries reflectance in the camera's own
space), then lit by two real lights, two measured lights of the same
camera's other photographs, mixed by a smooth mask ``a(x)``:

    light(x) = a(x) k L1 + (1 - a(x)) L2

with an intensity ratio ``k`` in [0.5, 2]. Masks: a linear gradient, a
soft-edged half (a sigmoid across a random line), shadow-shaped blobs, and a
second light reaching only part of the frame (a corner or a band). Pairs:
close (two daylights, 1.5-4 degrees apart), medium (4-10) and far (above 10:
daylight and tungsten), in equal numbers. The original photographs, lit by
one light, are scored beside them in every run, so the decision is scored
on both kinds.

Protocol: leave one benchmark out (the learnt model fitted on the other two,
as ``python -m benchmarks.real_photos`` does); the map's settings (the
decision's threshold, the gain on the windows' variation, the projection on
two lights) are chosen by inner leave-one-benchmark-out on the two training
benchmarks (a model fitted on one, its relit photographs scored on the
other), never on the left-out benchmark.

Per left-out benchmark and pooled, over the two-light photographs and the
single-light ones separately: the mean per-pixel angle per image (the light
at every non-masked pixel against the true mixed light), its mean / median
/ worst 25 % over images, for: one light by the learnt estimator (today's
default), one light by shades of gray, the best single light (the truth's
average over the pixels: an oracle), the windows' map always on, the
map with the decision (the product), and the best decision (each scene's
map or one light, whichever is better there: an oracle of the decision
alone, the bound any rule on the image has with these maps). And the
decision's confusion table,
and where the map's error comes from (:func:`decompose`: its level and its
variation, each replaced by the truth in turn), and whether the confidence
flags the answers that went wrong on these scenes (each fold's own
confidence law, :func:`fold_flag`).

Usage::

    python -m benchmarks.mixed_light            # 7-10 minutes on 2 cores (models cached in out/)
    python -m benchmarks.mixed_light --per 150  # fewer photographs per benchmark
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from recovery import learned as L
from recovery import light_mixture as LM
from recovery.confidence import FlagModel, auroc
from recovery.estimators import shades_of_gray
from recovery.regions import bilinear

from .realdata import REAL_DIR, error_stats, load_real, usable_mask
from .train_illuminant import build, dataset_features, dataset_regions, fit_model, locus, usable

MASKS = ("gradient", "soft-half", "blobs", "partial")
PAIRS = {"close": (1.5, 4.0), "medium": (4.0, 10.0), "far": (10.0, 40.0)}
#: the settings searched by the inner cross-validation
THRESHOLDS = (2.0, 4.0, 6.0, 8.0, 12.0, 16.0, 24.0, 32.0, 48.0, 64.0, float("inf"))
GAINS = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5)
PROJECT = (True, False)
#: weight of the windows' precision-weighted mean in the map's level (0: the whole image's estimate)
LEVELS = (0.0, 0.5, 0.75, 1.0)
#: the gain's rise with the evidence, ``max(gain, 1 - shrink / T)`` (0: the fixed gain;
#: :meth:`recovery.light_mixture.MixtureSettings.gain_at`)
SHRINKS = (0.0, 8.0, 16.0, 24.0, 32.0)


def angle_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (degrees) between the rows of ``a`` and ``b``."""
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = b / np.linalg.norm(b, axis=-1, keepdims=True)
    return np.degrees(2 * np.arctan2(np.linalg.norm(a - b, axis=-1), np.linalg.norm(a + b, axis=-1)))


# --------------------------------------------------------------------------- scenes
def mask_field(kind: str, shape, rng) -> np.ndarray:
    """(h, w) a(x) in [0, 1], smooth, of the given kind."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w].astype(float)
    yy, xx = yy / (h - 1), xx / (w - 1)
    th = rng.uniform(0, 2 * np.pi)
    proj = (xx - 0.5) * np.cos(th) + (yy - 0.5) * np.sin(th)
    if kind == "gradient":
        a = (proj - proj.min()) / (proj.max() - proj.min())
    elif kind == "soft-half":
        width = rng.uniform(0.02, 0.15)
        a = 1.0 / (1.0 + np.exp(-(proj - rng.uniform(-0.2, 0.2)) / width))
    elif kind == "blobs":
        a = np.zeros((h, w))
        for _ in range(rng.integers(1, 4)):
            cy, cx = rng.uniform(0.15, 0.85, 2)
            s = rng.uniform(0.1, 0.3)
            a = np.maximum(a, np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * s ** 2)))
        a = np.clip(a * 1.3, 0, 1)
    elif kind == "partial":      # the second light reaches only a corner or a band
        width = rng.uniform(0.03, 0.12)
        a = 1.0 / (1.0 + np.exp(-(proj - rng.uniform(0.15, 0.4)) / width))
    else:
        raise ValueError(kind)
    return a


def pick_pair(lights: np.ndarray, kind: str, rng) -> tuple[np.ndarray, np.ndarray]:
    """Two of a camera's measured lights whose angle falls in the pair's range."""
    lo, hi = PAIRS[kind]
    for _ in range(200):
        i, j = rng.integers(0, len(lights), 2)
        a = float(angle_rows(lights[i][None], lights[j][None])[0])
        if lo <= a < hi:
            return lights[i], lights[j]
    # the camera's lights do not span the range: the most distant pair found
    d = angle_rows(lights[:, None, :], lights[None, :, :])
    i, j = np.unravel_index(np.argmax(d), d.shape)
    return lights[i], lights[j]


def relight(image: np.ndarray, truth: np.ndarray, L1: np.ndarray, L2: np.ndarray, a: np.ndarray, k: float):
    """The photograph lit by ``a k L1 + (1 - a) L2``: (image, per-pixel light
    (h, w, 3) sum 1). Pixels saturated or masked in the original stay so."""
    sat = np.any(image >= 0.98, axis=-1)
    zero = np.all(image <= 0, axis=-1)
    refl = image / truth
    light = a[..., None] * k * L1 + (1 - a[..., None]) * L2
    out = refl * light
    top = float(out[~sat & ~zero].max()) if np.any(~sat & ~zero) else 1.0
    out = np.clip(out / top, 0, 1)
    out[sat] = 1.0
    out[zero] = 0.0
    return out.astype(np.float32), light / light.sum(axis=-1, keepdims=True)


def make_scenes(rs, idx, rng) -> list[dict]:
    """One two-light scene per photograph of ``idx`` (mask kinds and pair
    kinds in turn) and the photograph itself as a single-light scene."""
    scenes = []
    for n, i in enumerate(idx):
        cam = rs.camera[i]
        lights = rs.truth[(rs.camera == cam) & (np.arange(len(rs.truth)) != i)]
        img = rs.images[i]
        scenes.append({"i": int(i), "kind": "one light", "image": img,
                       "light": np.broadcast_to(rs.truth[i] / rs.truth[i].sum(), img.shape).copy()})
        mk, pk = MASKS[n % len(MASKS)], list(PAIRS)[(n // len(MASKS)) % len(PAIRS)]
        L1, L2 = pick_pair(lights, pk, rng)
        a = mask_field(mk, img.shape[:2], rng)
        im2, light = relight(img, rs.truth[i], L1, L2, a, float(np.exp(rng.uniform(np.log(0.5), np.log(2.0)))))
        scenes.append({"i": int(i), "kind": "two lights", "mask": mk, "pair": pk, "image": im2, "light": light,
                       "pair_angle": float(angle_rows(L1[None], L2[None])[0])})
    return scenes


# --------------------------------------------------------------------------- evidence per scene
def scene_evidence(sc: dict, matrix: np.ndarray, model) -> dict:
    """The whole image's learnt estimate and the windows' evidence."""
    img = sc["image"]
    m = usable_mask(img)
    can, ok, K, gam = L.canonical_analysis(img, m, matrix, model.canonical)
    out = {"K": K, "ok": False}
    try:
        f = L.features(can, ok)
    except L.InsufficientSurfaceVariation:
        return out
    uv0 = model.predict(model.inputs(f), np.array([gam]))[0] + f[L.REFERENCE]
    ev = LM.window_evidence(can, ok, model, gam)
    valid_px = np.any(img > 0, axis=-1)
    sog = shades_of_gray(img, m, 6.0)
    return {"K": K, "ok": True, "uv0": uv0, "ev": ev, "valid_px": valid_px, "sog": sog,
            "outside": bool(model.outside(gam)[0])}


def field_error(fld_uv: np.ndarray, ev, K: np.ndarray, light: np.ndarray, valid_px: np.ndarray) -> float:
    """Mean per-pixel angle of a (gr, gc, 2) field against the true light."""
    rows, cols = np.nonzero(valid_px)
    cr = np.unique(ev.centres[:, 0])
    cc = np.unique(ev.centres[:, 1])
    can = L.uv_to_rgb(fld_uv.reshape(-1, 2)).reshape(fld_uv.shape[:2] + (3,))
    cam = can @ np.linalg.inv(K).T
    est = bilinear(cam, cr, cc, rows.astype(float), cols.astype(float))
    return float(angle_rows(est, light[rows, cols]).mean())


def one_light_error(rgb: np.ndarray, light: np.ndarray, valid_px: np.ndarray) -> float:
    return float(angle_rows(np.broadcast_to(rgb, light[valid_px].shape), light[valid_px]).mean())


def score(scenes, evs, settings_list) -> dict:
    """Per scene: errors of one light (learnt, sog, oracle), the map always
    on and the decided map, for each settings; the decision."""
    rows = []
    for sc, e in zip(scenes, evs):
        light, vp = sc["light"], e.get("valid_px", np.any(sc["image"] > 0, axis=-1))
        oracle = light[vp].mean(axis=0)
        r = {"kind": sc["kind"], "oracle": one_light_error(oracle, light, vp)}
        if not e["ok"]:       # too few cells: the product falls back to one light (shades of gray)
            sog = shades_of_gray(sc["image"], usable_mask(sc["image"]), 6.0)
            e_sog = one_light_error(sog, light, vp)
            r.update(learned=e_sog, sog=e_sog, T=0.0, maps={s: (e_sog, e_sog, False, 0.0) for s in settings_list})
            rows.append(r)
            continue
        K = e["K"]
        one = np.linalg.solve(K, L.uv_to_rgb(e["uv0"]))
        r["learned"] = one_light_error(one, light, vp)
        r["sog"] = one_light_error(e["sog"], light, vp)
        T = LM.mixture_statistic(e["ev"])
        r["T"] = T
        maps = {}
        cache = {}
        for s in settings_list:
            key = (s.gain_at(T), s.project, s.level)      # settings with the same gain here share the field
            if key not in cache:
                fld = LM.light_field(e["uv0"], e["ev"], s, T)
                rng = LM.field_range_deg(fld, K) if e["ev"].valid.sum() >= 2 else 0.0
                cache[key] = (field_error(fld, e["ev"], K, light, vp), rng)
            always, rng = cache[key]
            chosen = (not e["outside"]) and e["ev"].valid.sum() >= 2 and T > s.threshold and rng > LM.MIN_RANGE_DEG
            maps[s] = (always, always if chosen else r["learned"], chosen, rng)
        r["maps"] = maps
        rows.append(r)
    return rows


def true_window_uv(light: np.ndarray, ev, K: np.ndarray, valid_px: np.ndarray) -> np.ndarray:
    """(n, 2) the true light averaged over each window's pixels (the
    windows of :func:`recovery.light_mixture.window_evidence`), canonical
    log-chroma; NaN where a window has no valid pixel."""
    out = np.full((len(ev.centres), 2), np.nan)
    for k, sl in enumerate(LM.window_slices(light.shape)[0]):
        px = light[sl][valid_px[sl]]
        if len(px):
            out[k] = L.rgb_to_uv(K @ px.mean(axis=0))
    return out


DECOMPOSITION = ("level alone", "level's angle from the truth's average light", "true level + estimated variation",
                 "estimated level + true variation", "true level + true variation")


def decompose(scenes, evs, s: LM.MixtureSettings) -> list[dict]:
    """Where the map's error comes from, per two-light scene with a map to
    decompose: the map's two parts (:func:`recovery.light_mixture.field_parts`),
    each in turn replaced by the truth. The true level is the truth's
    average light (the oracle); the true variation is the true light
    averaged over each window, about the windows' mean, at gain 1; with
    both true, what is left is the 3 x 3 bilinear field's own floor."""
    out = []
    for sc, e in zip(scenes, evs):
        if sc["kind"] != "two lights" or not e["ok"] or e["ev"].valid.sum() < 2:
            continue
        K, ev, vp, light = e["K"], e["ev"], e["valid_px"], sc["light"]
        oracle = light[vp].mean(axis=0)
        true_level = L.rgb_to_uv(K @ oracle)
        tw = true_window_uv(light, ev, K, vp)
        have = ev.valid & np.all(np.isfinite(tw), axis=1)
        true_dev = np.zeros_like(tw)
        if have.any():
            true_dev[have] = tw[have] - tw[have].mean(axis=0)
        level, dev = LM.field_parts(e["uv0"], ev, s)
        gain = s.gain_at(LM.mixture_statistic(ev))

        def err(lv, dv, g):
            return field_error(LM.compose_field(lv, dv, ev, g), ev, K, light, vp)

        out.append({DECOMPOSITION[0]: err(level, dev, 0.0),
                    DECOMPOSITION[1]: float(angle_rows(np.linalg.solve(K, L.uv_to_rgb(level))[None], oracle[None])[0]),
                    DECOMPOSITION[2]: err(true_level, dev, gain),
                    DECOMPOSITION[3]: err(level, true_dev, 1.0),
                    DECOMPOSITION[4]: err(true_level, true_dev, 1.0)})
    return out


def fold_flag(rs, feats, tuv, Ks, gam, b: str, good, cache: Path, log=print) -> FlagModel:
    """The confidence and flag of the outer fold without benchmark ``b``:
    fitted exactly as the shipped one is (``train_illuminant.build`` with the
    confidence's regions: the inner out-of-fold predictions of the other two
    benchmarks), never on ``b``; kept in ``cache`` as JSON."""
    p = cache / f"without_{b.replace(' ', '_').replace('+', 'plus')}_flag.json"
    if p.exists():
        return FlagModel.from_json(p.read_text())
    tr = np.flatnonzero((rs.dataset != b) & good)
    log(f"fitting the confidence without {b} (once; cached in {p})")
    m = build(rs, feats, tuv, Ks, tr, log=lambda s: None, gam=gam, regions=dataset_regions(rs))
    p.write_text(m.flag.to_json())
    return m.flag


def flag_rows(scenes, evs, rows, matrices, model, flag, s: LM.MixtureSettings) -> list[dict]:
    """Per scene: the product's answer (the decided map, or one light) and
    its error, beside the learnt estimate's confidence and flag under the
    fold's confidence law (:func:`fold_flag`)."""
    out = []
    for sc, e, r in zip(scenes, evs, rows):
        if not e["ok"]:
            continue
        img = sc["image"]
        try:
            res = L.estimate_learned(img, usable_mask(img), matrices[sc["i"]], model=model, flag=flag)
        except L.InsufficientSurfaceVariation:
            continue
        out.append({"kind": sc["kind"], "pair": sc.get("pair"), "error": r["maps"][s][1],
                    "confidence": float(res.confidence), "low": bool(res.confidence < flag.threshold)})
    return out


def flag_stats(rows: list[dict], limit: float = 6.0) -> dict:
    """AUROC of (1 - confidence) for errors above ``limit``, the share
    flagged, and the share of the failures flagged (the catch)."""
    err = np.array([r["error"] for r in rows])
    conf = np.array([r["confidence"] for r in rows])
    low = np.array([r["low"] for r in rows], bool)
    failed = err > limit
    a = auroc(1.0 - conf, failed) if 0 < failed.sum() < failed.size else float("nan")
    return {"n": int(err.size), "failures": float(failed.mean()) if err.size else float("nan"), "auroc": a,
            "flagged": float(low.mean()) if err.size else float("nan"),
            "catch": float(low[failed].mean()) if failed.any() else float("nan")}


def settings_grid():
    return [LM.MixtureSettings(t, g, p, lv, k) for t in THRESHOLDS for g in GAINS for p in PROJECT for lv in LEVELS
            for k in SHRINKS]


#: the single-light photographs may lose at most this fraction of their
#: one-light accuracy (mean) in every group for settings to be eligible
SINGLE_LIGHT_SLACK = 0.01


def choose(rows_by_group: list[list[dict]], grid) -> LM.MixtureSettings:
    """The settings with the lowest mean over groups of the two-light
    photographs' mean per-image error of the decided map, among those that
    keep the single-light photographs' mean within
    :data:`SINGLE_LIGHT_SLACK` of one light in every group (a threshold of
    infinity, never a map, always is)."""
    best = None
    for s in grid:
        ok, two = True, []
        for rows in rows_by_group:
            one = [r for r in rows if r["kind"] == "one light"]
            if np.mean([r["maps"][s][1] for r in one]) > (1 + SINGLE_LIGHT_SLACK) * np.mean([r["learned"] for r in one]):
                ok = False
            two.append(np.mean([r["maps"][s][1] for r in rows if r["kind"] == "two lights"]))
        v = float(np.mean(two))
        if ok and (best is None or v < best[0] - 1e-12):
            best = (v, s)
    return best[1]


def _fmt(s) -> str:
    return f"{s['mean']:5.2f} {s['median']:5.2f} {s['worst25']:5.2f}"


def _relit_example(rs, i: int = None, seed: int = 6):
    """A Cube+ photograph relit by two of its camera's lights more than 10
    degrees apart across a soft edge (the speed runs' scene)."""
    rng = np.random.default_rng(seed)
    cube = np.flatnonzero(rs.dataset == "Cube+")
    i = int(cube[300 % cube.size]) if i is None else i
    L1, L2 = pick_pair(rs.truth[rs.camera == rs.camera[i]], "far", rng)
    img, _ = relight(rs.images[i], rs.truth[i], L1, L2, mask_field("soft-half", rs.images[i].shape[:2], rng), 1.0)
    return img, rs.matrices[rs.camera[i]]


def speed(rs, repeats: int = 5) -> dict:
    """Item 5's figures, side by side in one run: the one-light estimate of
    a 64 x 64 photograph; the decision and map on the 1-megapixel analysis
    image (estimate with ``spatial="auto"`` minus ``spatial=False``); a
    24-megapixel DNG white-balanced through the app with the map and with
    one light (TIFF, PNG, JPEG), medians of ``repeats`` runs."""
    import io

    import cv2
    from fastapi.testclient import TestClient

    from recovery import estimate_illuminant
    from recovery.cameras import camera_from_matrix
    from service.app import app
    from testing.dngwriter import mosaic, write_dng

    img, matrix = _relit_example(rs)
    cam = camera_from_matrix(matrix)

    def med(fn):
        ts = []
        for _ in range(repeats):
            t = time.perf_counter()
            out = fn()
            ts.append(time.perf_counter() - t)
        return float(np.median(ts)), out

    out = {}
    estimate_illuminant(img, cam, white_level=1.0)                 # warm
    out["one_light_64_ms"] = 1e3 * med(lambda: estimate_illuminant(img, cam, white_level=1.0, spatial=False))[0]
    t_auto, est = med(lambda: estimate_illuminant(img, cam, white_level=1.0))
    out["auto_64_ms"] = 1e3 * t_auto
    # the default against one light on single-light photographs (one of every benchmark's cameras in turn)
    pick = np.random.default_rng(0).choice(len(rs.images), 40, replace=False)
    one, auto = [], []
    for i in pick:
        c_i = camera_from_matrix(rs.matrices[rs.camera[i]])
        im = rs.images[i]
        estimate_illuminant(im, c_i, white_level=1.0)
        one.append(med(lambda: estimate_illuminant(im, c_i, white_level=1.0, spatial=False))[0])
        auto.append(med(lambda: estimate_illuminant(im, c_i, white_level=1.0))[0])
    out.update(single_one_ms=(1e3 * float(np.median(one)), 1e3 * float(np.max(one))),
               single_auto_ms=(1e3 * float(np.median(auto)), 1e3 * float(np.max(auto))))
    big = cv2.resize(img, (1000, 1000), interpolation=cv2.INTER_CUBIC).clip(0, 1)
    t1, _ = med(lambda: estimate_illuminant(big, cam, white_level=1.0, spatial=False))
    t2, est = med(lambda: estimate_illuminant(big, cam, white_level=1.0))
    out.update(one_light_1mp_ms=1e3 * t1, auto_1mp_ms=1e3 * t2, decision_and_map_1mp_ms=1e3 * (t2 - t1),
               map_decided_1mp=est.light_map is not None)
    huge = cv2.resize(img, (6000, 4000), interpolation=cv2.INTER_LINEAR).clip(0, 1)
    buf = io.BytesIO()
    write_dng(buf, (mosaic(huge) * 60000).astype(np.uint16), color_matrix1=matrix, model="Canon EOS 550D relit")
    del huge
    data = buf.getvalue()
    c = TestClient(app, base_url="http://127.0.0.1")
    for fmt in ("tiff", "png", "jpeg"):
        for mode in ("false", "auto"):
            def post():
                r = c.post("/v1/white-balance", files={"file": ("relit.dng", data)},
                           data={"format": fmt, "spatial": mode})
                assert r.status_code == 200, r.text[:300]
                return json.loads(r.headers["x-illuminant"])["lights"]["found"]
            t, found = med(post) if repeats > 1 else med(post)
            out[f"wb24_{fmt}_{'map' if mode == 'auto' else 'one'}_s"] = t
            out[f"wb24_{fmt}_{mode}_lights"] = found
        out[f"wb24_{fmt}_ratio"] = out[f"wb24_{fmt}_map_s"] / out[f"wb24_{fmt}_one_s"]
    return out


def cast_profile(out: np.ndarray, ref: np.ndarray, parts: int = 8) -> np.ndarray:
    """Mean angle (degrees) per ``parts``-th of the width between a picture
    and a reference (linear RGB, the same size), after the one per-channel
    gain that matches them on the rightmost part (where a :mod:`testing.relight`
    photograph keeps its own light): the cast left that varies across the
    frame. Both are reduced 16 x (area) first; pixels near black or clipping
    are left out."""
    import cv2

    h, w = ref.shape[:2]
    o = cv2.resize(np.asarray(out, np.float32), (w // 16, h // 16), interpolation=cv2.INTER_AREA).astype(float)
    r = cv2.resize(np.asarray(ref, np.float32), (w // 16, h // 16), interpolation=cv2.INTER_AREA).astype(float)
    ok = (r.min(-1) > 0.01 * r.max()) & (r.max(-1) < 0.9 * r.max()) & (o.max(-1) < 0.9 * o.max())
    col = np.arange(r.shape[1])[None, :].repeat(r.shape[0], 0) * parts // r.shape[1]
    fit = ok & (col == parts - 1)
    o = o * np.array([np.median(r[..., k][fit] / np.maximum(o[..., k][fit], 1e-12)) for k in range(3)])
    ang = angle_rows(o.reshape(-1, 3), r.reshape(-1, 3)).reshape(ok.shape)
    return np.array([ang[ok & (col == q)].mean() for q in range(parts)])


def picture(raw_path: str, out_png: str | None = None) -> dict:
    """A real camera file relit at its mosaic by tungsten over its left half
    (:func:`testing.relight.relit_dng`), white-balanced through the service
    (``POST /v1/white-balance``, linear sRGB TIFF) with one light and with
    the default's decision; each picture's cast across the frame against the
    photograph's own white balance (:func:`cast_profile`). Writes the three
    pictures side by side to ``out_png`` (sRGB, 1/8 size)."""
    import io
    import json

    import cv2
    import tifffile
    from fastapi.testclient import TestClient

    from service.app import app
    from testing.relight import raw_mosaic, relit_dng, write_raw

    c = TestClient(app, base_url="http://127.0.0.1")

    def wb(data, spatial):
        r = c.post("/v1/white-balance", files={"file": ("x.dng", data)},
                   data={"format": "tiff", "output": "linear-sRGB", "spatial": spatial})
        r.raise_for_status()
        return tifffile.imread(io.BytesIO(r.content)).astype(float), json.loads(r.headers["x-illuminant"])

    raw = raw_mosaic(Path(raw_path).read_bytes())
    ref, h0 = wb(write_raw(raw, raw["cfa"]), "auto")
    data, g = relit_dng(raw, h0["illuminant"]["camera_rgb"])
    res = {"photograph_lights": h0["lights"]["found"], "second_over_first": g.tolist(),
           "second_light_angle_deg": float(angle_rows(g[None], np.ones((1, 3)))[0])}
    pics = [ref]
    for sp in ("false", "auto"):
        o, h = wb(data, sp)
        an = c.post("/v1/analyze", files={"file": ("x.dng", data)}, data={"spatial": sp}).json()
        res[sp] = {"lights": h["lights"]["found"], "reason": h["lights"]["reason"],
                   "gain": an["diagnostics"].get("spatial_test", {}).get("gain"),
                   "cast_by_eighths": cast_profile(o, ref).tolist()}
        pics.append(o)
    if out_png:
        hh, ww = ref.shape[:2]
        top = np.percentile(cv2.resize(np.asarray(ref, np.float32), (ww // 8, hh // 8)), 99)

        def show(im):
            im = cv2.resize(np.asarray(im, np.float32), (ww // 8, hh // 8), interpolation=cv2.INTER_AREA) / top
            im = np.clip(im, 0, 1)
            im = np.where(im <= 0.0031308, 12.92 * im, 1.055 * im ** (1 / 2.4) - 0.055)
            return (im * 255 + 0.5).astype(np.uint8)[..., ::-1]

        cv2.imwrite(out_png, np.concatenate([show(p_) for p_ in pics], axis=1), [cv2.IMWRITE_JPEG_QUALITY, 85])
        res["png"] = out_png
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(REAL_DIR))
    ap.add_argument("--per", type=int, default=300, help="photographs per benchmark (default 300)")
    ap.add_argument("--out", default="out")
    ap.add_argument("--cache", default="out/mixed_light_models", help="fitted models kept here between runs")
    ap.add_argument("--speed", action="store_true", help="only the speed figures (item 5), about a minute")
    ap.add_argument("--picture", metavar="RAW", help="only the picture figure: this Bayer DNG relit by tungsten "
                    "over its left half, white-balanced with one light and with the default (about 30 s)")
    ap.add_argument("--picture-png", default=None, help="with --picture: write the three pictures side by side here (PNG or JPEG by its extension)")
    a = ap.parse_args(argv)
    t_all = time.perf_counter()
    if a.picture:
        res = picture(a.picture, a.picture_png)
        print(f"{a.picture} relit by tungsten over its left half ({res['second_light_angle_deg']:.1f} degrees from "
              f"its own light in camera RGB); the photograph itself: {res['photograph_lights']} light(s) found")
        print("cast left in the white-balanced picture (linear sRGB, degrees) by eighths of the width, left to "
              "right, after one gain matching the right eighth to the photograph's own picture:")
        for sp, name in (("false", "one light (spatial=false)"), ("auto", "the default (spatial=auto)")):
            r = res[sp]
            print(f"  {name:27s} " + " ".join(f"{v:5.1f}" for v in r["cast_by_eighths"])
                  + f"   lights {r['lights']}" + (f", gain {r['gain']:.2f}" if r["gain"] is not None and r["lights"] > 1 else ""))
        print("  " + res["auto"]["reason"])
        if res.get("png"):
            print(f"wrote {res['png']}: the photograph, one light, the default")
        return 0
    rs = load_real(a.data)
    if a.speed:
        sp = speed(rs, repeats=3)
        print("speed, medians of 3 runs in this process (load average "
              f"{' '.join(f'{x:.1f}' for x in __import__('os').getloadavg())}):")
        print(f"  one light, 64 x 64: {sp['one_light_64_ms']:.1f} ms (target <= 20); with the decision "
              f"{sp['auto_64_ms']:.1f} ms")
        print(f"  40 single-light photographs, median / worst: one light {sp['single_one_ms'][0]:.1f} / "
              f"{sp['single_one_ms'][1]:.1f} ms; the default {sp['single_auto_ms'][0]:.1f} / "
              f"{sp['single_auto_ms'][1]:.1f} ms (target <= 20)")
        print(f"  1-megapixel analysis image: one light {sp['one_light_1mp_ms']:.0f} ms, with the decision and "
              f"map {sp['auto_1mp_ms']:.0f} ms: decision and map {sp['decision_and_map_1mp_ms']:.0f} ms (target "
              f"<= 150; map decided: {sp['map_decided_1mp']})")
        for fmt in ("tiff", "png", "jpeg"):
            print(f"  24-megapixel DNG white balance, {fmt}: one light {sp[f'wb24_{fmt}_one_s']:.2f} s, with the map "
                  f"{sp[f'wb24_{fmt}_map_s']:.2f} s ({sp[f'wb24_{fmt}_auto_lights']} lights found): ratio "
                  f"{sp[f'wb24_{fmt}_ratio']:.2f} (target <= 1.3)")
        return 0
    rng = np.random.default_rng(27)
    feats, tuv, Ks, gam = dataset_features(rs)
    good = usable(feats)
    loc = locus()
    cache = Path(a.cache)
    cache.mkdir(parents=True, exist_ok=True)
    outer_models, inner_models = {}, {}
    for b in rs.datasets:
        p = cache / f"without_{b.replace(' ', '_').replace('+', 'plus')}.npz"
        if p.exists():
            outer_models[b] = L.load_model(str(p))
        else:
            tr = np.flatnonzero((rs.dataset != b) & good)
            outer_models[b] = build(rs, feats, tuv, Ks, tr, log=lambda s: None, gam=gam)
            outer_models[b].save(p)
    for b in rs.datasets:       # a model fitted on one benchmark, with the ridge and law of the outer model
        for c in rs.datasets:
            if c == b:
                continue
            only = [d for d in rs.datasets if d not in (b, c)][0]
            key = (b, c)         # outer b left out, inner c left out: fitted on `only`
            p = cache / f"only_{only.replace(' ', '_').replace('+', 'plus')}_for_{b.replace(' ', '_').replace('+', 'plus')}.npz"
            if p.exists():
                inner_models[key] = L.load_model(str(p))
                continue
            om = outer_models[b]
            tr = np.flatnonzero((rs.dataset == only) & good)
            m = fit_model(feats[tr], tuv[tr], rs.dataset[tr], rs.camera[tr], om.info["selection"]["chosen_ridge"],
                          loc, sigma=om.sigma, conf=om.confidence_coef, gam=gam[tr])
            m.save(p)
            inner_models[key] = m
    flags = {b: fold_flag(rs, feats, tuv, Ks, gam, b, good, cache) for b in rs.datasets}
    print(f"models ready ({time.perf_counter() - t_all:.0f} s)")

    picks = {b: np.sort(rng.choice(np.flatnonzero(rs.dataset == b), min(a.per, int(np.sum(rs.dataset == b))),
                                   replace=False)) for b in rs.datasets}
    scenes = {b: make_scenes(rs, picks[b], rng) for b in rs.datasets}
    grid = settings_grid()
    t0 = time.perf_counter()
    # inner scores: for outer b, each other benchmark c scored by the model fitted on the third
    inner_rows = {}
    for b in rs.datasets:
        for c in rs.datasets:
            if c == b:
                continue
            m = inner_models[(b, c)]
            evs = [scene_evidence(sc, rs.matrices[rs.camera[sc["i"]]], m) for sc in scenes[c]]
            inner_rows[(b, c)] = score(scenes[c], evs, grid)
    chosen = {b: choose([inner_rows[(b, c)] for c in rs.datasets if c != b], grid) for b in rs.datasets}
    t_inner = time.perf_counter() - t0
    t0 = time.perf_counter()
    outer_rows, outer_evs = {}, {}
    n_ev = 0
    for b in rs.datasets:
        evs = [scene_evidence(sc, rs.matrices[rs.camera[sc["i"]]], outer_models[b]) for sc in scenes[b]]
        n_ev += len(evs)
        outer_evs[b] = evs
        outer_rows[b] = score(scenes[b], evs, sorted(set(grid) | {chosen[b]}, key=str))
    t_outer = time.perf_counter() - t0
    # the shipped settings: the same rule on every benchmark's relit photographs, each scored by the model
    # that did not see its benchmark (what the procedure chooses with all the development data)
    shipped = choose([outer_rows[b] for b in rs.datasets], grid)
    report = {"per_benchmark": a.per, "chosen": {b: vars(s) for b, s in chosen.items()}, "results": {},
              "shipped_choice": vars(shipped), "shipped_now": vars(LM.DEFAULT_SETTINGS)}
    print(f"settings the rule chooses on all three benchmarks (to ship): T > {shipped.threshold:g}, gain "
          f"{shipped.gain:g}, shrink {shipped.shrink:g}, {'projected' if shipped.project else 'free'}, level {shipped.level:g}; shipped now: "
          f"T > {LM.DEFAULT_SETTINGS.threshold:g}, gain {LM.DEFAULT_SETTINGS.gain:g}, shrink {LM.DEFAULT_SETTINGS.shrink:g}, "
          f"{'projected' if LM.DEFAULT_SETTINGS.project else 'free'}, level {LM.DEFAULT_SETTINGS.level:g}")
    print(f"\nsettings chosen by inner leave-one-benchmark-out (threshold on T, gain, projection): "
          + "; ".join(f"without {b}: T > {s.threshold:g}, gain {s.gain:g}, shrink {s.shrink:g}, "
                                 f"{'projected' if s.project else 'free'}, "
                                 f"level {s.level:g}"
                      for b, s in chosen.items()))
    # "best decision": each scene's map or one light, whichever is better there (an oracle of the decision
    # alone: what no rule on the image can beat with these maps)
    cols = ("learned", "sog", "oracle", "map always", "map decided", "best decision")
    print("\nmean per-pixel angle per image (degrees): mean / median / worst 25 % over images")
    pooled = {k: {c: [] for c in cols} for k in ("two lights", "one light")}
    conf_all = {k: [0, 0] for k in ("two lights", "one light")}
    for b in rs.datasets:
        s = chosen[b]
        report["results"][b] = {}
        for kind in ("two lights", "one light"):
            rows = [r for r in outer_rows[b] if r["kind"] == kind]
            vals = {"learned": [r["learned"] for r in rows], "sog": [r["sog"] for r in rows],
                    "oracle": [r["oracle"] for r in rows], "map always": [r["maps"][s][0] for r in rows],
                    "map decided": [r["maps"][s][1] for r in rows],
                    "best decision": [min(r["maps"][s][0], r["learned"]) for r in rows]}
            n_map = int(sum(r["maps"][s][2] for r in rows))
            conf_all[kind][0] += len(rows) - n_map
            conf_all[kind][1] += n_map
            print(f"\n{b} (left out), {kind}: {len(rows)} photographs; decided a map for {n_map}")
            print(f"  {'':22s} mean median worst25")
            report["results"][b][kind] = {"n": len(rows), "maps_decided": n_map}
            for c in cols:
                st = error_stats(vals[c])
                report["results"][b][kind][c] = st
                pooled[kind][c] += vals[c]
                print(f"  {c:22s} {_fmt(st)}")
        two = [r for r in outer_rows[b] if r["kind"] == "two lights"]
        for key, opts in (("pair", PAIRS), ("mask", MASKS)):
            line = []
            for o in opts:
                sel = [r for r, sc in zip(outer_rows[b], scenes[b]) if sc.get(key) == o]
                if sel:
                    line.append(f"{o} {np.mean([r['maps'][s][1] for r in sel]):.2f}/"
                                f"{np.mean([r['learned'] for r in sel]):.2f}/{np.mean([r['oracle'] for r in sel]):.2f}")
            print(f"  by {key} (decided map / one light / oracle, means): " + ", ".join(line))
    # where the map's error comes from: each of its two parts replaced by the truth in turn
    print("\nwhere the map's error comes from (two-light scenes with a map to decompose, each benchmark's chosen "
          "settings, the map always on; means):")
    print(f"  {'':48s} " + " ".join(f"{b[:10]:>10s}" for b in rs.datasets) + "     pooled")
    dec = {b: decompose(scenes[b], outer_evs[b], chosen[b]) for b in rs.datasets}
    report["decomposition"] = {}
    for k in DECOMPOSITION:
        vals = {b: float(np.mean([r[k] for r in dec[b]])) for b in rs.datasets}
        pooled_k = float(np.mean([r[k] for b in rs.datasets for r in dec[b]]))
        report["decomposition"][k] = {**vals, "pooled": pooled_k}
        print(f"  {k:48s} " + " ".join(f"{vals[b]:10.2f}" for b in rs.datasets) + f" {pooled_k:10.2f}")
    # does the confidence say when the answer (map or one light) went wrong on these scenes?
    print("\nthe confidence on these scenes (each fold's own confidence law, fitted as the shipped one on the other "
          "two benchmarks' single-light photographs; the error of the product's answer, the decided map or one "
          "light; a failure is above 6 degrees): n, failures, AUROC of (1 - confidence), flagged, caught")
    fr = {b: flag_rows(scenes[b], outer_evs[b], outer_rows[b], {sc["i"]: rs.matrices[rs.camera[sc["i"]]]
                                                                for sc in scenes[b]},
                       outer_models[b], flags[b], chosen[b]) for b in rs.datasets}
    report["confidence"] = {}
    groups = [("single-light", lambda r: r["kind"] == "one light"), ("two-light", lambda r: r["kind"] == "two lights")]
    groups += [(f"  {p} pairs", lambda r, p=p: r["pair"] == p) for p in PAIRS]
    for b in list(rs.datasets) + ["pooled"]:
        rows_b = [r for c in rs.datasets for r in fr[c]] if b == "pooled" else fr[b]
        report["confidence"][b] = {}
        print(f"  {b}" + (f" (flag threshold {flags[b].threshold:.3f})" if b != "pooled" else ""))
        for name, keep in groups:
            st = flag_stats([r for r in rows_b if keep(r)])
            report["confidence"][b][name.strip()] = st
            print(f"    {name:16s} {st['n']:5d} {st['failures']:6.1%} {st['auroc']:6.3f} {st['flagged']:6.1%} "
                  f"{st['catch']:6.1%}")
    print("\npooled over the left-out benchmarks")
    report["pooled"] = {}
    for kind in ("two lights", "one light"):
        print(f"  {kind}:")
        report["pooled"][kind] = {}
        for c in cols:
            st = error_stats(pooled[kind][c])
            report["pooled"][kind][c] = st
            print(f"  {c:22s} {_fmt(st)}")
    print("\ndecision (rows: truth; columns: decided one light / several)")
    for kind in ("one light", "two lights"):
        print(f"  {kind:12s} {conf_all[kind][0]:5d} {conf_all[kind][1]:5d}")
    report["confusion"] = conf_all
    tp = report["pooled"]["two lights"]
    print(f"\ntarget (two-light scenes): decided map mean {tp['map decided']['mean']:.2f} vs the best single light "
          f"{tp['oracle']['mean']:.2f}, median {tp['map decided']['median']:.2f} vs {tp['oracle']['median']:.2f}; "
          f"single-light photographs: decided {report['pooled']['one light']['map decided']['mean']:.2f} vs one "
          f"light {report['pooled']['one light']['learned']['mean']:.2f}")
    print(f"evidence per scene {1e3 * t_outer / max(n_ev, 1):.1f} ms (64 x 64, features of the image and 9 windows); "
          f"inner selection {t_inner:.0f} s; total {time.perf_counter() - t_all:.0f} s")
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "mixed_light.json").write_text(json.dumps(report, indent=1, default=float))
    print(f"wrote {out / 'mixed_light.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
