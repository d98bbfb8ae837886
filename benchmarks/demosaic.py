"""Demosaic accuracy and speed (issue 30): the product's choices beside LibRaw's.

``python -m benchmarks.demosaic [--images DIR] [--crops DIR] [--big] [--repeat 3]``

Standard test photographs are linearised (sRGB's transfer function
undone), mosaicked in each of the four Bayer phases (RGGB, BGGR, GRBG,
GBRG) and written as 16-bit DNGs (:func:`testing.dngwriter.write_dng`, black
0, white 65535, a camera whose native space is linear sRGB). Each DNG is
decoded by the product (:func:`service.decode.decode_upload`) and its
full-resolution linear image made by every demosaic in the same run:

* the product's: ``rcd`` (the default and ``quality=accurate``:
  :mod:`recovery.demosaic`) and ``fast`` (``quality=fast``: OpenCV's
  edge-aware bilinear), both on the kept mosaic;
* LibRaw's, through rawpy on the same DNG (``decoded.full_linear(demosaic=NAME)``:
  linear, no white balance, raw colour): LINEAR, VNG, PPG, AHD, DCB, DHT, AAHD;
* Menon et al. 2007 (DDFAPD with refining) from the ``colour-demosaicing``
  package, when it is installed (not a product dependency).

Each result is mapped back to the reference by the one 3x3 matrix that
fits it best (least squares), so that only the demosaic counts (LibRaw
scales the channels its own way), and scored on the image less a 10-pixel
border: CPSNR (dB, over the three channels of linear values in [0, 1]) and
mean CIEDE2000 (colour-science; the linear values taken as linear sRGB,
D65). Time per megapixel: the demosaic on the test images (the product's:
the demosaic of the kept mosaic; LibRaw's: ``postprocess`` of the file,
which also unpacks it), and with ``--big`` on a 24-megapixel DNG (the
white-balance bench's), the median of ``--repeat`` runs.

The test photographs: scikit-image's bundled colour photographs (astronaut,
chelsea, coffee, motorcycle_left, rocket; from ``skimage.data`` when
installed, else ``--images DIR`` holding those files) and matplotlib's
``grace_hopper.jpg``. They are 8-bit JPEG/PNG, so already demosaicked and
compressed once: the ground truth is what they hold.

``--crops DIR``: enlarged crops (false colour at edges, zippers) of the
reference and of each demosaic, written as PNG (sRGB-encoded).
"""

from __future__ import annotations

import argparse
import glob
import io
import os
import statistics
import sys
import time

import numpy as np

PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
LIBRAW = ("LINEAR", "VNG", "PPG", "AHD", "DCB", "DHT", "AAHD")
PRODUCT = ("rcd", "fast")
SKIMAGE_PHOTOS = ("astronaut.png", "chelsea.png", "coffee.png", "motorcycle_left.png", "rocket.jpg")
BORDER = 10


