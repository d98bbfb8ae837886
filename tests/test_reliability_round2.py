"""Issue 17 (reliability, second round), part A: real-world names and
metadata, meaningless targets, JSON bombs, a strict Host header. Each test
failed before its fix (a 500, a dropped connection, a black image answered
200) and builds its inputs in memory."""

from __future__ import annotations

import io
import json
import re
import urllib.parse

import numpy as np
import pytest
import tifffile
from fastapi.testclient import TestClient

from service.errors import ServiceError
from testing.dngwriter import scene_dng

ARTIST = "(c) José Müller, Straße"
MAKE = "Cámara Ñü"


@pytest.fixture(scope="module")
def client():
    from service.app import app

    with TestClient(app) as c:
        yield c


def _dng(seed=0, make=None, model=None) -> bytes:
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", 96, 128, seed=seed, make=make, model=model)
    return buf.getvalue()


def _utf8_dng() -> bytes:
    """A valid DNG whose Make and Artist are UTF-8 (as editors write them):
    the Make placeholder and the Software text (retagged Artist) rewritten
    byte for byte, as ``nonascii_metadata_tiff.py`` does."""
    data = bytearray(_dng(make="MMMMMMMMMMMM"))
    data = bytearray(bytes(data).replace(b"MMMMMMMMMMMM", MAKE.encode().ljust(12, b"\0")))
    old = b"wandell-recovery testing.dngwriter"
    i, j = data.find(old), data.find(b"\x31\x01\x02\x00")      # Software text; tag 305, ASCII, little-endian
    assert i > 0 and j > 0
    data[i:i + len(old)] = ARTIST.encode().ljust(len(old), b"\0")
    data[j:j + 2] = (315).to_bytes(2, "little")
    return bytes(data)


# --- item 1: non-ASCII metadata ------------------------------------------------------------------

def test_ascii_text_transliterates_for_ascii_only_fields():
    from service.outputs import ascii_text

    assert ascii_text(ARTIST) == "(c) Jose Muller, Strasse"
    assert ascii_text("写真\x00") == "???" and ascii_text("plain") == "plain"


def test_non_ascii_metadata_never_fails_an_image_and_is_carried_whole(client):
    """Default TIFF (was a 500: tifffile refuses non-7-bit strings): 200,
    ASCII tags transliterated, the text whole in the XMP tag (700); PNG and
    JPEG: the EXIF ASCII fields transliterated (not UTF-8 bytes read back as
    Latin-1), the text whole in their XMP (iTXt / APP1)."""
    dng = _utf8_dng()
    r = client.post("/v1/white-balance", files={"file": ("José.dng", dng)})
    assert r.status_code == 200, r.text
    with tifffile.TiffFile(io.BytesIO(r.content)) as tf:
        tags = tf.pages[0].tags
        assert tags[315].value == "(c) Jose Muller, Strasse" and tags[271].value == "Camara Nu"
        xmp = bytes(tags[700].value).decode("utf-8")
    assert ARTIST in xmp and MAKE in xmp
    for fmt, marker in (("png", b"XML:com.adobe.xmp\0"), ("jpeg", b"http://ns.adobe.com/xap/1.0/\0")):
        r = client.post("/v1/white-balance", data={"format": fmt}, files={"file": ("a.dng", dng)})
        assert r.status_code == 200, r.text
        assert marker in r.content and ARTIST.encode() in r.content and MAKE.encode() in r.content
        assert b"Jose Muller" in r.content               # the EXIF Artist, 7-bit
        assert "José".encode().decode("latin-1").encode("utf-8") not in r.content   # no mojibake


def test_non_ascii_metadata_cli_white_balance_succeeds(tmp_path):
    from service import cli

    src = tmp_path / "José.dng"
    src.write_bytes(_utf8_dng())
    out = tmp_path / "out.tif"
    assert cli.main(["white-balance", str(src), str(out), "--format", "tiff"]) == 0
    assert tifffile.imread(out).shape == (96, 128, 3)


# --- item 2: names in Content-Disposition ----------------------------------------------------------

def _params(cd: str) -> dict:
    out = {}
    for k, v in re.findall(r';\s*([^=;\s]+)\s*=\s*("(?:[^"\\]|\\.)*"|[^;]*)', cd):
        out[k.lower()] = v[1:-1] if v.startswith('"') else v.strip()
    return out


