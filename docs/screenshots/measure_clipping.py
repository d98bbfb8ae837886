import sys, numpy as np
sys.path.insert(0, ".")
from pathlib import Path
from PIL import Image
import tifffile, rawpy
from tests.test_dng_render import reference_rendering, _decode
from service import metadata
P = Path("/work/shared/data/raw/Blackmagic.dng")
def chrom(x):
    m = x.reshape(-1, 3).mean(0); return (m / m.sum()).round(3).tolist()
d = _decode(P); est = d.estimation.astype(np.float64); top = 150
be = metadata.color_profile(d).baseline_exposure
print("BaselineExposure", be, "estimation max", est[:top].max())
ref_be = reference_rendering(P, est[:top])
print("reference as specified (x2^BE, clipped): clouds", chrom(ref_be), "clipped fraction (any ch =1):", round(float((ref_be >= 0.999).any(-1).mean()), 3))
ref0 = reference_rendering(P, est[:top] * 2.0 ** -be)
print("reference without BaselineExposure (no clip at 1):", chrom(ref0), "max", ref0.max().round(3), "neg-clipped frac", round(float((ref0 <= 0).any(-1).mean()), 3))
ours = tifffile.imread("/tmp/meas/bm_corrected_linear.tif")[:600].astype(float) / 65535
print("service corrected linear top600: clipped fraction", round(float((ours >= 0.999).any(-1).mean()), 3))
with rawpy.imread(str(P)) as raw:
    rpl = raw.postprocess(use_camera_wb=True, gamma=(1, 1), no_auto_bright=True, output_bps=16)[:600].astype(float) / 65535
print("rawpy linear top600 clipped fraction", round(float((rpl >= 0.999).any(-1).mean()), 3), "max", rpl.max())
