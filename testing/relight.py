"""A real camera file relit by a second light at its raw mosaic: a two-light
photograph at full resolution whose lights are known relative to the first.

The raw digital numbers above black are multiplied, site by site, by
``a(x) + (1 - a(x)) g_c``: ``a`` a soft mask (1 keeps the photograph's own
light, 0 gives the second light), ``g = L2 / L1`` per channel (green 1), ``L1``
the photograph's light and ``L2`` the second light, both in the camera's RGB.
The sensor is linear, so this is the photograph as the same surfaces would
have been recorded under the mixed light ``L1 (a + (1 - a) g)``, up to clipping
at the white level (Wandell 1985, eq. 12: the response is linear in the
light). Used by the tests and the light-map figure of ``docs/mixed_light.md``.
"""

from __future__ import annotations

import io

import numpy as np

from .dngwriter import write_dng

__all__ = ["raw_mosaic", "soft_half", "relit_dng"]

#: CIE illuminant A (tungsten), XYZ of its white, Y = 1
XYZ_A = np.array([1.09850, 1.0, 0.35585])


def raw_mosaic(data: bytes) -> dict:
    """The visible raw mosaic of a Bayer DNG through LibRaw (rawpy), its
    black and white levels, 2x2 pattern (``"RGGB"`` ...) and the XYZ -> camera
    matrix for D65 read from its tags (ColorMatrix1 or 2, whichever is
    calibrated for D65, CalibrationIlluminant 21)."""
    import rawpy
    import tifffile

    with rawpy.imread(io.BytesIO(data)) as raw:
        cfa = np.array(raw.raw_image_visible, np.uint16)
        black = np.asarray(raw.black_level_per_channel, float)
        white = int(raw.white_level)
        pat = np.asarray(raw.raw_pattern)
        desc = raw.color_desc.decode()
    letters = "".join(desc[int(i)] for i in pat.ravel())
    tags = tifffile.TiffFile(io.BytesIO(data)).pages[0].tags
    cm = None
    for k in ("1", "2"):
        ill = tags.get(f"CalibrationIlluminant{k}")
        mat = tags.get(f"ColorMatrix{k}")
        if ill is not None and mat is not None and int(ill.value) == 21:
            v = np.asarray(mat.value, float)
            cm = (v[0::2] / v[1::2]).reshape(3, 3) if v.size == 18 else v.reshape(3, 3)
    if cm is None:
        raise ValueError("no ColorMatrix calibrated for D65 in this DNG")
    if len(set(black.tolist())) != 1:
        raise ValueError("per-site black levels are not handled here")
    return {"cfa": cfa, "black": float(black[0]), "white": white, "pattern": letters, "color_matrix": cm}


def soft_half(shape, edge: float = 0.5, width: float = 0.08) -> np.ndarray:
    """A mask that is 0 on the left and 1 on the right of the frame, a
    logistic edge at ``edge`` of the width, ``width`` (of the frame's width)
    its scale."""
    h, w = shape
    x = (np.arange(w) + 0.5) / w
    return np.broadcast_to(1.0 / (1.0 + np.exp(-(x - edge) / width)), (h, w))


def relit_dng(raw: dict, first_light_rgb, second_light_xyz=XYZ_A, mask=None) -> tuple[bytes, np.ndarray]:
    """The DNG (same levels, pattern and D65 colour matrix) of ``raw``
    (:func:`raw_mosaic`) relit by a second light across ``mask`` (default
    :func:`soft_half`), and ``g``, the second light over the first per camera
    channel (green 1). ``first_light_rgb``: the photograph's own light in the
    camera's RGB."""
    cfa, black, white = raw["cfa"], raw["black"], raw["white"]
    l1 = np.asarray(first_light_rgb, float)
    l2 = raw["color_matrix"] @ np.asarray(second_light_xyz, float)
    g = (l2 / l2[1]) / (l1 / l1[1])
    a = soft_half(cfa.shape) if mask is None else np.asarray(mask, float)
    chan = {"R": 0, "G": 1, "B": 2}
    site = np.empty(cfa.shape, int)
    for k, ch in enumerate(raw["pattern"]):
        site[k // 2::2, k % 2::2] = chan[ch]
    f = a + (1.0 - a) * g[site]
    out = np.clip(black + (cfa.astype(float) - black) * f, 0, white).astype(np.uint16)
    return write_raw(raw, out), g


def write_raw(raw: dict, cfa: np.ndarray) -> bytes:
    """``cfa`` written as a DNG with ``raw``'s levels, pattern and matrix."""
    buf = io.BytesIO()
    write_dng(buf, cfa, pattern=raw["pattern"], black_level=raw["black"], white_level=raw["white"],
              color_matrix1=raw["color_matrix"], calibration_illuminant1=21, model="relit")
    return buf.getvalue()