@pytest.mark.parametrize("name", ["写真.dng", "Привет.dng", "\u202egnp.dng", "a\x00b.dng", 'a";filename*=x;y=".dng',
                                  "a\\b\r\n.dng", "plain.dng"])
def test_content_disposition_is_rfc6266_with_an_ascii_fallback(name):
    from service.headers import content_disposition

    v = content_disposition(name.replace(".dng", ".xmp"))
    v.encode("latin-1")                                    # a valid header value
    assert not any(ord(c) < 32 or c == "\x7f" for c in v)
    p = _params(v)
    assert set(p) <= {"filename", "filename*"} and p["filename"].isascii() and '"' not in p["filename"]
    eff = urllib.parse.unquote(p["filename*"][len("UTF-8''"):]) if "filename*" in p else p["filename"]
    assert eff.endswith(".xmp") and "\x00" not in eff and "\u202e" not in eff


@pytest.mark.parametrize("name", ["写真.dng", "Привет.dng", "a\x00b.dng", 'a";filename*=UTF-8\'\'evil.html;x=".dng'])
def test_xmp_download_of_any_name(client, name):
    """Was a 500 (outside Latin-1), no answer (NUL) or rewritten parameters
    (quote)."""
    r = client.post("/v1/white-balance", data={"format": "xmp"}, files={"file": (name, _dng())})
    assert r.status_code == 200, r.text
    p = _params(r.headers["content-disposition"])
    assert set(p) <= {"filename", "filename*"}
    eff = urllib.parse.unquote(p["filename*"][len("UTF-8''"):]) if "filename*" in p else p["filename"]
    assert eff.endswith(".xmp") and p["filename"].endswith(".xmp")


# --- item 3: targets naming a temperature ----------------------------------------------------------

BAD_TARGETS = ["D²", "BB²", "BB0", "D0", "BB1", "BB" + "9" * 400, "D3999", "D25001", "BB25001", "D999"]


@pytest.mark.parametrize("target", BAD_TARGETS)
def test_temperature_targets_outside_their_range_are_422_on_every_road(client, target):
    """Was a 500 (Unicode digits) or a 200 with a NaN matrix and a black
    image (BB0/D0/BB1), in single files, batches and the CLI."""
    from service import jobs

    dng = _dng(make="Acme", model="Model 1")
    for path, fields in (("/v1/white-balance", {"format": "png"}), ("/v1/white-balance", {"response": "json"}),
                         ("/v1/preview", {"wb": "corrected"})):
        r = client.post(path, data={"target": target, **fields}, files={"file": ("s.dng", dng)})
        assert r.status_code == 422, (path, r.text)
        assert r.json()["error"] == "invalid_parameter" and " K" in r.json()["detail"], r.text
    with pytest.raises(ServiceError) as e:                  # what POST /v1/batches and the CLI validate with
        jobs.batch_options(target=target)
    assert e.value.status == 422 and ".." in e.value.detail
    r = client.post("/v1/render", data={"illuminant": target, "response": "json"},
                    files={"file": ("t.csv", "\n".join(f"{w},0.5" for w in range(400, 710, 10)).encode())})
    assert r.status_code == 422, r.text


@pytest.mark.parametrize("target", ["D50", "D93", "D4000", "D25000", "BB1000", "BB3200", "BB2700.5", "BB25000"])
def test_temperature_targets_inside_their_range_render(client, target):
    r = client.post("/v1/white-balance", data={"target": target, "response": "json"},
                    files={"file": ("s.dng", _dng(make="Acme", model="Model 1"))})
    assert r.status_code == 200, r.text
    assert np.all(np.isfinite(np.array(r.json()["correction_matrix"], float)))


def test_a_correction_that_is_not_finite_is_never_a_success(client, monkeypatch):
    from service import rendering

    real = rendering._recovery_correction_matrix

    def nan_matrix(*a, **kw):
        M, info = real(*a, **kw)
        return np.full_like(M, np.nan), info

    monkeypatch.setattr(rendering, "_recovery_correction_matrix", nan_matrix)
    for fields in ({"format": "png"}, {"response": "json"}):
        r = client.post("/v1/white-balance", data=fields, files={"file": ("s.dng", _dng())})
        assert r.status_code == 422 and r.json()["error"] == "unrenderable", r.text


