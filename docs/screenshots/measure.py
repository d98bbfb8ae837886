import io, sys, json
import numpy as np
sys.path.insert(0, ".")
from pathlib import Path
from PIL import Image
import tifffile, rawpy
from tests.test_dng_render import reference_rendering, _decode, _median_luminance

P = Path("/work/shared/data/raw/Blackmagic.dng")
def lin(s8):
    x = np.asarray(s8, float) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
def chrom(rgb_lin):
    m = rgb_lin.reshape(-1, 3).mean(0); return m / m.sum()
def stops(a, b): return np.log2(_median_luminance(a) / _median_luminance(b))
R = {}
def rep(name, img8=None, linimg=None, top=600):
    d = {}
    if img8 is not None:
        d["shape"] = img8.shape
        d["mean_rgb8"] = img8.reshape(-1, 3).mean(0).round(1).tolist()
        d["median_lum_lin"] = round(_median_luminance(img8), 4)
        d["clouds_rgb_from8bit"] = chrom(lin(img8[:top])).round(3).tolist()
    if linimg is not None:
        d["clouds_rgb_linear"] = chrom(linimg[:top]).round(3).tolist()
    R[name] = d; print(name, json.dumps(d, default=str), flush=True)

ours = np.asarray(Image.open("/tmp/meas/bm_corrected.jpg").convert("RGB"))
ours_lin = tifffile.imread("/tmp/meas/bm_corrected_linear.tif").astype(float) / 65535
rep("service corrected (CLI, auto, D65, sRGB JPEG / linear-sRGB TIFF)", ours, ours_lin)

# service's as-shot rendering via the REST API in-process
from fastapi.testclient import TestClient
from service.app import app
c = TestClient(app, base_url="http://127.0.0.1")
r = c.post("/v1/white-balance", files={"file": (P.name, P.read_bytes())}, data={"white": "as-shot", "format": "jpeg"})
print("as-shot", r.status_code, r.headers.get("content-type"))
if r.status_code == 200:
    asshot = np.asarray(Image.open(io.BytesIO(r.content)).convert("RGB"))
    r2 = c.post("/v1/white-balance", files={"file": (P.name, P.read_bytes())},
                data={"white": "as-shot", "format": "tiff", "output": "linear-sRGB"})
    asshot_lin = tifffile.imread(io.BytesIO(r2.content)).astype(float) / 65535 if r2.status_code == 200 else None
    rep("service as-shot (REST white=as-shot, JPEG / linear TIFF)", asshot, asshot_lin)
else:
    print(r.text[:500])

with rawpy.imread(str(P)) as raw:
    rp = raw.postprocess(use_camera_wb=True)
    rpl = raw.postprocess(use_camera_wb=True, gamma=(1, 1), no_auto_bright=True, output_bps=16).astype(float) / 65535
rep("rawpy postprocess(use_camera_wb=True) 8-bit / linear 16-bit", rp, rpl)

d = _decode(P)
est = d.estimation.astype(np.float64)
H = rp.shape[0]
top = int(round(600 * est.shape[0] / H))
print("estimation", est.shape, "top rows", top)
ref = reference_rendering(P, est[:top])
R["dng reference (top)"] = {"clouds_rgb_linear": chrom(ref).round(3).tolist(), "rows": top}
print("DNG reference", R["dng reference (top)"])
# glint pixels in the corrected JPEG at clipped places
print("stops ours vs rawpy:", round(stops(ours, rp), 3))
if r.status_code == 200: print("stops as-shot vs rawpy:", round(stops(asshot, rp), 3))
