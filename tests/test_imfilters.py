"""recovery.imfilters reproduces scipy.ndimage's filters (the estimators
moved off scipy.ndimage to keep it out of the CLI's start-up).

Tolerance: both compute the same sums of products of the input with the
same kernel weights, in another order (OpenCV's separable pass against
scipy's axis by axis), so they may differ by the rounding of those sums:
at most about (number of adds) x 2^-53 x max|input| x (the kernels' absolute
sums); 1e-13 of max|input| x |k_y|_1 x |k_x|_1 bounds that with margin for
every kernel here (at most 2 x 27 adds). Where the output cancels (a
derivative along a 2-pixel axis is ~1e-6) this is what the output's error
is measured against, not the output's own size. The binary erosion is exact.
"""

import numpy as np
import pytest
from scipy import ndimage

from recovery import estimators, imfilters, learned


RNG = np.random.default_rng(20261201)
SHAPES = [(64, 64), (5, 7), (2, 9), (301, 200)]


def _close(ours, theirs, a, ky=np.ones(1), kx=np.ones(1)):
    scale = float(np.abs(a).max()) * float(np.abs(ky).sum()) * float(np.abs(kx).sum())
    assert float(np.abs(ours - theirs).max()) <= 1e-13 * scale


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("sigma", [0.5, 1.0, 2.0, 3.3])
@pytest.mark.parametrize("order", [(0, 0), (0, 1), (1, 0), (0, 2), (2, 0), (1, 1)])
@pytest.mark.parametrize("mode", ["nearest", "reflect"])
def test_gaussian_filter_is_scipys(shape, sigma, order, mode):
    a = RNG.random(shape)
    _close(imfilters.gaussian_filter(a, sigma, order, mode), ndimage.gaussian_filter(a, sigma, order=order, mode=mode),
           a, imfilters.gaussian_kernel1d(sigma, order[0]), imfilters.gaussian_kernel1d(sigma, order[1]))


@pytest.mark.parametrize("shape", SHAPES)
def test_laplace_is_scipys(shape):
    a = RNG.normal(size=shape)
    _close(imfilters.laplace(a), ndimage.laplace(a), a, np.full(3, 2.0))


@pytest.mark.parametrize("shape", SHAPES)
@pytest.mark.parametrize("iterations", [1, 2, 5])
def test_binary_erosion_is_scipys(shape, iterations):
    m = RNG.random(shape) > 0.15
    assert np.array_equal(imfilters.binary_erosion(m, iterations),
                          ndimage.binary_erosion(m, iterations=iterations, border_value=1))


def test_kernels_are_normalised_and_their_moments_are_the_derivatives():
    # sum of the smoothing kernel is 1; the first-derivative kernel applied
    # to x gives 1 (its first moment), the second's second moment is 2
    x = np.arange(-8, 9, dtype=float)
    k0, k1, k2 = (imfilters.gaussian_kernel1d(2.0, o)[::-1] for o in (0, 1, 2))
    assert abs(k0.sum() - 1) < 1e-15
    # convolution kernels: sum_k k[k] f(-x_k) -> derivative of f at 0
    assert abs(np.dot(k1, -x) - 1.0) < 0.02            # a sampled Gaussian's derivative, not exact
    assert abs(np.dot(k2, x ** 2) - 2.0) < 0.05
    with pytest.raises(ValueError):
        imfilters.gaussian_kernel1d(0.0)


def _scipy_gray_edge(img, mask, p, sigma, order):
    """gray_edge as it was written on scipy.ndimage."""
    img = img / img.max()
    mags = np.empty_like(img)
    for k in range(3):
        if order == 1:
            gx = ndimage.gaussian_filter(img[..., k], sigma, order=(0, 1), mode="nearest")
            gy = ndimage.gaussian_filter(img[..., k], sigma, order=(1, 0), mode="nearest")
            mags[..., k] = np.hypot(gx, gy)
        else:
            gxx = ndimage.gaussian_filter(img[..., k], sigma, order=(0, 2), mode="nearest")
            gyy = ndimage.gaussian_filter(img[..., k], sigma, order=(2, 0), mode="nearest")
            gxy = ndimage.gaussian_filter(img[..., k], sigma, order=(1, 1), mode="nearest")
            mags[..., k] = np.sqrt(gxx ** 2 + gyy ** 2 + 2 * gxy ** 2)
    m = ndimage.binary_erosion(mask, iterations=max(1, int(np.ceil(2 * sigma))), border_value=1)
    px = mags[m]
    e = (px ** p).mean(axis=0) ** (1 / p)
    return e / e.sum()


