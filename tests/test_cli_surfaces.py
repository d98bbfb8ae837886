"""``wandell surfaces``: reflectances of one file from the command line, as ``POST /v1/surfaces`` gives them
(the same answer, limits and errors; JSON or CSV on stdout), run as users run it (``python -m service.cli``)."""

from __future__ import annotations


import numpy as np
import pytest

from .conftest import isolated_app_client, run_cli, scene_dng_bytes, strict_json


@pytest.fixture(scope="module")
def dng(tmp_path_factory):
    path = tmp_path_factory.mktemp("surf") / "scene.dng"
    path.write_bytes(scene_dng_bytes(96, 128, light="A", seed=3))
    return path


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"), base_url="http://127.0.0.1")


def test_the_cli_answers_what_the_endpoint_answers(dng, client):
    """The same points and rectangle with the measured-surface metamer set: the CLI's JSON is the endpoint's
    (reflectances, bands and ranges equal to rounding: the same pipeline on the same file), and the CSV the
    endpoint's CSV line for line."""
    regions = {"points": "[[20, 30], [70, 100]]", "rects": "[[0, 0, 40, 40]]", "metamers": "true",
               "metamer_model": "measured"}
    r = run_cli("surfaces", str(dng), "--points", regions["points"], "--rects", regions["rects"], "--metamers",
                "--metamer-model", "measured")
    assert r.returncode == 0, r.stderr
    mine = strict_json(r.stdout)
    rest = client.post("/v1/surfaces", files={"file": ("scene.dng", dng.read_bytes())}, data=regions)
    assert rest.status_code == 200, rest.text
    theirs = strict_json(rest.text)
    assert mine["method"] == theirs["method"] and mine["wavelengths"] == theirs["wavelengths"]
    assert "measured surfaces" in mine["metamers"]
    assert len(mine["surfaces"]) == len(theirs["surfaces"]) == 3
    for a, b in zip(mine["surfaces"], theirs["surfaces"]):
        assert a["kind"] == b["kind"] and a["where"] == b["where"]
        for k in ("reflectance", "reflectance_std", "metamer_lower", "metamer_upper"):
            np.testing.assert_allclose(a[k], b[k], rtol=1e-9, atol=1e-12, err_msg=k)
    csv = run_cli("surfaces", str(dng), "--grid", "2x3", "--format", "csv")
    assert csv.returncode == 0, csv.stderr
    rest_csv = client.post("/v1/surfaces", files={"file": ("scene.dng", dng.read_bytes())},
                           data={"grid": "2x3", "format": "csv"})
    assert csv.stdout.splitlines() == rest_csv.text.splitlines()
    assert len(csv.stdout.splitlines()) == 1 + 6


@pytest.mark.parametrize("args, code, words", [
    ((), 2, "give at least one of points, rects or grid"),
    (("--grid", "9x9", "--metamers"), 2, "at most 64"),
    (("--points", "x"), 2, "points is not valid JSON"),
    (("--points", "[[1, 1]]", "--format", "xml"), 2, "format must be json or csv"),
    (("--points", "[[1, 1]]", "--metamers", "--metamer-model", "smooth"), 2, "metamer_model must be physical or measured"),
    (("--points", "[[5000, 1]]",), 1, "outside the 96x128 image"),
])
def test_bad_regions_are_named_with_the_endpoints_words(dng, args, code, words):
    r = run_cli("surfaces", str(dng), *args)
    assert r.returncode == code, (r.returncode, r.stderr)
    assert words in r.stderr and r.stdout == ""
    assert "Traceback" not in r.stderr


def test_a_missing_file_is_a_usage_error():
    r = run_cli("surfaces", "no-such-file.dng", "--points", "[[1, 1]]")
    assert r.returncode == 2 and "does not exist" in r.stderr