# --- item 4: JSON form fields ----------------------------------------------------------------------

BIG = "[" + "9" * 5000 + ",0]"
DEEP = "[" * 100_000 + "]" * 100_000


@pytest.mark.parametrize("path, fields", [
    ("/v1/analyze", {"neutral": BIG}), ("/v1/surfaces", {"points": "[" + BIG + "]"}),
    ("/v1/analyze", {"neutral": DEEP}), ("/v1/surfaces", {"rects": DEEP}), ("/v1/surfaces", {"points": DEEP}),
    ("/v1/preview", {"neutral": DEEP, "wb": "corrected"}), ("/v1/white-balance", {"neutral": BIG}),
    ("/v1/analyze", {"neutral": '{"a": ' * 50 + "1" + "}" * 50}), ("/v1/surfaces", {"points": "[[1e999, 2]]"}),
])
def test_json_bombs_are_422_with_the_documented_shape(client, path, fields):
    """Was a 500 (ValueError: more than 4300 digits; RecursionError)."""
    r = client.post(path, data=fields, files={"file": ("s.dng", b"II*\0not read")})
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["error"] == "invalid_parameter" and ("[row, col]" in body["detail"] or "integers]" in body["detail"])


def test_one_parser_bounds_length_and_depth_before_json():
    from service.options import JSON_FIELD_MAX_CHARS, parse_json_field

    assert parse_json_field("[[1, 2], [3, 4]]", "points", "x") == [[1, 2], [3, 4]]
    for text in ("[" * 9 + "]" * 9, "1" * (JSON_FIELD_MAX_CHARS + 1), "9" * 4301, "[1,", "\ud800"):
        with pytest.raises(ServiceError) as e:
            parse_json_field(text, "points", "the shape")
        assert e.value.status == 422 and "the shape" in e.value.detail


# --- Host header -----------------------------------------------------------------------------------

@pytest.mark.parametrize("host", ["127.0.0.1:8000@evil.com", "[::1]evil.com", "localhost:80:80", "127.0.0.1 x",
                                  "localhost:8000/evil", "::1", "[::1]:8000x", "user@localhost"])
def test_host_header_is_parsed_strictly(env_settings, host):
    from service.app import app

    env_settings(allowed_hosts="")
    with TestClient(app, base_url="http://127.0.0.1:8000") as c:
        r = c.get("/health", headers={"host": host})
        assert r.status_code == 400 and r.json()["error"] == "host_not_allowed", (host, r.text)
        for ok in ("127.0.0.1:8000", "[::1]:8000", "localhost", "LOCALHOST:8000"):
            assert c.get("/health", headers={"host": ok}).status_code == 200, ok


# --- item 9: CSV parsing memory --------------------------------------------------------------------

_CSV_MEM = r"""
import resource, sys
row = "400," + ",".join(["0"] * 5_000_000)
csv = (row + "\n" + row.replace("400,", "410,", 1) + "\n").encode()
del row
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
from service.errors import ServiceError
from service.routers.render import load_csv
try:
    load_csv(csv)
except ServiceError as e:
    print(e.code, (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) // 1024)
"""


def test_a_wide_csv_is_refused_from_its_counts_at_a_small_multiple_of_its_size():
    """20 MB CSV of two 5-million-value spectra: the rows were Python lists
    of str and float (about 30 bytes per input byte, 600 MB) before the
    6-wavelength rule; now the counts are checked from a scan (peak RSS
    growth measured in a fresh interpreter, the text itself included)."""
    import subprocess
    import sys
    from pathlib import Path

    r = subprocess.run([sys.executable, "-c", _CSV_MEM], capture_output=True, text=True, timeout=120,
                       cwd=Path(__file__).resolve().parents[1])
    code, mib = r.stdout.split()
    assert code == "too_few_wavelengths", r.stdout + r.stderr
    assert int(mib) < 100, f"peak RSS +{mib} MiB for a 20 MB CSV"


