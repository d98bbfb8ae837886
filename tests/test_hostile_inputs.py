"""Hostile inputs that used to get a 500 or an unreadable answer (issue 10,
items 3 and 5, and DefaultScale of item 2): each is a 4xx with a JSON
``{"error", "detail"}`` naming the problem, or an answer clients can read."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from testing.dngwriter import mosaic, write_dng
from service.errors import ServiceError
from service.rawio import decode_upload

WL31 = ",".join(str(400 + 10 * i) for i in range(31))


@pytest.fixture(scope="module")
def client():
    from service.app import app

    with TestClient(app) as c:
        yield c


def _npy_header(shape, dtype="<f4") -> bytes:
    """A version-1.0 ``.npy`` header declaring ``shape`` (npy_overflow.py)."""
    hdr = "{'descr': '%s', 'fortran_order': False, 'shape': %r, }" % (dtype, tuple(shape))
    hdr += " " * (63 - (10 + len(hdr)) % 64) + "\n"
    return b"\x93NUMPY\x01\x00" + len(hdr).to_bytes(2, "little") + hdr.encode()


@pytest.mark.parametrize("shape", [(2**32, 2**32, 31), (2**62 + 1, 4, 31), (2**63, 1, 31)])
def test_npy_whose_shape_product_overflows_int64_is_refused(client, shape):
    """2**32 * 2**32 * 31 wraps to 0 in int64 and passed the size check;
    the exact product is far over any limit: 413."""
    data = _npy_header(shape) + np.full(64, 0.5, "<f4").tobytes()
    r = client.post("/v1/render", files={"file": ("c.npy", data)}, data={"wavelengths": WL31, "response": "json"})
    assert r.status_code == 413, r.text
    assert r.json()["error"] == "cube_too_large" and r.json()["detail"]


@pytest.mark.parametrize("n", [2, 4, 5])
def test_spectra_with_fewer_than_six_wavelengths_are_422(client, n):
    """repro_render_fewbands.sh: colour-science's Sprague interpolation
    asserts on fewer than 6 points (a 500 before)."""
    csv = "\n".join(f"{400 + 300 * i / (n - 1):g},0.5" for i in range(n)).encode()
    for form in ({"response": "json"}, {"response": "json", "strategy": "full"}):
        r = client.post("/v1/render", files={"file": ("s.csv", csv)}, data=form)
        assert r.status_code == 422, r.text
        assert r.json()["error"] == "too_few_wavelengths" and f"{n} wavelength" in r.json()["detail"]
    light = "\n".join(f"{380 + 400 * i / (n - 1):g},1" for i in range(n)).encode()
    csv31 = "\n".join(f"{400 + 10 * i},0.5" for i in range(31)).encode()
    r = client.post("/v1/render", files={"file": ("s.csv", csv31), "light_file": ("l.csv", light)},
                    data={"response": "json"})
    assert r.status_code == 422 and r.json()["error"] == "too_few_wavelengths", r.text


def test_six_wavelengths_still_render(client):
    csv = "\n".join(f"{400 + 60 * i},0.5" for i in range(6)).encode()
    r = client.post("/v1/render", files={"file": ("s.csv", csv)}, data={"response": "json"})
    assert r.status_code == 200, r.text


def _small_dng(**kw) -> bytes:
    rgb = np.full((48, 64, 3), 9000, np.uint16)
    rgb[..., 1] = 14000
    buf = io.BytesIO()
    write_dng(buf, mosaic(rgb, "RGGB"), white_level=16383, **kw)
    return buf.getvalue()


@pytest.mark.parametrize("make, model", [
    ("M" * 65536, "m" * 65536),                                   # repro_bigheader.sh
    ("A\r\nX-Injected: 1\r\n", "B\r\n\r\n<html>"),
    ("\x1b[31mred\x07", "tab\there\x7fnext"),
])
def test_file_strings_are_capped_and_printable(make, model):
    d = decode_upload(_small_dng(make=make, model=model), "s.dng", max_pixels=10**8)
    for s in (d.make, d.model):
        assert s is not None and len(s) <= 64, s
        assert s.isprintable() and s == s.strip(), repr(s)
        assert not any(c in s for c in "\r\n\t\x00\x1b\x07\x7f")


def test_a_64_kib_make_gives_a_header_clients_read(client):
    """The X-Illuminant header echoes Make/Model (camera name, warnings):
    with 64 KiB strings it was ~130 KiB, which curl and Python refuse. Every
    file string is now at most 64 characters, so the header stays within
    the 8 KiB that common servers and proxies accept for one header."""
    data = _small_dng(make="M" * 65536, model="<script>alert(1)</script>\r\n" + "m" * 65536)
    r = client.post("/v1/white-balance", files={"file": ("big.dng", data)}, data={"format": "png"})
    assert r.status_code == 200, r.text[:300]
    header = r.headers["x-illuminant"]
    assert len(header) < 8192, len(header)
    body = json.loads(header)
    assert "\r" not in header and "\n" not in header
    assert len(json.dumps(body)) < 8192


def _scaled_dng(h: int, w: int, scale) -> bytes:
    """A DNG of ``h x w`` with DefaultScale ``scale`` (horizontal, vertical
    as RATIONAL pairs)."""
    buf = io.BytesIO()
    write_dng(buf, mosaic(np.full((h, w, 3), 9000, np.uint16), "RGGB"), white_level=16383,
              extratags=[(50718, 5, 2, scale, True)])
    return buf.getvalue()


def test_default_scale_counts_against_the_pixel_limit():
    """repro_aspect.sh: DefaultScale 10:1 makes LibRaw stretch 64 x 48 to
    640 x 48 = 30,720 pixels. With the limit between the declared 3,072 and
    the stretched 30,720 pixels the file is a 413 before decoding; with the
    limit above, it decodes to the stretched full-resolution shape."""
    data = _scaled_dng(48, 64, (10, 1, 1, 1))
    with pytest.raises(ServiceError) as info:
        decode_upload(data, "a.dng", max_pixels=20_000)
    assert (info.value.status, info.value.code) == (413, "too_many_pixels"), info.value
    assert "640x48" in info.value.detail and "DefaultScale" in info.value.detail
    d = decode_upload(data, "a.dng", max_pixels=30_720)
    assert d.full_shape == (48, 640)
    # vertical stretch (1:10) counts the same way
    with pytest.raises(ServiceError) as info:
        decode_upload(_scaled_dng(48, 64, (1, 1, 10, 1)), "a.dng", max_pixels=20_000)
    assert info.value.status == 413 and "64x480" in info.value.detail
