"""The mechanisms behind issue 28's part B (request costs bounded by limits a
user can read, answers right or clearly refused): the literal light map's
sparse overlap solve and its region limit, and the service limits answered
as 4xx/503 JSON naming the limit. The shared reproductions themselves run in
``tests/test_round3_repros.py``."""

from __future__ import annotations

import numpy as np
import pytest

from recovery.errors import TooManyRegions
from recovery.regions import overlap_log_scales, region_count

EPS = np.finfo(float).eps


@pytest.fixture(scope="module")
def client():
    from fastapi.testclient import TestClient

    from service.app import app

    with TestClient(app) as c:
        yield c


@pytest.fixture(scope="module")
def nikon():
    from recovery import Camera

    return Camera.named("Nikon 5100 (NPL)")


def _overlap_system(rng, used):
    """The equations of estimate_light_map's step 2 on a grid of regions
    (``used`` marks those that take part): pairs of horizontal/vertical
    neighbours, random right-hand sides."""
    gr, gc = used.shape
    idx = -np.ones(used.shape, int)
    idx[used] = np.arange(used.sum())
    r, s = [], []
    for a in range(gr):
        for b in range(gc):
            if used[a, b]:
                for a2, b2 in ((a + 1, b), (a, b + 1)):
                    if a2 < gr and b2 < gc and used[a2, b2]:
                        r.append(idx[a, b])
                        s.append(idx[a2, b2])
    return np.array(r, int), np.array(s, int), rng.normal(size=len(r)), int(used.sum())


def _dense(r, s, d, n):
    """The former dense solve: one row per overlap, the gauge row, lstsq."""
    m = r.size
    A = np.zeros((m + 1, n))
    A[np.arange(m), r] = 1.0
    A[np.arange(m), s] = -1.0
    A[m] = 1.0 / n
    y = np.r_[d, 0.0]
    x, *_ = np.linalg.lstsq(A, y, rcond=None)
    return A, y, x


@pytest.mark.parametrize("keep", [1.0, 0.8, 0.6])     # connected, then split into several components
def test_sparse_overlap_solve_is_the_dense_minimum_norm_solution(rng, keep):
    """Same system, both minimum-norm least-squares solutions: they agree to
    the least-squares perturbation bound (Golub & Van Loan 2013, thm 5.3.1:
    relative error <= eps (2 kappa + kappa^2 |r| / (|A| |x|)) up to a modest
    constant, kappa the ratio of the largest to the smallest non-zero
    singular value), here with a constant of 100."""
    for trial in range(4):
        used = rng.random((13, 17)) < keep
        r, s, d, n = _overlap_system(rng, used)
        A, y, x_dense = _dense(r, s, d, n)
        x = overlap_log_scales(r, s, d, n)
        sv = np.linalg.svd(A, compute_uv=False)
        sv = sv[sv > sv[0] * max(A.shape) * EPS]
        kappa = sv[0] / sv[-1]
        xn = np.linalg.norm(x_dense)
        res = np.linalg.norm(A @ x_dense - y)
        bound = 100 * EPS * (2 * kappa + kappa ** 2 * res / (sv[0] * xn)) * xn
        assert np.linalg.norm(x - x_dense) <= bound, (trial, np.linalg.norm(x - x_dense), bound)
        assert np.linalg.norm(A @ x - y) <= res * (1 + 1e-9) + bound   # as good a fit


def test_sparse_overlap_solve_on_an_exact_system_recovers_the_scales(rng):
    """Right-hand sides made from known log scales (zero mean) are solved
    exactly: the answer is those scales (consistent system, one component)."""
    used = np.ones((20, 30), bool)
    r, s, _, n = _overlap_system(rng, used)
    truth = rng.normal(size=n)
    truth -= truth.mean()
    x = overlap_log_scales(r, s, truth[r] - truth[s], n)
    # conditioning of a 20x30 grid Laplacian is ~ (grid side)^2 ~ 1e3: 1e-10 leaves a margin of 1e3
    np.testing.assert_allclose(x, truth, atol=1e-10)


