"""The estimation image's binning of the Bayer mosaic
(service.decode.raw._bin_bayer_area, issue 19: both sites of a mosaic row in
one OpenCV call): the numbers of the plane-by-plane definition exactly."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from service.decode.raw import SATURATION_FRACTION, _bin_bayer_area


def _plane_by_plane(img, sites, blacks, white, f):
    """Each CFA plane gathered, block-averaged (INTER_AREA), scaled, and its
    saturation (any site at or above the threshold) per block."""
    H, W = img.shape
    hh, ww = (H // 2) // f, (W // 2) // f
    est = np.zeros((hh, ww, 3), np.float32)
    sat = np.zeros((hh, ww), bool)
    for dy, dx, idx, ch in sites:
        b = float(blacks[idx])
        plane = np.ascontiguousarray(img[dy:2 * hh * f:2, dx:2 * ww * f:2])
        mean = cv2.resize(plane, (ww, hh), interpolation=cv2.INTER_AREA).astype(np.float32)
        thr = math.ceil(b + SATURATION_FRACTION * (white - b))
        hit = cv2.resize(cv2.compare(plane, min(thr, 65535), cv2.CMP_GE), (ww, hh), interpolation=cv2.INTER_AREA)
        sat |= hit > 0
        mean -= np.float32(b)
        mean *= np.float32(1.0 / (white - b))
        est[..., ch] += mean * np.float32(0.5 if ch == 1 else 1.0)
    return est, sat


@pytest.mark.parametrize("pattern", [[(0, 0, 0, 0), (0, 1, 1, 1), (1, 0, 3, 1), (1, 1, 2, 2)],
                                     [(0, 0, 1, 1), (0, 1, 2, 2), (1, 0, 0, 0), (1, 1, 3, 1)]])
@pytest.mark.parametrize("shape,f", [((400, 604), 3), ((101, 203), 2), ((64, 64), 1), ((333, 517), 5), ((240, 330), 4),
                                     ((250, 370), 6)])
def test_binning_equals_the_plane_by_plane_definition(pattern, shape, f):
    rng = np.random.default_rng(shape[0] * f)
    white = 16383.0
    img = rng.integers(0, 16384, shape, dtype=np.uint16)
    img[10:30, 20:60] = 16383                                 # clipped blocks
    img[40:44, 7] = 16300                                     # one site near clipping
    blacks = [512.0, 500.0, 530.0, 515.0]
    est, sat = _bin_bayer_area(img, pattern, blacks, white, f)
    ref_est, ref_sat = _plane_by_plane(img, pattern, blacks, white, f)
    np.testing.assert_array_equal(est, ref_est)
    np.testing.assert_array_equal(sat, ref_sat)
    assert sat.any() and not sat.all()
