"""The product beside the raw editors photographers use (issue 30).

``python -m benchmarks.raw_editors [--per-set 250] [--shipped-model] [--batch 4] [--skip-wb] [--skip-batch]
[--skip-dng]``

(3., ``--skip-dng`` skips it: the product's ``format=dng`` made from the real
CinemaDNG's raw data as for a RAW that is not a DNG, opened by each editor
with its as-shot white; the balance of each one's JPEG beside the product's,
:func:`bench_dng_readback`.)

Runs ``rawtherapee-cli`` and ``darktable-cli`` when they are installed
(``apt-get install -y darktable rawtherapee``; each skipped with a message
otherwise) beside the product, on the same DNGs:

1. **Automatic white balance** on the development photographs
   (``../shared/data/real``: NUS 8-camera, Cube+, INTEL-TAU field;
   ``--per-set`` of each, drawn with a fixed seed). Each 64x64 linear
   thumbnail is enlarged 4x (each pixel a block of 4x4, so the demosaic
   has little to guess) and written as an RGGB DNG
   (:func:`testing.dngwriter.write_dng`, 14-bit) with the camera's own
   matrix (``cameras.json``, ColorMatrix1 for D65) and a **neutral as-shot
   white** (AsShotNeutral 1, 1, 1): a tool that keeps the camera's white
   corrects nothing. Each tool's light is read back from its output: the
   DNG is rendered twice, with the tool's automatic white balance and with
   the as-shot (fixed, unit) multipliers; both outputs are linearised
   (sRGB's curve undone), the fixed render gives the tool's camera-to-output
   matrix ``K`` (least squares against the known camera RGB), and the
   automatic render, taken back through ``K``, gives the multiplier of each
   camera channel (least squares per channel): the light is their inverse.
   The reading is validated first on DNGs whose as-shot white is set to a
   known light (the truth of the photograph): the fixed render of such a DNG
   must give back that light (its angular error is printed). The product's
   light is its estimate (:func:`service.pipeline.analyze`, ``auto`` and
   ``shades-of-gray``) on the same DNG. Errors: the angle (degrees) between
   the camera-RGB light and the benchmark's measured one.

   RawTherapee 5.9: the automatic white balance of ``rawtherapee-cli``
   (``[White Balance] Setting=autold``, "RGB grey"; its temperature
   correlation method is not in 5.9's command line). darktable 4.2: not
   measured, ``darktable-cli`` has no automatic white balance (only its GUI).

   **Leave one benchmark out.** The product's ``auto`` is the learnt
   estimator (:mod:`recovery.learned`), and the shipped model was fitted on
   these very photographs. So for the photographs of benchmark B the
   product runs with the model fitted on the other two benchmarks
   (:func:`fold_models`: :func:`benchmarks.train_illuminant.leave_one_benchmark_out`,
   the same fold models as ``python -m benchmarks.real_photos --no-loco``),
   swapped in for the duration (:func:`product_model`; its confidence and
   flag with it). Nothing of B chose or fitted it. ``--shipped-model`` also
   runs the shipped model (flattered: it saw every photograph), printed
   beside it. The editors' methods fit nothing.

   Printed per benchmark and pooled: mean, median, worst 25 % (the mean of
   the worst quarter, :func:`benchmarks.realdata.error_stats`) and the share
   of photographs on which each of the product's methods is closer than
   RawTherapee. The white-balance part took 7.5 minutes with the default
   ``--per-set 250`` and ``--shipped-model`` on the idle two-core machine
   (1.5 of them fitting the fold models; ``docs/demosaic.md``).

2. **Batch throughput and peak memory** on a folder of ``--batch`` copies of
   the 24-megapixel bench DNG (:func:`benchmarks.white_balance.write_bench_dng`),
   to JPEG, whole commands as a user types them: ``wandell batch IN OUT
   --format jpeg`` (``python -m service.cli``), ``darktable-cli IN
   OUT/$(FILE_NAME) --out-ext jpg`` (its own empty config, library in
   memory) and ``rawtherapee-cli -o OUT -j95 -d -Y -c IN`` (its default
   profile). Images per minute; peak memory is the largest resident set of
   the command or any one of its child processes (``wait4``'s
   ``ru_maxrss``), not their sum.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks.realdata import BENCHMARKS, error_stats

SHARED = os.environ.get("WANDELL_SHARED_DIR") or os.path.join(
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "shared")
REAL = os.path.join(SHARED, "data", "real")
SHARED_RAW = os.path.join(SHARED, "data", "raw")
SETS = ("nus8", "cubeplus", "tau_field")
#: each set's benchmark, as :mod:`benchmarks.realdata` names it
SET_NAMES = {f[:-len(".npz")]: b for b, f in BENCHMARKS.items()}
ENLARGE = 4
WHITE = 16383

_RT_PP3 = """[Version]
AppVersion=5.9
Version=346

