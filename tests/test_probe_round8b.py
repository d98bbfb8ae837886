"""Round 8b of probing (docs/probe_round8.md, "Round 8b"): the items round 8
noticed and left, each the minimal reproduction of a fault a user would hit,
through the command line as users run it (``python -m service.cli``) or the
real ASGI stack (FastAPI's TestClient), and holds once the fault is fixed."""

from __future__ import annotations

import io
import json
import math

import numpy as np
import pytest

from .conftest import isolated_app_client, strict_json, scene_dng_bytes
from .conftest import run_cli as _cli


@pytest.fixture(scope="module")
def dng() -> bytes:
    return scene_dng_bytes(64, 96)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")

_strict = strict_json


def _linear_dng(dtype, as_shot_neutral=(0.5, 1.0, 0.6)) -> bytes:
    from testing.dngwriter import write_linear_dng

    rgb = np.random.default_rng(0).uniform(0.05, 0.9, (48, 64, 3))
    scale = 4e9 if dtype == np.uint32 else 65535
    buf = io.BytesIO()
    write_linear_dng(buf, (rgb * scale).astype(dtype), as_shot_neutral=as_shot_neutral)
    return buf.getvalue()


# --- 1. a LinearRaw DNG of 32-bit integers without AsShotNeutral ------------------------------

def test_a_uint32_linear_dng_without_as_shot_neutral_is_read(client):
    """A LinearRaw DNG of 32-bit integers (LibRaw refuses the sample type;
    the service reads its samples itself) was read with an AsShotNeutral
    and refused without one, as "a DNG ... that LibRaw cannot decode:
    damaged, or a variant LibRaw does not support", on every endpoint. It
    is now read without an as-shot white: the light is the one of the same
    file with the tag (the samples are the same), ``white=as-shot`` is the
    422 a file without an as-shot white gets."""
    without, tagged = _linear_dng(np.uint32, None), _linear_dng(np.uint32)
    a = client.post("/v1/analyze", files={"file": ("a.dng", without)})
    assert a.status_code == 200, a.text[:400]
    b = client.post("/v1/analyze", files={"file": ("a.dng", tagged)})
    assert a.json()["illuminant"]["camera_rgb"] == b.json()["illuminant"]["camera_rgb"]
    img = client.post("/v1/white-balance", files={"file": ("a.dng", without)}, data={"format": "png"})
    assert img.status_code == 200 and img.content[:4] == b"\x89PNG", img.text[:300]
    r = client.post("/v1/white-balance", files={"file": ("a.dng", without)}, data={"white": "as-shot"})
    assert r.status_code == 422 and r.json()["error"] == "no_as_shot_white", r.text
    p = client.post("/v1/preview", files={"file": ("a.dng", without)})
    assert p.status_code == 200 and json.loads(p.headers["X-Preview"])["wb"] == "camera", p.text[:300]


# --- 2. an absurd as-shot white ----------------------------------------------------------------

@pytest.mark.parametrize("kind", ["bayer", "linear-raw"])
def test_an_absurd_as_shot_white_is_named_not_called_missing(client, kind):
    """A DNG whose AsShotNeutral is (1e-6, 1, 1e6) records an as-shot white,
    an unusable one, but ``white=as-shot`` answered "the file records no
    as-shot white balance" for a Bayer DNG (LibRaw drops a neutral under
    0.001) and, for a LinearRaw one (read by the service), rendered with a
    white multiplying a channel by 10^4. Both now answer the same 422
    ``no_as_shot_white`` naming the tag, its values and the rule; nothing
    non-finite anywhere."""
    from testing.dngwriter import scene_dng

    asn = (1e-6, 1.0, 1e6)
    if kind == "bayer":
        buf = io.BytesIO()
        scene_dng(buf, "Nikon 5100 (NPL)", "D65", 64, 96, seed=1, as_shot_neutral=asn)
        data = buf.getvalue()
    else:
        data = _linear_dng(np.uint16, asn)
    for f in ({"white": "as-shot", "format": "png"}, {"white": "as-shot", "response": "json"}):
        r = client.post("/v1/white-balance", files={"file": ("a.dng", data)}, data=f)
        assert r.status_code == 422, (f, r.status_code, r.text[:300])
        body = _strict(r.text)
        assert body["error"] == "no_as_shot_white" and "records no" not in body["detail"], body
        assert "AsShotNeutral" in body["detail"] and "1e+06" in body["detail"] and "factor" in body["detail"], body
    p = client.post("/v1/preview", files={"file": ("a.dng", data)})
    info = _strict(p.headers["X-Preview"])
    assert p.status_code == 200 and any("AsShotNeutral" in w for w in info["warnings"]), info
    assert "camera_multipliers" not in info or all(math.isfinite(v) for v in info["camera_multipliers"]), info
    for ep, f in (("/v1/analyze", {}), ("/v1/white-balance", {"format": "xmp"}), ("/v1/surfaces", {"grid": "2x2"})):
        r = client.post(ep, files={"file": ("a.dng", data)}, data=f)
        assert r.status_code == 200, (ep, r.text[:300])
        _strict(r.headers.get("X-Illuminant") or r.text)
    # /v1/analyze says it too (it had no as_shot block and no word of why: round 8b's "left alone", fixed)
    body = _strict(client.post("/v1/analyze", files={"file": ("a.dng", data)}).text)
    assert "as_shot" not in body and any("AsShotNeutral" in w and "not a usable white" in w
                                         for w in body["warnings"]), body["warnings"]


