"""The load command's quick variant against a real uvicorn server on
loopback (issue 6): 10 concurrent white-balance requests, small images."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from benchmarks import load
from recovery import angular_error


@pytest.fixture(scope="module")
def server():
    proc, base = load.start_server()
    try:
        yield proc, base
    finally:
        proc.terminate()
        proc.wait(10)


@pytest.fixture(scope="module")
def inputs():
    # 64 x 96: above LibRaw's 22-pixel minimum, milliseconds per request
    return load.make_inputs(10, 64, 96)


def test_inputs_have_different_lights(inputs):
    assert len({i.light for i in inputs}) == len(inputs)
    assert len({i.data for i in inputs}) == len(inputs)


def test_ten_concurrent_white_balance_requests(server, inputs):
    """Every request a 200 whose estimate is its own file's (equal to the
    file's serial reference, and within 3 degrees of its true light: the
    light posterior is within 0.6 degrees on these ColorChecker scenes for
    every light used, measured), with a 64 x 96 x 3 16-bit TIFF body."""
    proc, base = server
    rep = load.run_load(base, inputs, pid=proc.pid, timeout=120)
    print(rep.summary())
    assert rep.failures == []
    assert rep.ok == rep.n == 10
    assert len(rep.latencies_s) == 10 and rep.throughput > 0
    assert rep.peak_rss_mb is not None and rep.peak_rss_mb >= rep.rss_before_mb > 0
    assert max(rep.angles_deg) < 3.0
    assert proc.poll() is None            # still serving


def test_the_checks_catch_answers_that_belong_to_another_file(server, inputs):
    """Swap the recorded truth of two files with far-apart lights (CIE A and
    a 6500 K daylight): the run must report both as failures, so a server
    answering with another request's estimate would not pass."""
    proc, base = server
    a = next(i for i in inputs if i.light == "A")
    d = next(i for i in inputs if i.light == "D65")
    swapped = [dataclasses.replace(a, light_rgb=d.light_rgb), dataclasses.replace(d, light_rgb=a.light_rgb)]
    assert float(angular_error(a.light_rgb, d.light_rgb)) > 10
    rep = load.run_load(base, swapped, timeout=120)
    assert rep.ok == 0 and len(rep.failures) == 2
    assert all("true light" in f for f in rep.failures)


def test_only_loopback_targets_are_accepted():
    assert load._loopback("http://127.0.0.1:8000") and load._loopback("http://localhost:1")
    assert not load._loopback("http://10.0.0.1:8000")
    with pytest.raises(SystemExit):
        load.main(["--url", "http://192.168.1.5:8000"])


def test_angle_is_zero_for_parallel_vectors_and_ninety_for_orthogonal():
    assert float(angular_error([1, 2, 3], [2, 4, 6])) == pytest.approx(0.0, abs=1e-6)
    assert float(angular_error([1, 0, 0], [0, 1, 0])) == pytest.approx(90.0)
    assert np.isfinite(float(angular_error([1, 1, 1], [1, 1, 1])))