[White Balance]
Enabled=true
Setting={setting}
Equal=1
TemperatureBias=0
"""


def angle(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = a @ b / (np.linalg.norm(a) * np.linalg.norm(b))
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def srgb_to_linear(v):
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def photographs(per_set: int, seed: int = 0) -> list[dict]:
    """``per_set`` photographs of each development benchmark (fixed seed)."""
    cams = json.load(open(os.path.join(REAL, "cameras.json")))
    rng = np.random.default_rng(seed)
    out = []
    for s in SETS:
        with np.load(os.path.join(REAL, f"{s}.npz")) as z:      # each array read once (an npz decompresses
            d = {k: z[k] for k in ("camera", "images", "illuminant_rgb")}   # it at every access)
        n = len(d["camera"])
        for i in sorted(rng.choice(n, size=min(per_set, n), replace=False)):
            cam = str(d["camera"][i])
            if cam not in cams:
                continue
            out.append({"set": s, "index": int(i), "camera": cam, "image": d["images"][i].astype(np.float64) / 65535,
                        "truth": np.asarray(d["illuminant_rgb"][i], float),
                        "matrix": np.asarray(cams[cam]["xyz_to_camera_D65"], float)})
    return out


def camera_rgb(photo: dict) -> np.ndarray:
    """The camera RGB the DNG holds (the thumbnail enlarged, at the DNG's scale: 1 = white)."""
    img = np.clip(photo["image"], 0, 1) * 0.9           # the brightest pixel below white: nothing clips
    return np.repeat(np.repeat(img, ENLARGE, 0), ENLARGE, 1)


def write_photo_dng(path: str, photo: dict, as_shot=(1.0, 1.0, 1.0)) -> None:
    from recovery.demosaic import mosaic
    from testing.dngwriter import write_dng

    cfa = np.round(mosaic(camera_rgb(photo), "RGGB") * WHITE).astype(np.uint16)
    write_dng(path, cfa, pattern="RGGB", black_level=0, white_level=WHITE, color_matrix1=photo["matrix"],
              as_shot_neutral=list(as_shot), model="benchmark DNG")


def rt_render(dng: str, out: str, setting: str, tmp: str) -> np.ndarray:
    import tifffile

    pp3 = os.path.join(tmp, f"wb_{setting}.pp3")
    if not os.path.exists(pp3):
        with open(pp3, "w") as f:
            f.write(_RT_PP3.format(setting=setting))
    r = subprocess.run(["rawtherapee-cli", "-o", out, "-t", "-b16", "-Y", "-p", pp3, "-c", dng],
                       capture_output=True, text=True)
    if r.returncode != 0 or not os.path.exists(out):
        raise RuntimeError(f"rawtherapee-cli failed: {r.stdout[-300:]} {r.stderr[-300:]}")
    return srgb_to_linear(tifffile.imread(out).astype(np.float64) / 65535.0)


def _centre(a: np.ndarray, shape) -> np.ndarray:
    dy, dx = (a.shape[0] - shape[0]) // 2, (a.shape[1] - shape[1]) // 2
    return a[dy:dy + shape[0], dx:dx + shape[1]]


def read_light(auto: np.ndarray, fixed: np.ndarray, cam: np.ndarray, fixed_light) -> np.ndarray:
    """The light a tool applied: camera-RGB light (green 1) from its
    automatic render, its render with the as-shot white set to
    ``fixed_light`` (multipliers ``1 / fixed_light``) and the known camera
    RGB (see the module's docstring)."""
    cam = _centre(cam, fixed.shape)
    inner = (slice(ENLARGE, -ENLARGE), slice(ENLARGE, -ENLARGE))
    c, f, a = cam[inner].reshape(-1, 3), fixed[inner].reshape(-1, 3), auto[inner].reshape(-1, 3)
    # outputs clipped at 0 or near white break the linear model: left out
    ok = (c.min(1) > 0.002) & (f.max(1) < 0.97) & (a.max(1) < 0.97) & (f.min(1) > 0.002) & (a.min(1) > 0.002)
    if ok.sum() < 50:
        raise ValueError("too few unclipped pixels")
    mf = 1.0 / np.asarray(fixed_light, float)
    K, *_ = np.linalg.lstsq(c[ok] * mf, f[ok], rcond=None)     # f = (c * m_f) @ K
    y = np.linalg.solve(K.T, a[ok].T).T                        # a = (c * m_a) @ K  ->  y = c * m_a
    r = (y * c[ok]).sum(0) / (c[ok] ** 2).sum(0)
    light = 1.0 / r
    return light / light[1]


def grey_world(photo: dict) -> np.ndarray:
    """The mean camera RGB of the photograph (green 1): the fixed render's white."""
    img = photo["image"].reshape(-1, 3)
    m = img[(img.max(1) < 0.98) & (img.min(1) > 0)].mean(0)
    return m / m[1]


def product_light(dng_bytes: bytes, method: str) -> np.ndarray:
    from service import pipeline
    from service.settings import get_settings

    _, run = pipeline.analyze(dng_bytes, "a.dng", get_settings(), method=method)
    return np.asarray(run.estimate.rgb, float)


def fold_models(rs=None, log=print) -> dict:
    """The learnt model fitted without each benchmark.

    The whole training procedure of :mod:`benchmarks.train_illuminant` (its
    settings chosen by inner leave-one-benchmark-out, its uncertainty,
    confidence and flag calibrated there) run on the other two benchmarks:
    :func:`benchmarks.train_illuminant.leave_one_benchmark_out`, as
    ``python -m benchmarks.real_photos --no-loco`` calls it (without the
    histogram stage, as shipped).

    Parameters
    ----------
    rs : :class:`benchmarks.realdata.RealSet`, default all the development
        photographs (:func:`benchmarks.realdata.load_real`)
    log : callable for the training's progress

    Returns
    -------
    dict
        benchmark name -> :class:`recovery.learned.LearnedModel`, its
        ``info["fold"]`` naming the benchmark left out and those it was
        fitted on.
    """
    from benchmarks.realdata import load_real
    from benchmarks.train_illuminant import (dataset_features, dataset_regions, leave_one_benchmark_out,
                                             single_threaded)

    rs = load_real(REAL) if rs is None else rs
    feats, tuv, Ks, gam = dataset_features(rs)
    regions = dataset_regions(rs)
    with single_threaded():
        lodo = leave_one_benchmark_out(rs, feats, tuv, Ks, gam=gam, regions=regions, log=log)
    return {b: dataclasses.replace(m, info={**m.info, "fold": {"left_out": b,
                                                                "trained_on": [d for d in rs.datasets if d != b]}})
            for b, (m, _, _) in lodo.items()}


@contextlib.contextmanager
def product_model(model):
    """The product's learnt estimator uses ``model`` for the duration.

    :func:`recovery.learned.load_model` (without a path: the shipped model)
    returns ``model`` instead, and :func:`recovery.confidence.load_flag_model`
    its confidence and flag (``model.flag``) when it has them; both are
    restored, and their caches cleared, on leaving. The product reads both
    only through these functions at call time, so nothing else changes.
    ``model=None``: the shipped model, nothing swapped.

    Parameters
    ----------
    model : :class:`recovery.learned.LearnedModel` or None
    """
    from recovery import confidence, learned

    if model is None:
        yield None
        return
    load, load_flag = learned.load_model, confidence.load_flag_model
    learned.load_model = lambda path=None: model if path is None else load(path)
    if model.flag is not None:
        confidence.load_flag_model = lambda path=None: model.flag if path is None else load_flag(path)
    try:
        yield model
    finally:
        learned.load_model, confidence.load_flag_model = load, load_flag
        load.cache_clear()
        load_flag.cache_clear()


def model_text(model) -> str:
    """Which learnt model: what it was fitted on (its ``info``)."""
    if model is None:
        from recovery.learned import load_model

        info = load_model().info
        return "shipped model (recovery/data/learned_illuminant.npz), fitted on " + ", ".join(
            f"{b} ({n})" for b, n in info.get("benchmarks", {}).items())
    from benchmarks.train_illuminant import ridge_text

    f = model.info["fold"]
    return (f"fold model fitted on {' and '.join(f['trained_on'])} only ({f['left_out']} left out; ridge "
            f"{ridge_text(model.info['selection']['chosen_ridge'])})")


#: the methods measured, in the order printed
PRODUCT_AUTO, PRODUCT_SHIPPED, PRODUCT_SOG = ("product auto (fold model)", "product auto (shipped model)",
                                              "product shades-of-gray")
RT_AUTO, VALIDATION = "RawTherapee auto (RGB grey)", "validation (as-shot set to the truth)"


def bench_white_balance(per_set: int, shipped: bool = False, folds: dict | None = None, log=print) -> dict:
    """Angular errors of each method on ``per_set`` photographs of each
    development benchmark written as DNGs (see the module's docstring).

    Parameters
    ----------
    per_set : photographs of each benchmark (fixed seed)
    shipped : also the product's ``auto`` with the shipped model
    folds : benchmark name -> model (default :func:`fold_models`)
    log : callable for progress

    Returns
    -------
    dict
        ``n``; ``sets`` (N,) each photograph's benchmark; ``errors``:
        method -> (N,) degrees (NaN where a tool did not run); ``models``:
        benchmark -> which model the product's ``auto`` used; ``seconds``:
        the fold fits and the photographs.
    """
    have_rt = shutil.which("rawtherapee-cli") is not None
    if not have_rt:
        log("rawtherapee-cli not installed (apt-get install -y rawtherapee): its column is skipped")
    log("darktable: not measured for white balance (darktable-cli has no automatic white balance)")
    t0 = time.perf_counter()
    if folds is None:
        log("fitting the learnt model without each benchmark (benchmarks.train_illuminant.leave_one_benchmark_out)",
            flush=True)
        folds = fold_models(log=lambda s: None)
    t_fit = time.perf_counter() - t0
    models = {b: model_text(m) for b, m in folds.items()}
    for b, t in models.items():
        log(f"  {b} photographs: product auto uses the {t}")
    if shipped:
        log(f"  and, with --shipped-model, the {model_text(None)}")
    t1 = time.perf_counter()
    photos = photographs(per_set)
    keys = [PRODUCT_AUTO, *([PRODUCT_SHIPPED] if shipped else []), PRODUCT_SOG, RT_AUTO, VALIDATION]
    errs = {k: np.full(len(photos), np.nan) for k in keys}
    with tempfile.TemporaryDirectory() as tmp:
        for k, ph in enumerate(photos):
            dng = os.path.join(tmp, "a.dng")
            write_photo_dng(dng, ph)
            data = open(dng, "rb").read()
            with product_model(folds[SET_NAMES[ph["set"]]]):
                errs[PRODUCT_AUTO][k] = angle(product_light(data, "auto"), ph["truth"])
            if shipped:
                errs[PRODUCT_SHIPPED][k] = angle(product_light(data, "auto"), ph["truth"])
            errs[PRODUCT_SOG][k] = angle(product_light(data, "shades-of-gray"), ph["truth"])
            if have_rt:
                cam = camera_rgb(ph)
                try:
                    gw = grey_world(ph)
                    ref = os.path.join(tmp, "gw.dng")
                    write_photo_dng(ref, ph, as_shot=gw)
                    fixed = rt_render(ref, os.path.join(tmp, "fixed.tif"), "Camera", tmp)
                    auto = rt_render(dng, os.path.join(tmp, "auto.tif"), "autold", tmp)
                    errs[RT_AUTO][k] = angle(read_light(auto, fixed, cam, gw), ph["truth"])
                    # validation: the as-shot white set to the truth, rendered with it, read the same way
                    val = os.path.join(tmp, "v.dng")
                    t = ph["truth"] / ph["truth"][1]
                    write_photo_dng(val, ph, as_shot=t)
                    known = rt_render(val, os.path.join(tmp, "known.tif"), "Camera", tmp)
                    errs[VALIDATION][k] = angle(read_light(known, fixed, cam, gw), ph["truth"])
                except (RuntimeError, ValueError) as exc:
                    log(f"  {ph['set']} #{ph['index']}: RawTherapee skipped ({exc})")
            if (k + 1) % 25 == 0:
                log(f"  {k + 1}/{len(photos)} photographs, {time.perf_counter() - t1:.0f} s", flush=True)
    return {"n": len(photos), "sets": np.array([SET_NAMES[p["set"]] for p in photos]), "errors": errs,
            "models": models, "seconds": {"fold fits": t_fit, "photographs": time.perf_counter() - t1}}


def wb_table(r: dict) -> list[str]:
    """The lines printed for :func:`bench_white_balance`'s result: per
    benchmark and pooled, each method's mean, median and worst 25 %
    (degrees) and the share of photographs on which the product's method
    is closer than RawTherapee's (both measured)."""
    rt = r["errors"][RT_AUTO]
    groups = [(b, r["sets"] == b) for b in dict.fromkeys(r["sets"])] + [("pooled", np.ones(r["n"], bool))]
    lines = []
    for g, m in groups:
        lines.append(f"\n{g} ({int(m.sum())} photographs)" + (f"; product auto: {r['models'][g]}"
                                                               if g in r["models"] else ""))
        lines.append(f"{'':40s} {'mean':>6s} {'median':>6s} {'worst25':>7s} {'n':>4s}  beats RawTherapee on")
        for k, e in r["errors"].items():
            e = e[m]
            ok = np.isfinite(e)
            if not ok.any():
                lines.append(f"{k:40s} (not run)")
                continue
            s = error_stats(e[ok])
            line = f"{k:40s} {s['mean']:6.2f} {s['median']:6.2f} {s['worst25']:7.2f} {s['n']:4d}"
            both = ok & np.isfinite(rt[m])
            if k.startswith("product") and both.any():
                line += f"  {100 * np.mean(e[both] < rt[m][both]):.0f} % (of {int(both.sum())})"
            lines.append(line)
    return lines


def _run(argv, env=None) -> tuple[float, float, int]:
    """(seconds, peak MB of the command or one of its children, exit status)."""
    t0 = time.perf_counter()
    p = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    _, status, ru = os.wait4(p.pid, 0)
    p.returncode = os.waitstatus_to_exitcode(status)
    return time.perf_counter() - t0, ru.ru_maxrss / 1024, p.returncode


def bench_batch(n: int, repeat: int, log=print) -> dict:
    from benchmarks.white_balance import bench_arguments, write_bench_dng

    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        src = write_bench_dng(tmp, bench_arguments(__doc__, []))
        folder = os.path.join(tmp, "in")
        os.makedirs(folder)
        for i in range(n):
            shutil.copy(src, os.path.join(folder, f"img{i:02d}.dng"))
        env = dict(os.environ)
        env.pop("PYTHONDONTWRITEBYTECODE", None)
        cmds = {"wandell batch (quality default: RCD)": lambda out: [sys.executable, "-m", "service.cli", "batch",
                                                                      folder, out, "--format", "jpeg", "-q"],
                "wandell batch --quality fast (bilinear)": lambda out: [sys.executable, "-m", "service.cli", "batch",
                                                                         folder, out, "--format", "jpeg", "-q",
                                                                         "--quality", "fast"]}
        if shutil.which("darktable-cli"):
            cfg = os.path.join(tmp, "dtcfg")
            cmds["darktable-cli 4.2"] = lambda out: ["darktable-cli", folder, os.path.join(out, "$(FILE_NAME)"),
                                                     "--out-ext", "jpg", "--core", "--configdir", cfg,
                                                     "--library", ":memory:"]
        else:
            log("darktable-cli not installed (apt-get install -y darktable): skipped")
        if shutil.which("rawtherapee-cli"):
            cmds["rawtherapee-cli 5.9"] = lambda out: ["rawtherapee-cli", "-o", out, "-j95", "-d", "-Y", "-c", folder]
        else:
            log("rawtherapee-cli not installed (apt-get install -y rawtherapee): skipped")
        for k in cmds:
            res[k] = {"t": [], "mb": []}
        for i in range(repeat):
            for k, make in cmds.items():                 # interleaved: the machine's drift hits all alike
                out = os.path.join(tmp, f"out_{abs(hash(k))}_{i}")
                os.makedirs(out)
                secs, mb, rc = _run(make(out), env)
                made = len([f for f in os.listdir(out) if f.lower().endswith((".jpg", ".jpeg"))])
                log(f"  {k}: {secs:.1f} s, {made}/{n} JPEGs, peak {mb:.0f} MB, exit {rc}", flush=True)
                if rc != 0 or made != n:
                    log(f"  {k}: FAILED (exit {rc}, {made} of {n} outputs)")
                res[k]["t"].append(secs)
                res[k]["mb"].append(mb)
                shutil.rmtree(out, ignore_errors=True)
    return res


def bench_dng_readback(src: str, log=print) -> dict:
    """The product's DNG with the white balance inside (``format=dng``), made
    as for a RAW that is not a DNG (:func:`service.dngwrite.raw_as_dng` of
    ``src``'s raw data), read back by each editor with its default (as-shot)
    white: does it open, and is its balance the product's? Each tool's JPEG
    is reduced to its mean sRGB; the balance is the ratios R/G and B/G of the
    linearised means, printed beside the product's own JPEG of the same file."""
    from service import pipeline
    from service.dngwrite import raw_as_dng
    from service.settings import Settings

    out: dict = {}
    with open(src, "rb") as f:
        data = f.read()
    with tempfile.TemporaryDirectory() as tmp:
        decoded, run = pipeline.analyze(data, os.path.basename(src), Settings())
        text, _, summary = pipeline.xmp_sidecar(decoded, run)
        dng = os.path.join(tmp, "IMG.wandell.dng")
        with open(dng, "wb") as f:
            f.write(raw_as_dng(data, text, summary["camera_rgb"], make=decoded.make, model=decoded.model,
                               color_matrix=decoded.color_matrix))
        ours = os.path.join(tmp, "ours.jpg")
        subprocess.run([sys.executable, "-m", "service.cli", "white-balance", "-q", src, ours], check=True)
        cmds = {"product (wandell white-balance)": None}
        if shutil.which("darktable-cli"):
            cmds["darktable-cli"] = ["darktable-cli", dng, os.path.join(tmp, "dt.jpg"), "--core", "--configdir",
                                     os.path.join(tmp, "dtconf"), "--library", ":memory:"]
        else:
            log("darktable-cli not installed: its read-back is skipped")
        if shutil.which("rawtherapee-cli"):
            cmds["rawtherapee-cli"] = ["rawtherapee-cli", "-o", os.path.join(tmp, "rt.jpg"), "-j90", "-Y", "-c", dng]
        else:
            log("rawtherapee-cli not installed: its read-back is skipped")
        import cv2

        for name, argv in cmds.items():
            path = ours if argv is None else argv[2]
            if argv is not None:
                r = subprocess.run(argv, capture_output=True, text=True)
                if r.returncode != 0 or not os.path.exists(path):
                    out[name] = {"read": False, "why": (r.stdout + r.stderr)[-200:]}
                    continue
            img = cv2.imread(path)[..., ::-1].astype(np.float64) / 255.0
            m = srgb_to_linear(img).reshape(-1, 3).mean(axis=0)
            out[name] = {"read": True, "mean_srgb": (255 * img.reshape(-1, 3).mean(axis=0)).round(1).tolist(),
                         "r_g": float(m[0] / m[1]), "b_g": float(m[2] / m[1])}
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--per-set", type=int, default=250, help="photographs of each development benchmark")
    ap.add_argument("--shipped-model", action="store_true",
                    help="also the product's auto with the shipped model (fitted on these photographs)")
    ap.add_argument("--batch", type=int, default=4, help="24-megapixel DNGs in the batch folder")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each batch command (median)")
    ap.add_argument("--skip-wb", action="store_true")
    ap.add_argument("--skip-batch", action="store_true")
    ap.add_argument("--skip-dng", action="store_true", help="skip the editors reading the product's DNG back")
    args = ap.parse_args(argv)
    print(f"load average {os.getloadavg()[0]:.1f} {os.getloadavg()[1]:.1f} on {os.cpu_count()} CPUs")
    if not args.skip_wb:
        if not os.path.exists(os.path.join(REAL, "cameras.json")):
            print(f"no development photographs at {REAL}: white balance skipped")
        else:
            t0 = time.perf_counter()
            r = bench_white_balance(args.per_set, shipped=args.shipped_model)
            print(f"\nautomatic white balance, {r['n']} development photographs as DNGs with a neutral as-shot "
                  "white (angular error, degrees; worst25 = mean of the worst quarter)")
            for line in wb_table(r):
                print(line)
            print(f"white balance part: {time.perf_counter() - t0:.0f} s (fold fits "
                  f"{r['seconds']['fold fits']:.0f} s, photographs {r['seconds']['photographs']:.0f} s)")
    if not args.skip_dng:
        src = os.path.join(SHARED_RAW, "Blackmagic.dng")
        if not os.path.exists(src):
            print(f"no real RAW at {src}: the DNG read-back is skipped")
        else:
            print("\nthe product's DNG with the white balance inside (format=dng, made from the real CinemaDNG's "
                  "raw data as for a non-DNG RAW), read back with each editor's as-shot white:")
            print(f"{'':34s} {'opens':>6s} {'R/G':>6s} {'B/G':>6s}  mean sRGB of its JPEG")
            for k, v in bench_dng_readback(src).items():
                if v["read"]:
                    print(f"{k:34s} {'yes':>6s} {v['r_g']:6.3f} {v['b_g']:6.3f}  {v['mean_srgb']}")
                else:
                    print(f"{k:34s} {'NO':>6s}  {v['why']}")
    if not args.skip_batch:
        print(f"\nbatch of {args.batch} x 24-megapixel DNG -> JPEG, whole commands (median of {args.repeat}); "
              f"load average {os.getloadavg()[0]:.1f}")
        res = bench_batch(args.batch, args.repeat)
        ipm = {k: 60 * args.batch / statistics.median(v["t"]) for k, v in res.items()}
        print(f"{'command':42s} {'s':>7s} {'img/min':>8s} {'peak MB':>8s}")
        for k, v in res.items():
            print(f"{k:42s} {statistics.median(v['t']):7.1f} {ipm[k]:8.1f} {max(v['mb']):8.0f}")
        dt = [k for k in ipm if k.startswith("darktable")]
        if dt:
            for k in ipm:
                if k.startswith("wandell"):
                    print(f"{k} / darktable-cli: {ipm[k] / ipm[dt[0]]:.1f}x (target >= 5)")
        print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