def test_a_plausible_as_shot_white_is_still_used(client):
    """What holds: an ordinary AsShotNeutral still renders ``white=as-shot``."""
    for data in (scene_dng_bytes(64, 96), _linear_dng(np.uint16)):
        r = client.post("/v1/white-balance", files={"file": ("a.dng", data)}, data={"white": "as-shot",
                                                                                      "response": "json"})
        assert r.status_code == 200 and r.json()["method"] == "as-shot", r.text[:300]


# --- 3. white-balance -q --xmp when the DNG copy cannot be written ------------------------------

def test_white_balance_quiet_xmp_says_when_the_dng_copy_is_not_written(tmp_path, dng):
    """``wandell white-balance -q --xmp RAW OUT`` wrote the image and the
    sidecar but not the DNG copy (``NAME.wandell.dng``, past NAME_MAX for a
    251-byte stem) and printed nothing: without ``-q`` it said "no DNG
    copy: cannot write ...". ``--quiet`` keeps failures, notes and warnings
    on stderr (its help), so it is said there too. (Since round 9b a long
    name is cut, so the copy cannot be written here because a folder holds
    its name and ``--xmp-overwrite`` asks to replace it.)"""
    raw = tmp_path / ("y" * 20 + ".dng")
    raw.write_bytes(dng)
    (tmp_path / ("y" * 20 + ".wandell.dng")).mkdir()
    out = tmp_path / "o.tif"
    r = _cli("white-balance", "-q", "--xmp", "--xmp-overwrite", str(raw), str(out))
    assert out.exists() and (tmp_path / ("y" * 20 + ".xmp")).exists(), (r.stdout[-400:], r.stderr[-400:])
    assert "no DNG copy" in r.stderr and "cannot write" in r.stderr, (r.returncode, r.stdout, r.stderr)
    assert r.stdout == "", r.stdout


# --- 4. OUT_DIR/batch.json: a user's file of that name ------------------------------------------

