"""Every decode is a function of the file alone (issue 10, item 1).

LibRaw decodes into a buffer it does not clear: when strips or tiles are
missing, outside the file or damaged, part of the image is whatever the
previous decode left there, i.e. another user's photo. The mutations of a
real CinemaDNG in :func:`benchmarks.fuzz.dng_mutations` cover every class that
leaked (truncations, zeroed tails, destroyed SOI markers, damaged JPEG frame
and table headers, tile geometry, tile offsets and counts, IFD bytes). Each
is decoded right after two different images; the two results must be the
same image or the same 4xx refusal, and every file whose strips or tiles are
damaged must be refused.

The real file is ``shared/data/raw/Blackmagic.dng``: without it these tests
skip, unless ``CI`` is set (then they fail).
"""

from __future__ import annotations

import io

import numpy as np
import pytest

from benchmarks import fuzz
from service.errors import ServiceError
from service.rawio import decode_upload

from .conftest import shared_file

BIG = 10**8


@pytest.fixture(scope="module")
def blackmagic() -> bytes:
    return shared_file("data/raw/Blackmagic.dng").read_bytes()


@pytest.fixture(scope="module")
def victims(blackmagic):
    bo, _, ent = fuzz.ifd_entries(blackmagic)
    (w,), (h,) = fuzz._longs(blackmagic, bo, ent[256]), fuzz._longs(blackmagic, bo, ent[257])
    return fuzz.victim_dngs(h, w)


def _leave_in_memory(victim: bytes) -> None:
    """Decode ``victim`` with LibRaw and free it: its pixels stay in the
    freed memory the next decode may be given."""
    import rawpy

    with rawpy.imread(io.BytesIO(victim)) as raw:
        assert raw.raw_image_visible.any()


def _outcome(data: bytes):
    try:
        d = decode_upload(data, "real.dng", max_pixels=BIG)
    except ServiceError as e:
        return (e.status, e.code)
    return d.estimation


def _same(a, b) -> bool:
    if isinstance(a, tuple) or isinstance(b, tuple):
        return a == b
    return a.shape == b.shape and np.array_equal(a, b)


def test_victims_leak_through_a_raw_decode_of_the_496_byte_header(blackmagic, victims):
    """The hole itself, at LibRaw's level: the 496-byte header decoded by
    LibRaw directly (no verification) after each victim gives that victim's
    pixels, so the victims can reveal a leak."""
    import rawpy

    head = blackmagic[:496]
    got = []
    for v in victims:
        _leave_in_memory(v)
        with rawpy.imread(io.BytesIO(head)) as raw:
            got.append(raw.raw_image_visible.copy())
    assert not np.array_equal(got[0], got[1])


def test_every_decode_is_a_function_of_the_file_alone(blackmagic, victims):
    muts = fuzz.dng_mutations(blackmagic)
    assert {m.kind for m in muts} == set(fuzz.DNG_KINDS)
    original = _outcome(blackmagic)
    assert not isinstance(original, tuple), original
    for m in muts:
        results = []
        for v in victims:
            _leave_in_memory(v)
            results.append(_outcome(m.data))
        assert _same(*results), f"{m.kind} ({m.what}): decode depends on the previous image"
        if m.kind == "dng-valid":
            assert not isinstance(results[0], tuple), f"{m.what}: refused {results[0]}"
            if "cut" in m.what:      # bytes after the last tile belong to nothing: the same image
                assert _same(results[0], original), m.what
        elif m.kind not in ("dng-ifd-flip", "dng-data"):   # these may leave the image decodable
            assert isinstance(results[0], tuple) and 400 <= results[0][0] < 500, \
                f"{m.kind} ({m.what}) was decoded, not refused"


@pytest.mark.parametrize("short", range(1, 16))
def test_files_short_of_their_last_tile_are_corrupt(blackmagic, short):
    bo, _, ent = fuzz.ifd_entries(blackmagic)
    offs, cnts = fuzz._longs(blackmagic, bo, ent[324]), fuzz._longs(blackmagic, bo, ent[325])
    end = max(o + c for o, c in zip(offs, cnts))
    with pytest.raises(ServiceError) as info:
        decode_upload(blackmagic[:end - short], "real.dng", max_pixels=BIG)
    assert (info.value.status, info.value.code) == (422, "corrupt_file")
    assert "beyond the end" in info.value.detail


def test_the_496_byte_upload_after_another_is_refused_over_http(victims):
    """repro_leak.sh: a photo, then the 496-byte header of the real DNG:
    422 with a JSON error, not the photo."""
    from fastapi.testclient import TestClient

    from service.app import app

    head = shared_file("repro/bm_trunc_496.dng").read_bytes()
    with TestClient(app) as c:
        assert c.post("/v1/analyze", files={"file": ("victim.dng", victims[0])}).status_code == 200
        r = c.post("/v1/white-balance", files={"file": ("x.dng", head)}, data={"format": "png"})
    assert r.status_code == 422, r.status_code
    body = r.json()
    assert body["error"] == "corrupt_file" and "tile" in body["detail"].lower(), body