@pytest.mark.parametrize("order,p,sigma", [(1, 1, 1), (1, 6, 1), (1, 6, 2), (2, 6, 1)])
def test_gray_edge_estimates_are_unchanged(order, p, sigma):
    img = RNG.random((64, 64, 3)) * np.array([0.5, 0.8, 0.3]) + 0.01
    mask = RNG.random((64, 64)) > 0.1
    ours = estimators.gray_edge(img, mask, p, sigma, order)
    np.testing.assert_allclose(ours / ours.sum(), _scipy_gray_edge(img, mask, p, sigma, order), rtol=1e-12)


def test_gray_pixels_estimate_is_unchanged():
    img = RNG.random((64, 64, 3)) + 0.05
    ok = RNG.random((64, 64)) > 0.1
    lg = np.log(np.clip(img, 1e-4, None))
    c = np.stack([np.abs(ndimage.laplace(ndimage.gaussian_filter(lg[..., k], 0.5))) for k in range(3)], -1)
    mm = ok & np.all(c > 1e-3, axis=-1)
    cc = c[mm]
    gi = np.std(cc / cc.sum(axis=1, keepdims=True), axis=1)
    k = max(1, int(0.05 * gi.size))
    theirs = img[mm][np.argsort(gi, kind="stable")[:k]].mean(axis=0)
    np.testing.assert_allclose(learned._gray_pixels(img, ok, 0.05), theirs, rtol=1e-12)


@pytest.mark.parametrize("order,mode", [((0, 0), "reflect"), ((0, 1), "nearest"), ((1, 1), "nearest"),
                                        ((2, 0), "nearest")])
def test_three_channels_in_one_call_are_each_channel_alone(order, mode):
    img = RNG.random((40, 33, 3))
    together = imfilters.gaussian_filter(img, 1.5, order, mode)
    for k in range(3):
        np.testing.assert_allclose(together[..., k], imfilters.gaussian_filter(img[..., k], 1.5, order, mode),
                                   rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="2-D array"):
        imfilters.gaussian_filter(RNG.random((4, 4, 5)), 1.0)


def _features_one_by_one(cells, ok):
    """The 19 classical estimates of recovery.learned.FEATURE_NAMES, each
    computed alone by recovery.estimators (what features() shares work
    between)."""
    img = np.clip(cells, 1e-6, None)
    px = img[ok]
    est = [estimators.gray_world(px), *(estimators.shades_of_gray(px, None, p) for p in (2, 4, 8, 16)),
           estimators.white_patch(px), np.percentile(px, 99, axis=0), np.percentile(px, 95, axis=0),
           *(estimators.gray_edge(img, ok, p, s, o) for p, s, o in ((1, 1, 1), (6, 1, 1), (6, 2, 1), (6, 1, 2))),
           *(estimators.bright_pixels(px, None, q) for q in (0.005, 0.01, 0.02, 0.05, 0.1)),
           learned._gray_pixels(img, ok, 0.05), learned._gray_pixels(img, ok, 0.2)]
    return learned.rgb_to_uv(np.array(est))


@pytest.mark.parametrize("shape", [(64, 64), (32, 32), (23, 41)])
def test_features_share_work_without_changing_an_estimate(shape):
    # the work shared between the 19 estimates (one filtering per sigma and
    # order, one ordering of the brightness, one contrast map) changes only
    # rounding: 1e-12 in log-chroma is 1e-10 degrees
    img = RNG.random((*shape, 3)) * np.array([0.6, 0.9, 0.4]) + 0.02
    ok = RNG.random(shape) > 0.15
    np.testing.assert_allclose(learned.features(img, ok), _features_one_by_one(img, ok), rtol=0, atol=1e-12)


def test_windows_read_the_whole_images_maps_and_give_each_windows_features():
    # window_features (the light map's nine windows at once) against features() of each window
    # reading its part of the whole image's filtered maps: the same estimates, to rounding (the
    # Minkowski sums are taken over the whole image's maximum instead of the window's)
    img = RNG.random((64, 64, 3)) * np.array([0.6, 0.9, 0.4]) + 0.02
    ok = RNG.random((64, 64)) > 0.15
    ok[:20, :20] = False                            # a window with few usable cells
    img[32:, 32:] = [0.3, 0.3, 0.3]                 # and one of a single colour: refused
    wins = [(slice(r, r + 32), slice(c, c + 32)) for r in (0, 16, 32) for c in (0, 16, 32)]
    feats, valid = learned.window_features(img, ok, wins)
    maps = learned.shared_maps(img, ok)
    for k, w in enumerate(wins):
        try:
            ref = learned.features(img[w], ok[w], learned.window_maps(maps, w))
        except learned.InsufficientSurfaceVariation:
            assert not valid[k] and np.all(np.isnan(feats[k]))
            continue
        assert valid[k]
        np.testing.assert_allclose(feats[k], ref, rtol=0, atol=1e-12)
    assert not valid[8] and valid.sum() >= 6
