"""The estimation image's binning of the Bayer mosaic
(service.decode.raw._bin_bayer_area, issue 19: both sites of a mosaic row in
one OpenCV call): the numbers of the plane-by-plane definition exactly."""

from __future__ import annotations

import numpy as np
import pytest

from service.decode.raw import _bin_bayer_area
from service.decode.raw import _bin_bayer_planes as _plane_by_plane   # the definition: each plane gathered


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