def test_batch_keeps_a_users_batch_json_and_says_so(tmp_path, dng):
    """``wandell batch`` writes its summary to ``OUT_DIR/batch.json`` and
    replaced a user's file of that name without a word, while round 8 made
    the outputs keep files no batch wrote unless ``--force``. The summary
    follows the same rule: the user's file is kept and a warning on stderr
    (with ``-q`` too) says so; a summary of an earlier run is replaced;
    ``--force`` replaces the user's file; a read-only one is always kept."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    out.mkdir()
    (src / "a.dng").write_bytes(dng)
    mine = out / "batch.json"
    mine.write_text('{"my": "notes"}\n')
    args = ("batch", "--workers", "1", "--format", "jpeg", str(src), str(out))
    r = _cli(*args, "-q")
    assert r.returncode == 0 and (out / "a.jpg").exists(), (r.stdout[-400:], r.stderr[-400:])
    assert mine.read_text() == '{"my": "notes"}\n'
    assert "batch.json" in r.stderr and "kept" in r.stderr and "--force" in r.stderr, r.stderr
    mine.chmod(0o444)
    r = _cli(*args, "--force")
    assert mine.read_text() == '{"my": "notes"}\n' and "read-only" in r.stderr, r.stderr
    mine.chmod(0o644)
    r = _cli(*args, "--force")
    assert r.returncode == 0 and _strict(mine.read_text())["counts"]["total"] == 1, r.stderr
    r = _cli(*args)                         # our own summary of the last run: replaced, no warning
    assert r.returncode == 0 and "batch.json" not in r.stderr, r.stderr
    assert _strict(mine.read_text())["counts"]["skipped"] == 1


# --- 5. /v1/surfaces takes every estimation field /v1/analyze takes ------------------------------

@pytest.mark.parametrize("fields", [
    {"method": "maloney-wandell", "surface_dim": "2", "light_dim": "2"},
    {"method": "maloney-wandell", "surface_dim": "auto", "light_dim": "auto"},
    {"method": "maloney-wandell", "light_model": "fourier"},
    {"method": "maloney-wandell", "light_model": "illuminant-pca", "spatial": "true", "region_size": "16"},
    {"method": "bayes", "spatial": "true", "region_size": "24"},
    {"light_model": "daylight"},
], ids=["dims", "dims-auto", "light-model", "literal-map", "bayes-map", "default-daylight"])
def test_surfaces_take_every_estimation_field_and_answer_analyzes_light(client, dng, fields):
    """``/v1/surfaces`` refused ``region_size``, ``surface_dim``,
    ``light_dim`` and ``light_model`` (422 ``unknown_field``) though each
    changes the light ``/v1/analyze`` answers (the map's regions, the
    literal method's models, the light's spectrum model), and the surfaces
    are read under that light. They are taken as on ``/v1/analyze``: the
    same fields give the same light (and the same map)."""
    a = client.post("/v1/analyze", files={"file": ("a.dng", dng)}, data=fields)
    s = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data={"points": "[[10, 10]]", **fields})
    assert a.status_code == 200 and s.status_code == 200, (a.text[:300], s.text[:300])
    aj, sj = a.json(), s.json()
    assert sj["illuminant"]["camera_rgb"] == aj["illuminant"]["camera_rgb"], (aj["illuminant"], sj["illuminant"])
    assert sj["illuminant"]["spectrum"] == aj["illuminant"]["spectrum"]
    assert sj["method"] == aj["method"] and sj.get("light_map") == aj.get("light_map")
    assert sj["lights"]["found"] == aj["lights"]["found"]


@pytest.mark.parametrize("field,value", [("region_size", "3"), ("surface_dim", "99"), ("light_dim", "x"),
                                         ("light_model", "nope")])
def test_surfaces_refuse_a_bad_estimation_field_naming_it(client, dng, field, value):
    r = client.post("/v1/surfaces", files={"file": ("a.dng", dng)}, data={"points": "[[1, 1]]", field: value,
                                                                            "method": "maloney-wandell"})
    assert r.status_code == 422 and field in r.json()["detail"] and r.json()["error"] != "unknown_field", r.text


# --- 6. /docs examples of the X-Illuminant header --------------------------------------------------

@pytest.mark.parametrize("fmt,name", [("jpeg", "IlluminantHeader"), ("xmp", "EstimateSummary")])
def test_the_docs_examples_of_the_x_illuminant_header_show_its_fields(client, dng, fmt, name):
    """Round 8 added ``confidence`` and ``low_confidence`` to the
    ``X-Illuminant`` header (and ``low_confidence`` to the XMP's summary)
    and declared them, but the examples ``/docs`` shows
    (``service/schemas/examples.json``, regenerated by ``python -m
    testing.response_examples``, never by hand) lacked them. Every field of a
    live header of the estimate is in its example, and the example is the
    one ``/openapi.json`` serves."""
    from service.schemas.examples import EXAMPLES

    r = client.post("/v1/white-balance", files={"file": ("a.dng", dng)}, data={"format": fmt})
    live = _strict(r.headers["X-Illuminant"])
    assert {"confidence", "low_confidence"} <= set(live), live
    assert set(live) <= set(EXAMPLES[name]), sorted(set(live) - set(EXAMPLES[name]))
    served = client.get("/openapi.json").json()["components"]["schemas"][name]["examples"]
    assert EXAMPLES[name] in served