def test_sparse_overlap_solve_without_equations_is_zero():
    assert np.array_equal(overlap_log_scales(np.array([], int), np.array([], int), np.array([]), 5), np.zeros(5))


def test_light_map_of_a_long_strip_stays_small():
    """25,000 regions in a chain (the reproduction's 100000 x 2 image at the
    default region side): the solve is sparse, a few MB and well under a
    second, where the dense system was 25,000^2 floats (5 GB)."""
    import time
    import tracemalloc

    n = 25_000
    r, s = np.arange(n - 1), np.arange(1, n)
    d = np.full(n - 1, 0.01)
    tracemalloc.start()
    t0 = time.perf_counter()
    x = overlap_log_scales(r, s, d, n)
    elapsed = time.perf_counter() - t0
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    # exact answer: a ramp of slope -0.01, centred
    ramp = -0.01 * np.arange(n)
    np.testing.assert_allclose(x, ramp - ramp.mean(), atol=1e-8 * n)
    assert peak < 100 * 2 ** 20, peak                  # dense: 5 GB; sparse: O(n) arrays of 8 bytes
    assert elapsed < 30, elapsed                        # not a timing target: a bound far from O(n^3)


def _scene(rng):
    """A 96 x 96 Mondrian of 16 surfaces under D65 (inside the model): at the
    default region side (24) the literal map has 7 x 7 = 49 regions."""
    from testing.scenes import mondrian_scene

    return mondrian_scene(rng, 16, "Nikon 5100 (NPL)", "D65", 96).image


def test_default_region_side_grows_to_the_region_limit_and_says_so(nikon, rng):
    from recovery import estimate_illuminant

    img = _scene(rng)
    est = estimate_illuminant(img, nikon, "maloney-wandell", spatial=True, max_regions=20)
    d = est.diagnostics
    assert d["regions_total"] <= 20
    assert "region_size_coarsened" in d and "limit of 20" in d["region_size_coarsened"]
    # the smallest side that fits: one pixel less makes too many regions
    side = d["region_size"][0]
    assert region_count(img.shape[:2], side - 1, 0.5) > 20 >= region_count(img.shape[:2], side, 0.5)
    unlimited = estimate_illuminant(img, nikon, "maloney-wandell", spatial=True)
    assert unlimited.diagnostics["regions_total"] > 20
    assert "region_size_coarsened" not in unlimited.diagnostics


def test_explicit_region_side_past_the_limit_is_refused_before_any_region(nikon, rng, monkeypatch):
    from recovery import estimate_illuminant
    from recovery import regions

    def no_map(*a, **k):
        raise AssertionError("the map must not be started")
    monkeypatch.setattr(regions, "estimate_light_map", no_map)
    monkeypatch.setattr("recovery.api.estimate_light_map", no_map)
    img = _scene(rng)
    with pytest.raises(TooManyRegions, match="limit of 20 light-map regions"):
        estimate_illuminant(img, nikon, "maloney-wandell", spatial=True, region_size=8, max_regions=20,
                            on_failure="raise")


def test_region_limit_through_the_service_is_a_413_naming_it(client, env_settings):
    import io

    import tifffile

    env_settings(max_light_map_regions=50)
    rng = np.random.default_rng(4)
    buf = io.BytesIO()
    tifffile.imwrite(buf, rng.integers(1000, 50000, (64, 64, 3)).astype(np.uint16), photometric="rgb")
    data = {"method": "maloney-wandell", "spatial": "true", "region_size": "8"}
    r = client.post("/v1/analyze", files={"file": ("a.tif", buf.getvalue())}, data=data)
    assert r.status_code == 413, r.text
    body = r.json()
    assert body["error"] == "too_many_regions"
    assert "WANDELL_MAX_LIGHT_MAP_REGIONS" in body["detail"] and "50" in body["detail"]
    # the default region side fits itself under the limit and answers
    r = client.post("/v1/analyze", files={"file": ("a.tif", buf.getvalue())},
                    data={"method": "maloney-wandell", "spatial": "true"})
    assert r.status_code == 200, r.text