def srgb_to_linear(v: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1's decoding of sRGB values in [0, 1]."""
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(v: np.ndarray) -> np.ndarray:
    v = np.clip(v, 0, 1)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def photo_paths(images: str | None = None) -> list[str]:
    """The test photographs found (see the module's docstring)."""
    paths = []
    dirs = [images] if images else []
    try:
        import skimage.data

        dirs.append(os.path.dirname(skimage.data.__file__))
    except ImportError:
        pass
    for d in dirs:
        found = [os.path.join(d, n) for n in SKIMAGE_PHOTOS if os.path.exists(os.path.join(d, n))]
        if found:
            paths += found
            break
    try:
        import matplotlib

        p = os.path.join(os.path.dirname(matplotlib.__file__), "mpl-data", "sample_data", "grace_hopper.jpg")
        if os.path.exists(p):
            paths.append(p)
    except ImportError:
        pass
    return paths


def load_linear(path: str) -> np.ndarray:
    """A photograph as linear RGB in [0, 1] (float64), cropped to even sides."""
    import cv2

    im = cv2.imread(path, cv2.IMREAD_COLOR)
    if im is None:
        raise ValueError(f"cannot read {path}")
    im = im[: im.shape[0] // 2 * 2, : im.shape[1] // 2 * 2, ::-1].astype(np.float64) / 255.0
    return srgb_to_linear(im)


def reference_u16(lin: np.ndarray) -> np.ndarray:
    return np.round(np.clip(lin, 0, 1) * 65535).astype(np.uint16)


def dng_bytes(ref16: np.ndarray, pattern: str) -> bytes:
    """The DNG of ``ref16`` mosaicked with ``pattern`` (black 0, white 65535)."""
    from recovery.demosaic import mosaic
    from testing.dngwriter import write_dng

    buf = io.BytesIO()
    write_dng(buf, mosaic(ref16, pattern), pattern=pattern, black_level=0, white_level=65535)
    return buf.getvalue()


def fit_matrix(out: np.ndarray, ref: np.ndarray, b: int = BORDER) -> np.ndarray:
    """``out`` (H, W, 3) mapped onto ``ref`` by its best 3x3 matrix (least
    squares over the image less a ``b``-pixel border)."""
    o = out[b:-b, b:-b].reshape(-1, 3)
    r = ref[b:-b, b:-b].reshape(-1, 3)
    M, *_ = np.linalg.lstsq(o, r, rcond=None)
    return (out.reshape(-1, 3) @ M).reshape(out.shape)


def cpsnr(out: np.ndarray, ref: np.ndarray, b: int = BORDER) -> float:
    """CPSNR (dB) of linear values in [0, 1], less a ``b``-pixel border."""
    d = np.clip(out[b:-b, b:-b], 0, 1) - ref[b:-b, b:-b]
    return float(10 * np.log10(1.0 / np.mean(d * d)))


def ciede2000(out: np.ndarray, ref: np.ndarray, b: int = BORDER) -> float:
    """Mean CIEDE2000 of linear sRGB values (D65), less a ``b``-pixel border."""
    import colour

    cs = colour.RGB_COLOURSPACES["sRGB"]

    def lab(x):
        xyz = colour.RGB_to_XYZ(np.clip(x[b:-b, b:-b], 0, 1), cs, apply_cctf_decoding=False)
        return colour.XYZ_to_Lab(xyz, cs.whitepoint)

    return float(np.mean(colour.delta_E(lab(out), lab(ref), method="CIE 2000")))


def product_demosaic(data: bytes, method: str) -> tuple[np.ndarray, float]:
    """The product's full-resolution linear image of a DNG by ``method``
    (``rcd``, ``fast`` or a LibRaw name) and the seconds of the demosaic
    alone (the product's: of the kept mosaic; LibRaw's: its ``postprocess``
    of the file)."""
    from service.decode import decode_upload

    d = decode_upload(data, "a.dng", max_pixels=10 ** 9, estimation_pixels=10 ** 9,
                      keep_mosaic=method in PRODUCT)
    t0 = time.perf_counter()
    rgb = d.full_linear("uint16", demosaic=method)
    return rgb, time.perf_counter() - t0


def menon(data_ref16: np.ndarray, pattern: str) -> tuple[np.ndarray, float] | None:
    try:
        from colour_demosaicing import demosaicing_CFA_Bayer_Menon2007
    except ImportError:
        return None
    from recovery.demosaic import mosaic

    cfa = mosaic(data_ref16, pattern).astype(np.float64) / 65535
    t0 = time.perf_counter()
    rgb = demosaicing_CFA_Bayer_Menon2007(cfa, pattern)
    return np.clip(rgb, 0, 1) * 65535, time.perf_counter() - t0


def score(images: list[tuple[str, np.ndarray]], methods, patterns=PATTERNS, crops=None, log=print) -> dict:
    """Every method on every image and phase: ``{method: {"cpsnr": [...],
    "de": [...], "seconds": s, "mp": m, "by_image": {name: [cpsnr...]}}}``."""
    res = {m: {"cpsnr": [], "de": [], "seconds": 0.0, "mp": 0.0, "by_image": {}} for m in methods}
    for name, lin in images:
        ref16 = reference_u16(lin)
        ref = ref16 / 65535.0
        for pattern in patterns:
            data = dng_bytes(ref16, pattern)
            for m in methods:
                if m == "menon2007":
                    got = menon(ref16, pattern)
                    if got is None:
                        continue
                    rgb, secs = got
                else:
                    rgb, secs = product_demosaic(data, m)
                out = fit_matrix(rgb.astype(np.float64) / 65535.0, ref)
                r = res[m]
                r["cpsnr"].append(cpsnr(out, ref))
                r["de"].append(ciede2000(out, ref))
                r["seconds"] += secs
                r["mp"] += ref16.shape[0] * ref16.shape[1] / 1e6
                r["by_image"].setdefault(name, []).append(r["cpsnr"][-1])
                if crops is not None and pattern == "RGGB":
                    crops.setdefault(name, {})[m] = out
        log(f"  {name}: " + ", ".join(f"{m} {statistics.mean(res[m]['by_image'].get(name, [np.nan])):.2f}"
                                      for m in methods), flush=True)
    return res


#: the crops written with --crops: (image, top, left, size), chosen where
#: bilinear interpolation shows false colour and zippers (edges, fine lines)
CROPS = (("astronaut.png", 20, 160, 64), ("motorcycle_left.png", 180, 380, 64), ("grace_hopper.jpg", 300, 200, 64),
         ("chelsea.png", 100, 150, 64))


def write_crops(crops: dict, refs: dict, methods, out_dir: str, scale: int = 4) -> list[str]:
    """Side-by-side enlarged crops (reference, then each method), sRGB PNG."""
    import cv2

    os.makedirs(out_dir, exist_ok=True)
    written = []
    for name, top, left, size in CROPS:
        if name not in crops:
            continue
        tiles = [refs[name]] + [crops[name][m] for m in methods if m in crops[name]]
        row = []
        for t in tiles:
            c = linear_to_srgb(t[top:top + size, left:left + size])
            c = np.repeat(np.repeat(c, scale, 0), scale, 1)
            c = np.pad(c, ((0, 0), (0, 4), (0, 0)), constant_values=1.0)
            row.append(c)
        img = (np.concatenate(row, 1) * 255 + 0.5).astype(np.uint8)
        path = os.path.join(out_dir, f"crop_{os.path.splitext(name)[0]}.png")
        cv2.imwrite(path, img[..., ::-1])
        written.append(path)
    return written


def big_timing(repeat: int, methods, log=print) -> dict:
    """Seconds (median of ``repeat``) of each demosaic of a 24-megapixel DNG."""
    import tempfile

    from benchmarks.white_balance import bench_arguments, write_bench_dng

    with tempfile.TemporaryDirectory() as tmp:
        args = bench_arguments(__doc__, [])
        path = write_bench_dng(tmp, args)
        with open(path, "rb") as f:
            data = f.read()
    times = {m: [] for m in methods if m != "menon2007"}
    for i in range(repeat):
        for m in times:                       # interleaved: the machine's drift hits all alike
            _, secs = product_demosaic(data, m)
            times[m].append(secs)
            log(f"  24 MP {m}: {secs:.2f} s", flush=True)
    return {m: statistics.median(t) for m, t in times.items()}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--images", help="a folder holding scikit-image's photographs (when skimage is not installed)")
    ap.add_argument("--crops", help="write enlarged crops as PNG into this folder")
    ap.add_argument("--big", action="store_true", help="also time each demosaic on a 24-megapixel DNG")
    ap.add_argument("--repeat", type=int, default=3, help="runs of the 24-megapixel timing (median)")
    ap.add_argument("--methods", help="comma-separated subset (default: all)")
    args = ap.parse_args(argv)

    paths = photo_paths(args.images)
    if not paths:
        sys.exit("no test photographs found: install scikit-image or pass --images DIR")
    methods = list(PRODUCT) + list(LIBRAW) + ["menon2007"]
    if args.methods:
        methods = [m for m in args.methods.split(",") if m]
    try:
        import numba  # noqa: F401
        kernel = "numba"
    except ImportError:
        kernel = "numpy (numba not installed: RCD's time is that of its vectorised numpy steps)"
    print(f"load average {os.getloadavg()[0]:.1f} {os.getloadavg()[1]:.1f}; RCD kernel: {kernel}")
    print("images: " + ", ".join(paths))
    images = [(os.path.basename(p), load_linear(p)) for p in paths]
    crops = {} if args.crops else None
    warm = dng_bytes(reference_u16(images[0][1][:64, :64]), "RGGB")
    for m in methods:                    # libraries loaded, RCD's compiled loops read from numba's cache
        if m != "menon2007":
            product_demosaic(warm, m)
    res = score(images, methods, crops=crops)
    print(f"\n{len(images)} photographs x 4 Bayer phases; 3x3 matrix fitted per result; {BORDER}-pixel border left out")
    print(f"{'demosaic':12s} {'CPSNR dB':>9s} {'min':>6s} {'phase spread':>12s} {'CIEDE2000':>9s} {'ms/MP':>7s}")
    best_libraw = max((statistics.mean(res[m]["cpsnr"]) for m in LIBRAW if res.get(m, {}).get("cpsnr")),
                      default=None)
    for m in methods:
        r = res[m]
        if not r["cpsnr"]:
            print(f"{m:12s} (not installed)")
            continue
        spread = max(max(v) - min(v) for v in r["by_image"].values())
        print(f"{m:12s} {statistics.mean(r['cpsnr']):9.2f} {min(r['cpsnr']):6.2f} {spread:12.2f} "
              f"{statistics.mean(r['de']):9.3f} {1e3 * r['seconds'] / r['mp']:7.1f}")
    if best_libraw is not None and res.get("rcd", {}).get("cpsnr"):
        d = statistics.mean(res["rcd"]["cpsnr"]) - best_libraw
        print(f"\ndefault (rcd) minus LibRaw's best: {d:+.2f} dB (target >= -1.0)")
    print("(phase spread: the largest difference between the four phases' CPSNR on one photograph)")
    if crops is not None:
        refs = {name: reference_u16(lin) / 65535.0 for name, lin in images}
        shown = [m for m in ("fast", "rcd", "AHD", "DHT", "AAHD", "menon2007") if m in methods]
        for p in write_crops(crops, refs, shown, args.crops):
            print(f"crop: {p} (reference, {', '.join(shown)})")
    if args.big:
        print(f"\n24-megapixel DNG, demosaic seconds (median of {args.repeat}); load average "
              f"{os.getloadavg()[0]:.1f}")
        t = big_timing(args.repeat, methods)
        for m, s in t.items():
            print(f"{m:12s} {s:7.2f} s {1e3 * s / 24:7.1f} ms/MP")
        print(f"load average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
