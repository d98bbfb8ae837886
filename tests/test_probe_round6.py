"""Round 6 of probing the newest features as a new user and as a hostile
client (docs/probe_round6.md): each test is the minimal reproduction of one
fault found, through the command line as users run it (``python -m
service.cli``) or the real ASGI stack (FastAPI's TestClient), and holds once
the fault is fixed."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from .conftest import isolated_app_client, scene_dng_bytes

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


@pytest.fixture(scope="module")
def dng() -> bytes:
    return scene_dng_bytes(64, 96)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")


def _cli(*args: str):
    env = dict(os.environ, PYTHONPATH=ROOT)
    return subprocess.run([sys.executable, "-m", "service.cli", *args], capture_output=True, text=True,
                          timeout=300, env=env, cwd=ROOT)


def _strict(text: str):
    def bad(name):
        raise ValueError(f"non-finite JSON constant {name}")
    return json.loads(text, parse_constant=bad)


# --- 1. wandell batch --xmp, run again ---------------------------------------------------

def test_a_rerun_of_batch_xmp_does_not_take_its_own_dng_copies_as_photographs(tmp_path, dng):
    """``wandell batch --xmp IN OUT`` writes, for each DNG, a copy with the
    white balance inside beside it (``IMG.wandell.dng``). Run again (a
    rerun, as after Ctrl-C or to add photographs), the copies were new
    inputs: 2 more outputs (``OUT/a.wandell.png``), 2 copies of the copies
    (``IN/a.wandell.wandell.dng``) and their sidecars, one generation more at
    each run. Now the copies are left out, as the sidecars are (not listed
    as "not processed"); the rerun skips the finished photographs and
    writes nothing new."""
    src, out = tmp_path / "in", tmp_path / "out"
    src.mkdir()
    for name in ("a.dng", "b.dng"):
        (src / name).write_bytes(dng)
    r = _cli("batch", "--xmp", "--format", "png", "--workers", "1", str(src), str(out))
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert sorted(p.name for p in src.iterdir()) == ["a.dng", "a.wandell.dng", "a.xmp", "b.dng", "b.wandell.dng",
                                                     "b.xmp"]
    first = sorted(p.name for p in out.iterdir())
    r = _cli("batch", "--xmp", "--format", "png", "--workers", "1", str(src), str(out))
    assert r.returncode == 0, (r.stdout, r.stderr)
    assert sorted(p.name for p in src.iterdir()) == ["a.dng", "a.wandell.dng", "a.xmp", "b.dng", "b.wandell.dng",
                                                     "b.xmp"], "copies of the copies were written"
    assert sorted(p.name for p in out.iterdir()) == first, "the copies were processed as photographs"
    assert "0 done, 2 skipped" in r.stdout and "2 in all" in r.stdout, r.stdout
    assert "not processed" not in r.stdout, r.stdout       # our outputs, as the sidecars
    # a .wandell.dng whose original is not there is a photograph like any other
    (src / "a.dng").rename(tmp_path / "a.dng")
    (src / "a.xmp").unlink()
    r = _cli("batch", "--format", "png", "--workers", "1", str(src), str(out))
    assert r.returncode == 0 and "a.wandell.png" in {p.name for p in out.iterdir()}, (r.stdout, r.stderr)


# --- 2. spatial: what the answer says of the map ------------------------------------------

def _two_light_tiff(rows: int = 200, cols: int = 300) -> bytes:
    """A linear 16-bit TIFF (no camera metadata: the generic camera) of
    random colours, its left half under a yellowish light and its right
    half under a bluish one (camera RGB gains 1, 1, 0.4 and 0.4, 1, 1)."""
    import io

    import numpy as np
    import tifffile

    img = np.random.default_rng(0).random((rows, cols, 3)) * 30000 + 1000
    half = cols // 2
    img[:, :half] *= (1.0, 1.0, 0.4)
    img[:, half:] *= (0.4, 1.0, 1.0)
    buf = io.BytesIO()
    tifffile.imwrite(buf, img.astype(np.uint16))
    return buf.getvalue()


@pytest.mark.parametrize("method, data", [("maloney-wandell", "two_lights"), ("auto", "three_pixels")])
def test_a_fallback_says_one_light_and_why_not_a_map_it_did_not_make(client, method, data):
    """``method=maloney-wandell&spatial=true`` where the literal method
    cannot run (here its light gives a non-positive camera response) falls
    back to shades-of-gray with one light, but ``lights.reason`` still read
    "a light map was asked for (spatial=true): the subspace method on
    overlapping regions of 50 pixels a side, each with its own light" beside
    ``found: 1`` (and ``diagnostics.spatial_decision`` said "light map");
    ``auto`` on a 3x3 image (the learnt estimator cannot run) gave an empty
    reason. Now both say one light, that the method asked for could not run,
    why, and which fallback made the light."""
    import io

    import numpy as np
    import tifffile

    if data == "two_lights":
        body = _two_light_tiff()
    else:
        buf = io.BytesIO()
        tifffile.imwrite(buf, (np.random.default_rng(0).random((3, 3, 3)) * 30000 + 1000).astype(np.uint16))
        body = buf.getvalue()
    r = client.post("/v1/analyze", files={"file": ("x.tif", body)}, data={"method": method, "spatial": "true"})
    assert r.status_code == 200, r.text[:300]
    b = _strict(r.text)
    assert b["method"] == "shades-of-gray" and b["diagnostics"]["decision"].startswith("fallback to"), b["method"]
    assert b["lights"]["found"] == 1 and "light_map" not in b
    assert b["diagnostics"]["spatial_decision"] == "one light", b["diagnostics"]["spatial_decision"]
    reason = b["lights"]["reason"]
    assert reason.startswith("one light") and "could not run" in reason and "shades-of-gray" in reason, reason
    assert "overlapping regions" not in reason, reason


def test_spatial_true_is_a_map_where_the_learnt_windows_cannot_read_the_image(client):
    """``spatial=true`` is "always a map" (docs/mixed_light.md, the field's
    description), but on a TIFF the learnt estimator cannot read (the
    generic camera: outside its training range) the answer was one light,
    "its windows cannot tell whether the light varies", on a picture whose
    halves are under clearly different lights. Now the light posterior's
    regions make the map, as they do for ``method=bayes`` and for a
    ``region_size``; ``/v1/white-balance`` corrects by it."""
    body = _two_light_tiff()
    r = client.post("/v1/analyze", files={"file": ("two.tif", body)}, data={"spatial": "true"})
    assert r.status_code == 200, r.text[:300]
    b = _strict(r.text)
    assert b["lights"]["found"] == 2 and b["lights"]["decision"] == "light map", b["lights"]
    lm = b["light_map"]
    rgb = np.asarray(lm["camera_rgb"], float)
    assert np.all(np.isfinite(rgb)) and rgb.shape[-1] == 3
    # the map sees the two halves: blue over red is higher on the right than on the left
    ratio = rgb[..., 2] / rgb[..., 0]
    assert ratio[:, -1].mean() > ratio[:, 0].mean(), ratio
    r = client.post("/v1/white-balance", files={"file": ("two.tif", body)}, data={"spatial": "true", "format": "png"})
    assert r.status_code == 200, r.text[:300]
    assert _strict(r.headers["x-illuminant"])["lights"]["found"] == 2
    r = client.post("/v1/analyze", files={"file": ("two.tif", body)}, data={"spatial": "false"})
    assert _strict(r.text)["lights"]["found"] == 1


# --- 3. the light posterior's regions: bounded like the literal map's ---------------------

@pytest.mark.parametrize("method, spatial", [("bayes", "true"), ("auto", "true"), ("bayes", "auto")])
def test_a_region_size_for_the_posterior_map_is_bounded_by_the_light_map_region_limit(client, dng, env_settings,
                                                                                        method, spatial):
    """``spatial=true&region_size=8`` with ``method=bayes`` (or ``auto``,
    whose map is the posterior's when a region size is asked for) made a
    grid of regions, each with its own light posterior, of any size: 8,772
    regions on Blackmagic.dng's accurate analysis image took 17-22 s (0.4 s
    without the region size), where ``WANDELL_MAX_LIGHT_MAP_REGIONS`` bounds
    the literal method's map to 4,096 (docs/limits.md). Now the same limit
    bounds the posterior's regions: past it a 413 ``too_many_regions``
    naming it, before any estimate (with ``spatial=auto`` too, whether or
    not this image's windows would have asked for the regions); under it
    the answer is as before."""
    env_settings(max_light_map_regions=16)
    f = {"file": ("s.dng", dng)}     # 64 x 96: a 32 x 48 analysis image, 4 x 6 regions of 8
    r = client.post("/v1/analyze", files=f, data={"method": method, "spatial": spatial, "region_size": "8"})
    assert r.status_code == 413, r.text[:300]
    body = _strict(r.text)
    assert body["error"] == "too_many_regions"
    assert "WANDELL_MAX_LIGHT_MAP_REGIONS" in body["detail"] and "24 regions" in body["detail"], body["detail"]
    r = client.post("/v1/analyze", files=f, data={"method": method, "spatial": spatial, "region_size": "16"})
    assert r.status_code == 200, r.text[:300]      # 2 x 3 regions
    assert _strict(r.text)["lights"]["found"] == (2 if spatial == "true" else 1)
    r = client.post("/v1/analyze", files=f, data={"method": method, "spatial": "false", "region_size": "8"})
    assert r.status_code == 200, r.text[:300]      # one light: no regions


# --- 4. the XMP sidecar and format=dng of a white the user set ----------------------------

def test_a_white_the_user_set_without_a_temperature_is_named_as_the_users(client):
    """``format=xmp`` with ``white=50000/+150`` on a TIFF (the generic
    camera) was refused as "the estimated light is too far from the
    Planckian locus": the light was the user's white, not an estimate (round
    4 fixed the same confusion for rendering, not for the sidecar). Now the
    422 ``no_temperature`` names the user's white and what to change; with
    ``format=dng`` a TIFF is ``not_a_raw`` whatever the white, as it is for
    a white that has a temperature."""
    body = _two_light_tiff(40, 60)
    r = client.post("/v1/white-balance", files={"file": ("t.tif", body)},
                    data={"white": "50000/+150", "format": "xmp"})
    assert r.status_code == 422, r.text[:300]
    b = _strict(r.text)
    assert b["error"] == "no_temperature", b
    assert "the white you set (white='50000/+150')" in b["detail"] and "estimated" not in b["detail"], b["detail"]
    for white in ("50000/+150", "5000/+10"):
        r = client.post("/v1/white-balance", files={"file": ("t.tif", body)}, data={"white": white, "format": "dng"})
        assert r.status_code == 422 and _strict(r.text)["error"] == "not_a_raw", (white, r.text[:300])


# --- 5. a sensitivities CSV of very many columns ---------------------------------------------

def test_a_sensitivities_csv_with_too_many_channel_columns_is_refused_before_it_is_resampled(client, dng):
    """A sensitivities CSV of three wavelengths and 2,000,000 channel
    columns (12 MB, under the CSV's 64,000,000-value limit) was resampled
    channel by channel before the image's 3 channels refused it: 20 s and
    +1.9 GB of server memory for one request (``/v1/analyze`` and
    ``/v1/surfaces``), bounded by no documented limit. Now more than
    ``recovery.cameras.MAX_CSV_CHANNELS`` (64) channel columns are a 422
    ``bad_csv`` saying so, before any resampling; 4 columns still reach the
    camera check (the image has 3 channels)."""
    from recovery.cameras import MAX_CSV_CHANNELS

    def csv(n):
        return "".join(f"{w}," + ",".join(["1"] * n) + "\n" for w in (400, 550, 700)).encode()

    for path, extra in (("/v1/analyze", {}), ("/v1/surfaces", {"grid": "2x2"})):
        r = client.post(path, files={"file": ("s.dng", dng), "sensitivities": ("s.csv", csv(MAX_CSV_CHANNELS + 1))},
                        data=extra)
        assert r.status_code == 422, r.text[:300]
        b = _strict(r.text)
        assert b["error"] == "bad_csv" and f"more than {MAX_CSV_CHANNELS}" in b["detail"], b
    r = client.post("/v1/analyze", files={"file": ("s.dng", dng), "sensitivities": ("s.csv", csv(4))})
    assert r.status_code == 422 and "has 4" in _strict(r.text)["detail"], r.text[:300]


@pytest.mark.parametrize("given, named", [({"neutral": "[0, 0, 8, 8]"}, "neutral"),
                                          ({"white": "5000/+10"}, "white="), ({"white": "as-shot"}, "white=as-shot")])
def test_a_white_given_with_spatial_true_says_why_one_light(client, dng, given, named):
    """``spatial=true`` with ``neutral`` (or ``white=as-shot`` or a
    Temperature/Tint) answers one light, the one given, with no map: right,
    but ``lights.reason`` was empty (in the JSON and in ``X-Illuminant``), so
    the user who asked for a map was not told why there is none. Now the
    reason names the white given and where a map comes from."""
    for data in ({"response": "json"}, {"format": "png"}):
        r = client.post("/v1/white-balance", files={"file": ("s.dng", dng)}, data={"spatial": "true", **given, **data})
        assert r.status_code == 200, r.text[:300]
        lights = (_strict(r.text) if "response" in data else _strict(r.headers["x-illuminant"]))["lights"]
        assert lights["found"] == 1 and lights["reason"].startswith("one light: "), lights
        assert named in lights["reason"] and "light map comes from the estimate" in lights["reason"], lights