# ---------------------------------------------------------------------------
# A singular colour matrix: a 422 naming the tag (singular_color_matrix.py)
# ---------------------------------------------------------------------------

def _srationals(m) -> list:
    vals = []
    for v in np.asarray(m, float).ravel():
        vals += [int(round(v * 10000)), 10000]
    return vals


def _mosaic_dng(color_matrix1=None, **kw) -> bytes:
    """A 240 x 360 RGGB mosaic of coloured blocks as a DNG (testing.dngwriter);
    ``color_matrix1`` given is written over the tag afterwards, as a damaged
    file has it (the writer refuses a singular one)."""
    import io

    import tifffile

    from testing.dngwriter import mosaic, write_dng

    rng = np.random.default_rng(2)
    blocks = rng.uniform(0.05, 0.6, (240 // 40 + 1, 360 // 40 + 1, 3))
    rgb = np.kron(blocks, np.ones((40, 40, 1)))[:240, :360]
    buf = io.BytesIO()
    write_dng(buf, (mosaic(rgb) * 60000).astype(np.uint16), white_level=65535, as_shot_neutral=(0.5, 1.0, 0.6),
              **kw)
    if color_matrix1 is not None:
        buf.seek(0)
        with tifffile.TiffFile(buf, mode="r+b") as tf:
            tf.pages[0].tags[50721].overwrite(_srationals(color_matrix1))
    return buf.getvalue()


def _calibration1(m):
    """CameraCalibration1 (50723, SRATIONAL x 9) as a tifffile extra tag."""
    return [(50723, "2i", 9, _srationals(m), True)]


@pytest.mark.parametrize("what, kw, tag", [
    ("ColorMatrix1 of ones (rank 1)", {"color_matrix1": np.ones((3, 3))}, "ColorMatrix1"),
    ("CameraCalibration1 diag(1, 1, 0)", {"extratags": _calibration1(np.diag([1.0, 1.0, 0.0]))}, "CameraCalibration1"),
    ("CameraCalibration1 of ones", {"extratags": _calibration1(np.ones((3, 3)))}, "CameraCalibration1"),
])
def test_singular_colour_matrix_is_a_422_naming_the_tag(client, what, kw, tag):
    data = _mosaic_dng(**kw)
    for path, fields in (("/v1/analyze", {}), ("/v1/white-balance", {"format": "png"}),
                         ("/v1/surfaces", {"grid": "2x2"})):
        r = client.post(path, files={"file": ("cm.dng", data)}, data=fields)
        assert r.status_code == 422, (what, path, r.status_code, r.text[:300])
        body = r.json()
        assert body["error"] == "bad_color_matrix" and tag in body["detail"], (what, path, body)


def test_a_well_conditioned_profile_has_no_problem_and_the_same_file_answers(client):
    from recovery.dng_color import ColorProfile
    from service.metadata import profile_problem

    srgb_to_xyz_inv = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    assert profile_problem(ColorProfile(srgb_to_xyz_inv, camera_calibration1=np.diag([1.0, 1.1, 0.9]))) is None
    assert "ColorMatrix2" in profile_problem(ColorProfile(srgb_to_xyz_inv, color_matrix2=np.ones((3, 3)),
                                                          illuminant1=17, illuminant2=21))
    r = client.post("/v1/analyze", files={"file": ("ok.dng", _mosaic_dng(color_matrix1=srgb_to_xyz_inv))})
    assert r.status_code == 200, r.text[:300]


# ---------------------------------------------------------------------------
# HEAD wherever GET is (head_405.py)
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("path", ["/health", "/v1/models", "/v1/cameras", "/"])
def test_head_answers_like_get_without_a_body(client, path):
    g, h = client.get(path), client.head(path)
    assert g.status_code == h.status_code == 200
    assert h.content == b""
    assert h.headers["content-length"] == g.headers["content-length"]
    assert h.headers["content-type"] == g.headers["content-type"]


def test_head_is_not_added_where_get_is_not_served_nor_documented(client):
    r = client.head("/v1/analyze")
    assert r.status_code == 405
    schema = client.get("/openapi.json").json()
    assert all("head" not in ops for ops in schema["paths"].values())
    assert "get" in schema["paths"]["/health"]


# ---------------------------------------------------------------------------
# Slow clients: an overall body deadline, a connection cap, a send deadline
# (slow_uploads_fd_exhaustion.py, stalled_readers_tmpdir.py)
# ---------------------------------------------------------------------------

def _scope(path="/v1/analyze", method="POST", headers=()):
    return {"type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method,
            "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": b"",
            "root_path": "", "headers": [(b"host", b"127.0.0.1:8000"), *headers],
            "client": ("127.0.0.1", 1), "server": ("127.0.0.1", 8000)}


def test_a_body_that_trickles_is_cut_off_at_the_body_deadline(env_settings):
    """A byte every 0.1 s never trips the 30 s gap timeout; the whole body
    must still arrive within WANDELL_BODY_DEADLINE (1 s here): a 408 naming
    it, with Connection: close."""
    import asyncio
    import json
    import time

    from service.app import app

    env_settings(body_timeout=30, body_deadline=1)
    head = (b'--zz\r\nContent-Disposition: form-data; name="file"; filename="a.dng"\r\n'
            b"Content-Type: application/octet-stream\r\n\r\n")
    first, sent = [head], []

    async def receive():
        if first:
            return {"type": "http.request", "body": first.pop(), "more_body": True}
        await asyncio.sleep(0.1)
        return {"type": "http.request", "body": b"a", "more_body": True}

    async def send(message):
        sent.append(message)

    scope = _scope(headers=[(b"content-type", b"multipart/form-data; boundary=zz"),
                            (b"transfer-encoding", b"chunked")])
    t0 = time.monotonic()
    asyncio.run(asyncio.wait_for(app(scope, receive, send), 30))
    took = time.monotonic() - t0
    start = [m for m in sent if m["type"] == "http.response.start"]
    body = json.loads(b"".join(m.get("body", b"") for m in sent if m["type"] == "http.response.body"))
    assert len(start) == 1 and start[0]["status"] == 408, sent
    assert body["error"] == "body_deadline" and "WANDELL_BODY_DEADLINE" in body["detail"]
    assert (b"connection", b"close") in start[0]["headers"]
    assert 1 <= took < 15          # 1 s, plus scheduling on a loaded 2-core machine


def test_an_answer_the_client_stops_taking_is_given_up_and_its_file_removed(env_settings, tmp_path):
    """The client takes the headers and nothing more (the socket's buffer
    full: the send waits for ever). After WANDELL_SEND_TIMEOUT (0.5 s) the
    answer is abandoned without an error escaping, and the temporary file
    it was sent from is gone."""
    import asyncio
    import time

    from service.limits import SendDeadlineMiddleware
    from service.routers.analysis import TemporaryFileResponse

    env_settings(send_timeout=0.5)
    path = tmp_path / "answer.png"
    path.write_bytes(b"x" * (3 * 1024 * 1024))
    got = []

    async def receive():
        await asyncio.sleep(3600)

    async def send(message):
        got.append(message["type"])
        if message["type"] == "http.response.body":
            await asyncio.sleep(3600)          # the reader stopped reading

    mw = SendDeadlineMiddleware(TemporaryFileResponse(str(path), media_type="image/png"))
    t0 = time.monotonic()
    asyncio.run(asyncio.wait_for(mw(_scope("/x", "GET"), receive, send), 30))
    took = time.monotonic() - t0
    assert not path.exists()
    assert got == ["http.response.start", "http.response.body"]
    assert 0.5 <= took < 10


def test_a_temporary_answer_sent_whole_is_removed_too(tmp_path):
    import asyncio

    from service.routers.analysis import TemporaryFileResponse

    path = tmp_path / "answer.png"
    path.write_bytes(b"y" * (2 * 1024 * 1024 + 5))
    body = []

    async def receive():
        await asyncio.sleep(3600)

    async def send(message):
        body.append(message.get("body", b""))

    asyncio.run(TemporaryFileResponse(str(path))(_scope("/x", "GET"), receive, send))
    assert b"".join(body) == b"y" * (2 * 1024 * 1024 + 5) and not path.exists()


def test_connection_cap_default_follows_the_descriptor_limit():
    from service.__main__ import connection_cap

    assert connection_cap(0, 1024) == (1024 - 100) // 2
    assert connection_cap(0, 20000) == (20000 - 100) // 2
    assert connection_cap(0, 50) == 8
    assert connection_cap(7, 1024) == 7


def test_accept_errors_are_logged_once_a_minute_without_the_traceback():
    import logging

    from service.__main__ import _RateLimitedAcceptErrors

    f = _RateLimitedAcceptErrors(interval=60)
    rec = lambda msg: logging.LogRecord("asyncio", logging.ERROR, __file__, 1, msg, None,  # noqa: E731
                                        (OSError, OSError(24, "Too many open files"), None))
    passed = [f.filter(rec("socket.accept() out of system resource\nsocket: <...>")) for _ in range(1000)]
    assert passed.count(True) == 1 and passed[0]
    assert f.filter(rec("something else")) is True      # other asyncio errors untouched


def test_a_real_server_answers_connections_past_its_cap_with_a_503_naming_it():
    """``python -m service`` with WANDELL_MAX_CONNECTIONS=3: three idle
    connections are held; the fourth is answered at once with 503
    too_many_connections (JSON naming the setting) and closed; once they
    go, /health answers 200."""
    import json
    import socket
    import time

    import httpx

    from .conftest import running_server

    with running_server({"max_connections": 3, "keep_alive_timeout": 30}) as (base, _, _):
        port = int(base.rsplit(":", 1)[1])
        held = [socket.create_connection(("127.0.0.1", port)) for _ in range(3)]
        time.sleep(0.5)
        extra = socket.create_connection(("127.0.0.1", port))
        extra.settimeout(10)
        extra.sendall(b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        data = b""
        while True:
            piece = extra.recv(4096)
            if not piece:
                break
            data += piece
        extra.close()
        head, _, body = data.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 503"), data[:200]
        d = json.loads(body)
        assert d["error"] == "too_many_connections" and "WANDELL_MAX_CONNECTIONS" in d["detail"]
        for s in held:
            s.close()
        time.sleep(0.5)
        assert httpx.get(base + "/health", timeout=10).status_code == 200


# ---------------------------------------------------------------------------
# /v1/surfaces' box sums at the corners only (mem_surfaces_tiff.py)
# ---------------------------------------------------------------------------

def test_streamed_box_sums_equal_the_summed_area_table(rng):
    """Same sums as the full table (_box over _box_sums) for random boxes and
    strip heights, to the error bound of recursive summation (Higham 2002,
    eq. 4.4: |error| <= (n - 1) eps sum |x|, n the terms summed; both sides
    sum at most h*w terms, so 2 h w eps sum|a| bounds their difference)."""
    from service.pipeline import _box, _box_sums, box_sums_streamed

    for h, w, strip in [(100, 70, 7), (64, 64, 64), (5, 300, 2), (300, 5, 1000), (129, 33, 64)]:
        a = rng.normal(size=(h, w, 4))
        n = 300
        r0 = rng.integers(0, h, n)
        r1 = np.minimum(h, r0 + rng.integers(1, h + 1, n))
        c0 = rng.integers(0, w, n)
        c1 = np.minimum(w, c0 + rng.integers(1, w + 1, n))
        ref = _box(_box_sums(a), r0, c0, r1, c1)
        got = box_sums_streamed(lambda i, j: a[i:j], h, w, r0, c0, r1, c1, strip=strip)
        assert np.all(np.abs(got - ref) <= 2 * h * w * EPS * np.abs(a).sum()), (h, w, strip)
    # corners on the first row and column (empty sums there) and one-pixel boxes
    a = rng.normal(size=(10, 12, 1))
    got = box_sums_streamed(lambda i, j: a[i:j], 10, 12, [0, 9, 3], [0, 11, 0], [1, 10, 10], [1, 12, 12], strip=4)
    np.testing.assert_allclose(got[:, 0], [a[0, 0, 0], a[9, 11, 0], a[3:, :, 0].sum()], rtol=1e-12)


def test_streamed_box_sums_hold_a_strip_not_the_table(rng):
    """A 2000 x 3000 image with 5 layers: the full table would be 240 MB of
    float64 (plus its temporaries); the streamed sums hold a strip's worth
    (64 x 3001 x 5 doubles, 7.7 MB) a few times over."""
    import tracemalloc

    from service.pipeline import box_sums_streamed

    h, w = 2000, 3000
    row = rng.random((1, w, 5))

    def layers(i, j):
        return np.repeat(row, j - i, axis=0)
    tracemalloc.start()
    got = box_sums_streamed(layers, h, w, [0, 100], [0, 7], [h, 1500], [w, 2000])
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    np.testing.assert_allclose(got[0], h * row[0].sum(axis=0), rtol=1e-10)
    np.testing.assert_allclose(got[1], 1400 * row[0, 7:2000].sum(axis=0), rtol=1e-10)
    assert peak < 6 * 64 * (w + 1) * 5 * 8, peak


# ---------------------------------------------------------------------------
# LinearRaw DNGs read tile by tile (mem_linear_raw_dng.py)
# ---------------------------------------------------------------------------

def _linear_dng(img, black=0, white=None, tile=None, compression=None, orientation=1) -> bytes:
    """A LinearRaw DNG (PhotometricInterpretation 34892, three samples per
    pixel) of ``img`` with tifffile: the tags LibRaw needs and no more."""
    import io

    import tifffile

    cm = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    if white is None:
        white = 1 if img.dtype.kind == "f" else np.iinfo(img.dtype).max
    black = np.atleast_1d(black)
    tags = [(271, "s", 0, "Acme", True), (272, "s", 0, "LinCam", True), (274, "H", 1, orientation, True),
            (50706, "B", 4, (1, 4, 0, 0), True), (50707, "B", 4, (1, 1, 0, 0), True),
            (50708, "s", 0, "Acme LinCam", True), (50721, "2i", 9, _srationals(cm), True),
            (50778, "H", 1, 21, True), (50728, "2I", 3, _srationals((0.5, 1.0, 0.6)), True),
            (50713, "H", 2, (1, 1), True), (50714, "2I", black.size, [v for b in black for v in (int(b), 1)], True),
            (50717, "I", 1, int(white), True)]
    buf = io.BytesIO()
    kw = dict(photometric=34892, subfiletype=0, compression=compression, metadata=None, extratags=tags,
              planarconfig="contig")
    if tile:
        kw["tile"] = tile
    else:
        kw["rowsperstrip"] = 16
    tifffile.imwrite(buf, img, **kw)
    return buf.getvalue()


def _linear_base(rng, h=300, w=452):
    blocks = rng.uniform(0.05, 0.9, (h // 16 + 1, w // 16 + 1, 3))
    return np.kron(blocks, np.ones((16, 16, 1)))[:h, :w]


@pytest.mark.parametrize("orientation", [1, 6])
def test_linear_dng_estimation_is_libraws_to_its_rounding(rng, monkeypatch, orientation):
    """16-bit samples with a black level: the tile-by-tile estimation image
    equals the one LibRaw's postprocess made (the former path) to LibRaw's
    rounding to whole 16-bit output values (half a DN each side: 1/65535),
    oriented the same, with the same neutral and shape."""
    import service.decode.linear_dng as L
    from service.decode.upload import decode_upload

    base = _linear_base(rng)
    data = _linear_dng((1000 + base * 60000).astype(np.uint16), black=1000, orientation=orientation)
    ours = decode_upload(data, "a.dng", max_pixels=10 ** 8, estimation_pixels=10 ** 8)
    monkeypatch.setattr(L, "linear_dng_estimation", lambda *a, **k: None)
    libraw = decode_upload(data, "a.dng", max_pixels=10 ** 8, estimation_pixels=10 ** 8)
    assert "the file's own samples" in ours.warnings[-1] and "LibRaw's own" in libraw.warnings[-1]
    assert ours.estimation.shape == libraw.estimation.shape and ours.full_shape == libraw.full_shape
    assert np.max(np.abs(ours.estimation - libraw.estimation)) <= 1 / 65535 + 1e-7
    np.testing.assert_allclose(ours.as_shot_neutral, libraw.as_shot_neutral, rtol=1e-6)
    assert not ours.saturated.any() and not libraw.saturated.any()


def test_linear_dng_float_tiles_are_read_as_their_samples_and_block_averaged(rng):
    """float32 samples (white 1) in deflate tiles: the estimation image is
    the samples themselves (to float32 rounding), and with an estimation
    size of a ninth, their 3x3 block means; a sample at 98 % of white marks
    its block saturated."""
    from service.decode.upload import decode_upload

    base = _linear_base(rng).astype(np.float32)
    base[7, 7] = 0.99
    data = _linear_dng(base, tile=(64, 64), compression="zlib")
    full = decode_upload(data, "a.dng", max_pixels=10 ** 8, estimation_pixels=10 ** 8)
    np.testing.assert_allclose(full.estimation, base, rtol=2 * np.finfo(np.float32).eps)
    assert full.saturated.sum() == 1 and full.saturated[7, 7]
    small = decode_upload(data, "a.dng", max_pixels=10 ** 8, estimation_pixels=300 * 452 // 9 + 1)   # f = 3
    h, w = 100, 150
    means = base[:3 * h, :3 * w].astype(np.float64).reshape(h, 3, w, 3, 3).mean(axis=(1, 3))
    assert small.estimation.shape == (h, w, 3)
    np.testing.assert_allclose(small.estimation, means, rtol=4 * np.finfo(np.float32).eps)
    assert small.saturated.sum() == 1 and small.saturated[2, 2]


def test_linear_dng_estimation_holds_a_tile_not_the_image(rng):
    """A 2000 x 3000 float DNG in 256-pixel tiles binned to 0.375 MP: the
    decoded image would be 72 MB (float32) and LibRaw's buffers more; the
    tile-by-tile read holds the estimation image, its float64 sums and
    saturation flags (0.375 MP x 37 bytes, 14 MB) and a tile's temporaries."""
    import tracemalloc

    from service.decode.linear_dng import linear_dng_estimation

    img = np.broadcast_to(rng.uniform(0.1, 0.8, (1, 3000, 3)).astype(np.float32), (2000, 3000, 3))
    data = _linear_dng(np.ascontiguousarray(img), tile=(256, 256), compression="zlib")
    tracemalloc.start()
    got = linear_dng_estimation(data, 2000, 3000, 375_001)     # f = 4
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert got is not None and got[0].shape == (500, 750, 3)
    n = 500 * 750
    assert peak < n * (3 * 8 + 3 * 4 + 1) + 8 * 2 ** 20, peak     # the sums, the image, the flags; 8 MiB for a tile


def test_linear_dng_outside_the_plain_layout_is_left_to_libraw(rng, monkeypatch):
    import service.decode.linear_dng as L

    data = _linear_dng((_linear_base(rng) * 60000).astype(np.uint16))
    assert L.linear_dng_estimation(data, 300, 452, None) is not None
    assert L.linear_dng_estimation(data, 301, 452, None) is None          # not the size LibRaw reports
    assert L.linear_dng_estimation(_mosaic_dng(), 240, 360, None) is None  # a CFA DNG
    tiled = _linear_dng((_linear_base(rng) * 60000).astype(np.uint16), tile=(64, 64))
    assert L.linear_dng_estimation(tiled, 300, 452, None) is not None
    monkeypatch.setattr(L, "MAX_TILE_PIXELS", 64 * 64 - 1)                  # a tile declared too large
    assert L.linear_dng_estimation(tiled, 300, 452, None) is None
