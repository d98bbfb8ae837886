"""The fused correction (service.correction, issue 19): chunks where the
highlight blend and the clip at 1 change nothing go through one transform
by M instead of the step-by-step path; the pixels agree up to float32
rounding (one code of the 16-bit linear values before the table)."""

from __future__ import annotations

import numpy as np
import pytest

from service import correction

M = np.array([[1.9, -0.7, -0.2], [-0.3, 1.6, -0.3], [0.05, -0.5, 1.45]])
NEUTRAL = [1.0, 0.966, 0.447]          # a tungsten light: blue weak, its white balance reaches 1 early


def _image(rng, h=96, w=200):
    """Rows of chunks of every kind: dark and mid-tone (plain), a bright blue
    patch whose white balance clips (blue above 0.447 of full scale), a
    clipped highlight, a channel at saturation."""
    img = (rng.uniform(0.02, 0.4, size=(h, w, 3)) * 65535).astype(np.uint16)
    img[20:28, 10:30] = [12000, 15000, 40000]        # blue / 0.447 > 1: clipped by the white balance
    img[50:54, 100:120] = 65535                       # clipped highlight
    img[70:72, 150:160, 1] = 64000                    # one channel near clipping
    return img


def _both(img, bits, encoding, curve, rows=8, **kw):
    out = {}
    for fused in (False, True):
        correction.FUSED = fused
        try:
            out[fused] = correction.apply_matrix_inplace(img.copy(), M, encoding, bits, rows_per_chunk=rows,
                                                         threads=1, neutral=NEUTRAL, curve=curve, **kw)
        finally:
            correction.FUSED = True
    return out[False].astype(int), out[True].astype(int)


@pytest.mark.parametrize("bits,encoding,curve,tol", [(16, None, None, 1), (8, "sRGB", "libraw", 1),
                                                     (8, "sRGB", None, 1)])
def test_fused_chunks_give_the_step_by_step_pixels(bits, encoding, curve, tol, monkeypatch):
    img = _image(np.random.default_rng(3))
    taken = []
    plain = correction._plain_chunk
    monkeypatch.setattr(correction, "_plain_chunk", lambda *a: taken.append(plain(*a)) or taken[-1])
    old, new = _both(img, bits, encoding, curve)
    assert any(taken) and not all(taken)        # both paths ran
    assert np.abs(new - old).max() <= tol
    assert np.count_nonzero(new != old) <= 0.05 * old.size      # float32 rounding near a half code


def test_a_chunk_with_a_highlight_or_a_clipped_white_balance_is_not_fused():
    hi = (60000.0, 60000.0, 29000.0)
    mask = np.empty((2, 4), np.uint8)
    base = np.full((2, 4, 3), 1000, np.uint16)
    assert correction._plain_chunk(base, hi, mask)
    for ch, v in ((0, 60001), (2, 29001)):
        x = base.copy()
        x[1, 3, ch] = v
        assert not correction._plain_chunk(x, hi, mask)


def test_a_shoulder_keeps_the_step_by_step_path(monkeypatch):
    called = []
    monkeypatch.setattr(correction, "_plain_chunk", lambda *a: called.append(1) or True)
    img = _image(np.random.default_rng(4))
    correction.apply_matrix_inplace(img, M, "sRGB", 8, rows_per_chunk=8, threads=1, neutral=NEUTRAL,
                                    shoulder={"luminance": (0.2126, 0.7152, 0.0722), "knee": 0.75, "peak": 2.0})
    assert not called


@pytest.mark.parametrize("threads,rows", [(1, 8), (2, 1), (2, 7), (4, 3)])
def test_8bit_output_in_the_input_memory_is_the_same_image(threads, rows):
    # reuse_input: the 8-bit output written into the first half of the 16-bit
    # input's memory, each chunk waiting for the chunks it overwrites to have
    # been read: the same pixels as into a new array, whatever the threads
    img = _image(np.random.default_rng(6), h=203, w=61)
    ref = correction.apply_matrix_inplace(img.copy(), M, "sRGB", 8, rows_per_chunk=rows, threads=threads,
                                          neutral=NEUTRAL, curve="libraw")
    for _ in range(3):
        x = img.copy()
        out = correction.apply_matrix_inplace(x, M, "sRGB", 8, rows_per_chunk=rows, threads=threads,
                                              neutral=NEUTRAL, curve="libraw", reuse_input=True)
        assert np.shares_memory(out, x) and out.dtype == np.uint8
        assert np.array_equal(out, ref)
    crop = img.copy()[3:200, 2:60]           # not contiguous: a new array
    ref = correction.apply_matrix_inplace(np.ascontiguousarray(crop), M, "sRGB", 8, rows_per_chunk=rows,
                                          threads=threads, neutral=NEUTRAL, curve="libraw")
    out = correction.apply_matrix_inplace(crop, M, "sRGB", 8, rows_per_chunk=rows, threads=threads,
                                          neutral=NEUTRAL, curve="libraw", reuse_input=True)
    assert not np.shares_memory(out, crop) and np.array_equal(out, ref)
