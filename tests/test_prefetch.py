"""The demosaic started on a thread while the light is estimated
(service.pipeline.prefetch_full_linear, issue 19): the same image as
without it, taken once, and never left running after a failure."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from service import pipeline
from service.errors import ServiceError
from service.settings import get_settings
from testing.dngwriter import scene_dng


@pytest.fixture(scope="module")
def dng(tmp_path_factory):
    p = tmp_path_factory.mktemp("prefetch") / "a.dng"
    scene_dng(p, "Nikon 5100 (NPL)", "D4000", 96, 144, seed=3, grid=(4, 6))
    return p.read_bytes()


def test_prefetched_render_equals_the_plain_one(dng):
    s = get_settings()
    dec0, run0 = pipeline.analyze(dng, "a.dng", s)
    plain, _, _ = pipeline.render_full(dec0, run0, "D65", "sRGB", 8)
    dec1, run1 = pipeline.analyze(dng, "a.dng", s, prefetch=True)
    assert dec1.__dict__.get("_full_future") is not None
    first, _, _ = pipeline.render_full(dec1, run1, "D65", "sRGB", 8)
    assert "_full_future" not in dec1.__dict__                   # taken once (it is corrected in place)
    again, _, _ = pipeline.render_full(dec1, run1, "D65", "sRGB", 8)
    np.testing.assert_array_equal(first, plain)
    np.testing.assert_array_equal(again, plain)


def _demosaic_threads():
    return [t for t in threading.enumerate() if t.name == "wandell-demosaic" and t.is_alive()]


def test_a_failed_estimate_waits_for_the_demosaic(dng):
    with pytest.raises(Exception, match="no such camera"):
        pipeline.analyze(dng, "a.dng", get_settings(), camera="no such camera", prefetch=True)
    for _ in range(100):                 # the thread has set its result; it ends right after
        if not _demosaic_threads():
            break
        time.sleep(0.01)
    assert not _demosaic_threads()


def test_a_failed_render_drops_the_prefetch(dng):
    dec, run = pipeline.analyze(dng, "a.dng", get_settings(), prefetch=True)
    with pytest.raises(ServiceError):
        pipeline.render_full(dec, run, "D65", "no such output", 8)
    assert "_full_future" not in dec.__dict__