def test_csv_counts_are_checked_before_any_value_is_parsed(monkeypatch):
    from recovery import tables
    from recovery.errors import InputError

    real = tables.np.loadtxt

    def no_parse(lines, *a, **kw):      # the header test reads the first line only when it is short
        if len(lines) > 1 or len(lines[0]) >= 10_000:
            raise AssertionError("values parsed before the counts were checked")
        return real(lines, *a, **kw)

    monkeypatch.setattr(tables.np, "loadtxt", no_parse)
    wide = ("400," + ",".join(["1"] * 1000) + "\n") * 3
    for kw, code in (({"max_values": 2000}, "too_many_values"), ({"min_rows": 6}, "too_few_rows"),
                     ({"max_rows": 2}, "bad_csv")):
        with pytest.raises(InputError) as e:
            tables.read_csv_table(wide.encode(), **kw)
        assert e.value.code == code, e.value
    monkeypatch.undo()
    t = tables.read_csv_table(b"nm;a;b\n400;0,5;1\n410;0,25;2\n")     # decimal commas, header
    assert t.header == ["nm", "a", "b"] and t.values.tolist() == [[0.5, 1.0], [0.25, 2.0]]
    assert t.values.T.flags.c_contiguous                                  # spectra contiguous: no copy


# --- item 10: compressed linear TIFFs --------------------------------------------------------------

from testing.tiffs import linear_tiff as _linear_tiff  # noqa: E402 (the shared fixture builder)


def _packbits_tiff(h, w) -> bytes:
    n = h * w * 6
    return _linear_tiff(h, w, 32773, b"\x81\x00" * (n // 128) + (bytes([257 - n % 128, 0]) if n % 128 else b""), h)


_TIFF_MEM = r"""
import resource, sys, zlib
sys.path.insert(0, ".")
from tests.test_reliability_round2 import _linear_tiff, _packbits_tiff
h, w = 1500, 2000
data = _packbits_tiff(h, w) if sys.argv[1] == "packbits" else _linear_tiff(h, w, 8, zlib.compress(bytes(100 * w * 6)), 100)
from service.rawio import decode_upload
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
decode_upload(data, "x.tif", max_pixels=10**8)
print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) // 1024)
"""


def test_packbits_tiff_costs_what_deflate_costs():
    """3 MP PackBits 16-bit RGB TIFF of one strip: tifffile's pure-Python
    decoder (no imagecodecs) built a list of ints per strip, about 9 bytes
    per decoded byte (~160 MB here, 3.1 GB at 60 MP); with C decoders the
    peak is the deflate file's (the image buffers), within 40 MiB."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    mib = {k: int(subprocess.run([sys.executable, "-c", _TIFF_MEM, k], capture_output=True, text=True, timeout=120,
                                 cwd=root, check=True).stdout) for k in ("packbits", "deflate")}
    assert mib["packbits"] <= mib["deflate"] + 40, mib


def test_linear_tiff_compressions_outside_the_list_are_415(monkeypatch):
    import sys

    from service.rawio import decode_upload

    raw = bytes(64 * 96 * 6)
    for comp in (34925, 50000, 7, 99):            # LZMA, ZSTD, JPEG, unknown
        with pytest.raises(ServiceError) as e:
            decode_upload(_linear_tiff(64, 96, comp, raw, 64), "x.tif", max_pixels=10**8)
        assert e.value.status == 415 and "PackBits" in e.value.detail, e.value
    img = decode_upload(_packbits_tiff(64, 96), "x.tif", max_pixels=10**8)
    assert img.full_shape == (64, 96)
    monkeypatch.setitem(sys.modules, "imagecodecs", None)       # without C decoders: refused, not slow
    with pytest.raises(ServiceError) as e:
        decode_upload(_packbits_tiff(64, 96), "x.tif", max_pixels=10**8)
    assert e.value.status == 415


def test_real_dng_with_a_non_ascii_unique_camera_model(client):
    """The issue's case: the real Blackmagic.dng with one character of
    UniqueCameraModel changed to a Latin-1 'é' (was a 500 for the default TIFF)."""
    from .conftest import shared_file

    data = bytearray(shared_file("data/raw/Blackmagic.dng").read_bytes())
    i = data.find(b"Blackmagic Pocket Cinema Camera 4K\0")
    assert i > 0
    data[i + 1] = 0xE9                                     # "Béackmagic ..." (one byte: Latin-1)
    r = client.post("/v1/white-balance", files={"file": ("bm.dng", bytes(data))})
    assert r.status_code == 200 and r.content[:4] == b"II*\0", r.text[:300]
