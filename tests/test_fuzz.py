"""2,000 mutated RAW files through the ASGI app (issue 6), mutations of a real
DNG each sent after two different images (issue 10), and the mutation
generators themselves."""

from __future__ import annotations

import io
import os
import struct

import pytest
from fastapi.testclient import TestClient

from benchmarks import fuzz
from service.app import app

from .conftest import shared_file

N_FUZZ = int(os.environ.get("WANDELL_FUZZ_N", "2000"))


@pytest.fixture(scope="module")
def seeds():
    return fuzz.seed_dngs()


def test_ifd_entries_reads_the_written_tags(seeds):
    """The parser the mutations rely on finds the dimensions and the strip
    that testing.dngwriter wrote (fuzz.SEEDS gives the sizes)."""
    for data, (_, _, _, h, w) in zip(seeds, fuzz.SEEDS):
        bo, ifd, ent = fuzz.ifd_entries(data)
        width = struct.unpack(bo + "I", data[ent[256][3]:ent[256][3] + 4])[0]
        length = struct.unpack(bo + "I", data[ent[257][3]:ent[257][3] + 4])[0]
        off = struct.unpack(bo + "I", data[ent[273][3]:ent[273][3] + 4])[0]
        cnt = struct.unpack(bo + "I", data[ent[279][3]:ent[279][3] + 4])[0]
        assert (width, length) == (w, h)
        assert off + cnt == len(data) and cnt == w * h * 2     # one uncompressed 16-bit strip, last in the file


def test_mutations_are_deterministic_and_cover_every_kind(seeds):
    a = list(fuzz.mutations(2 * len(fuzz.KINDS), seeds))
    b = list(fuzz.mutations(2 * len(fuzz.KINDS), seeds))
    assert [m.data for m in a] == [m.data for m in b]
    assert {m.kind for m in a} == set(fuzz.KINDS)
    # each mutation changed something (or renamed the file)
    for m in a:
        assert m.data not in seeds or m.filename != "fuzz.dng", (m.kind, m.what)


def test_huge_declared_dimensions_are_refused_before_decoding(seeds):
    """ImageWidth/Length patched to 100000 x 100000 on a 7 kB file: a 413
    from the header check (10^10 pixels > max_pixels), no pixel buffer."""
    bo, _, ent = fuzz.ifd_entries(seeds[0])
    d = bytearray(seeds[0])
    fuzz._set_long(d, bo, ent, fuzz.TAG_WIDTH, 100000)
    fuzz._set_long(d, bo, ent, fuzz.TAG_LENGTH, 100000)
    with TestClient(app) as c:
        r = c.post("/v1/analyze", files={"file": ("big.dng", bytes(d), "image/x-adobe-dng")})
    assert r.status_code == 413 and r.json()["error"] == "too_many_pixels", r.text


def test_two_thousand_mutated_raws_never_crash_the_service():
    """Every mutated file: a 4xx with {"error", "detail"}, or a 200 whose
    numbers are all finite (fuzz._check); no 5xx, no request over the
    timeout; /health answers afterwards; RSS growth within
    fuzz.memory_bound_mb() (the light-posterior cache's capacity, which
    mutated colour matrices fill, plus 64 MB of allocator slack: see its
    docstring)."""
    bound = fuzz.memory_bound_mb()
    rep = fuzz.run(N_FUZZ, timeout=60.0, sample_every=10, warmup=min(200, N_FUZZ // 4))
    print(rep.table())
    assert rep.failures == []
    assert rep.n == N_FUZZ + len(range(0, N_FUZZ, 10))
    assert all(400 <= s < 500 or s == 200 for s in rep.statuses), rep.statuses
    assert rep.health_after == 200
    # the mutations reach both outcomes: refusals and files that stay valid
    assert rep.statuses[200] > 0 and sum(v for s, v in rep.statuses.items() if s >= 400) > N_FUZZ // 4
    assert rep.rss_growth_mb < bound, f"RSS grew {rep.rss_growth_mb:.0f} MB, bound {bound:.0f} MB"


def test_real_dng_mutations_answer_the_same_whatever_came_before():
    """Every 3rd mutation of the real CinemaDNG (fuzz.dng_mutations: every
    kind is in that subset) through /v1/analyze, once after each of two
    different 9-Mpx images: the same status and body (timings aside) both
    times, 4xx JSON errors or 200s with finite numbers, never a 5xx or a
    hang. ``python -m benchmarks.fuzz --real-dng`` sends all of them."""
    data = shared_file("data/raw/Blackmagic.dng").read_bytes()
    assert {m.kind for m in fuzz.dng_mutations(data)[::3]} == set(fuzz.DNG_KINDS)
    rep, dependent = fuzz.run_real_dng(data, every=3, timeout=60.0)
    print(rep.table())
    assert dependent == [] and rep.failures == []
    assert rep.n == 2 * len(fuzz.dng_mutations(data)[::3])
    assert all(400 <= s < 500 or s == 200 for s in rep.statuses), rep.statuses
    assert rep.statuses[200] > 0 and rep.statuses[422] > 0
    assert rep.health_after == 200


def test_issue17_hostile_inputs_never_5xx():
    """fuzz.run_round2 (``python -m benchmarks.fuzz --round2``): non-ASCII
    metadata, hostile file names, temperature targets out of range or in
    Unicode digits, JSON bombs, PackBits/CSV bombs (small), Host tricks.
    Before issue 17: 28 of 191 raised (a 500 in a server), 8 black images
    or rewritten headers answered 200, 4 hostile Hosts served; now every
    answer is a JSON 4xx or a checked 200 (finite numbers, a non-black
    image, only filename/filename* in Content-Disposition)."""
    rep, peaks = fuzz.run_round2()
    print(fuzz.round2_table(rep, peaks))
    assert rep.failures == []
    assert not [s for s in rep.statuses if s >= 500], rep.statuses
    assert set(rep.by_kind) == set(fuzz.ROUND2_KINDS)
    assert rep.health_after == 200
    # the valid ones still work: every non-ASCII-metadata and hostile-name file renders
    for kind in ("nonascii-metadata", "hostile-name"):
        assert set(rep.by_kind[kind]) == {200}, (kind, rep.by_kind[kind])
    assert set(rep.by_kind["host"]) == {400}
