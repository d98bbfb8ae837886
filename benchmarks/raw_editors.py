"""The product beside the raw editors photographers use (issue 30).

``python -m benchmarks.raw_editors [--per-set 20] [--batch 4] [--skip-wb] [--skip-batch] [--skip-dng]``

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

   Caveat: the product's ``auto`` was fitted on these development
   photographs (leave-one-benchmark-out figures are
   ``python -m benchmarks.train_illuminant``'s); photographs it never saw
   are the fair test (the issue's 568). The editors' methods fit nothing.

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
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

SHARED = os.environ.get("WANDELL_SHARED_DIR") or os.path.join(
    os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))), "shared")
REAL = os.path.join(SHARED, "data", "real")
SHARED_RAW = os.path.join(SHARED, "data", "raw")
SETS = ("nus8", "cubeplus", "tau_field")
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
        d = np.load(os.path.join(REAL, f"{s}.npz"))
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


def bench_white_balance(per_set: int, log=print) -> dict:
    have_rt = shutil.which("rawtherapee-cli") is not None
    if not have_rt:
        log("rawtherapee-cli not installed (apt-get install -y rawtherapee): its column is skipped")
    log("darktable: not measured for white balance (darktable-cli has no automatic white balance)")
    photos = photographs(per_set)
    errs = {"product auto": [], "product shades-of-gray": [], "RawTherapee auto (RGB grey)": [],
            "validation (as-shot set to the truth)": []}
    with tempfile.TemporaryDirectory() as tmp:
        for k, ph in enumerate(photos):
            dng = os.path.join(tmp, "a.dng")
            write_photo_dng(dng, ph)
            data = open(dng, "rb").read()
            for m, key in (("auto", "product auto"), ("shades-of-gray", "product shades-of-gray")):
                errs[key].append(angle(product_light(data, m), ph["truth"]))
            if have_rt:
                cam = camera_rgb(ph)
                try:
                    gw = grey_world(ph)
                    ref = os.path.join(tmp, "gw.dng")
                    write_photo_dng(ref, ph, as_shot=gw)
                    fixed = rt_render(ref, os.path.join(tmp, "fixed.tif"), "Camera", tmp)
                    auto = rt_render(dng, os.path.join(tmp, "auto.tif"), "autold", tmp)
                    errs["RawTherapee auto (RGB grey)"].append(angle(read_light(auto, fixed, cam, gw), ph["truth"]))
                    # validation: the as-shot white set to the truth, rendered with it, read the same way
                    val = os.path.join(tmp, "v.dng")
                    t = ph["truth"] / ph["truth"][1]
                    write_photo_dng(val, ph, as_shot=t)
                    known = rt_render(val, os.path.join(tmp, "known.tif"), "Camera", tmp)
                    errs["validation (as-shot set to the truth)"].append(
                        angle(read_light(known, fixed, cam, gw), ph["truth"]))
                except (RuntimeError, ValueError) as exc:
                    log(f"  {ph['set']} #{ph['index']}: RawTherapee skipped ({exc})")
            if (k + 1) % 10 == 0:
                log(f"  {k + 1}/{len(photos)} photographs", flush=True)
    return {"n": len(photos), "errors": errs}


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
    ap.add_argument("--per-set", type=int, default=20, help="photographs of each development benchmark")
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
            r = bench_white_balance(args.per_set)
            print(f"\nautomatic white balance, {r['n']} development photographs as DNGs with a neutral as-shot "
                  "white (angular error, degrees)")
            print(f"{'':40s} {'mean':>6s} {'median':>6s} {'p95':>6s} {'n':>4s}")
            for k, e in r["errors"].items():
                if e:
                    print(f"{k:40s} {np.mean(e):6.2f} {np.median(e):6.2f} {np.percentile(e, 95):6.2f} {len(e):4d}")
                else:
                    print(f"{k:40s} (not run)")
            a, b = r["errors"]["product auto"], r["errors"]["RawTherapee auto (RGB grey)"]
            if a and len(a) == len(b):
                print(f"product auto better than RawTherapee on {100 * np.mean(np.array(a) < np.array(b)):.0f} %")
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
