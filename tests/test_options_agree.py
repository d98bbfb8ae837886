"""Issue 18: each request option is declared once (service.schemas.options),
so the OpenAPI document's form fields, the CLI's ``--help`` and the README's
options table list the same accepted values and defaults."""

from __future__ import annotations

import contextlib
import io
import os
import re

import pytest
from fastapi.testclient import TestClient

from service import cli
from service.app import app
from service.schemas import options_table

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ENDPOINTS = ("/v1/analyze", "/v1/white-balance", "/v1/preview", "/v1/surfaces", "/v1/batches", "/v1/render")
#: Where an endpoint narrows (or widens) a field's values on purpose: (path, name) -> values.
#: a command that takes more than the README's row lists: batches also write DNGs
CLI_WIDENED = {("batch", "format"): ["dng"]}
NARROWED = {("/v1/white-balance", "format"): {"tiff", "png", "png16", "jpeg", "jpg", "xmp", "dng"},
            ("/v1/batches", "format"): {"tiff", "png", "png16", "jpeg", "jpg", "dng"},
            ("/v1/preview", "format"): {"jpeg", "jpg", "png"},
            ("/v1/surfaces", "format"): {"json", "csv"},
            ("/v1/render", "format"): {"tiff", "png", "png16"},
            ("/v1/render", "output"): {"sRGB", "linear-sRGB"}}


@pytest.fixture(scope="module")
def spec():
    with TestClient(app) as c:
        return c.get("/openapi.json").json()


def _readme_rows() -> dict:
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        text = f.read()
    table = text.split("<!-- options-table")[1].split("<!-- /options-table -->")[0]
    rows = {}
    for line in table.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) == 4 and cells[0].startswith("`"):
            name = cells[0].strip("`")
            choices = re.findall(r"`([^`]*)`", cells[3]) if cells[3].startswith("`") else None
            rows[name] = (cells[2].strip("`") or None, choices)
    return rows


def _form_fields(spec, path) -> dict:
    comps = spec["components"]["schemas"]
    body = spec["paths"][path]["post"]["requestBody"]["content"]
    sch = comps[next(iter(body.values()))["schema"]["$ref"].split("/")[-1]]
    return sch["properties"]


def _enum(prop):
    return prop.get("enum") or next((s["enum"] for s in prop.get("anyOf", []) if s.get("enum")), None)


def _flag_help(text: str, flag: str) -> str | None:
    """The help of ``flag`` in ``--help`` output (on its line, or the next
    when the flag is long)."""
    lines = text.splitlines()
    for i, ln in enumerate(lines):
        if ln.strip().startswith(flag + " ") or ln.strip() == flag:
            nxt = lines[i + 1] if i + 1 < len(lines) else ""
            return ln + (" " + nxt.strip() if nxt.startswith("   ") and not nxt.strip().startswith("-") else "")
    return None


def _cli_help(command: str, monkeypatch) -> str:
    monkeypatch.setenv("COLUMNS", "10000")       # one line per option: nothing wrapped
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        cli.main([command, "--help"])
    return out.getvalue()


def test_readme_holds_the_generated_table():
    with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
        assert options_table() in f.read(), "README's options table is stale: paste service.schemas.options_table()"


def test_openapi_cli_and_readme_list_the_same_choices(spec, monkeypatch):
    rows = _readme_rows()
    assert {"method", "quality", "output", "format", "lighting", "neutral", "exposure"} <= set(rows)
    helps = {c: _cli_help(c, monkeypatch) for c in ("analyze", "white-balance", "batch")}
    checked = 0
    for name, (default, choices) in rows.items():
        field = name.split(" ")[0]
        for path in ENDPOINTS:
            prop = _form_fields(spec, path).get(field)
            if prop is None or (field == "format" and (name == "format (surfaces)") != (path == "/v1/surfaces")):
                continue
            if choices is not None:
                want = NARROWED.get((path, field), set(choices))
                assert set(_enum(prop) or ()) == want, (path, field, _enum(prop), want)
                checked += 1
            if (path, field) not in NARROWED and name != "format (surfaces)":
                assert str(prop.get("default")) == str(default if default is not None else ""), (path, field, prop)
        flag = "--" + field.replace("_", "-")
        for command, text in helps.items():
            line = _flag_help(text, flag)
            if line is None or choices is None or name == "format (surfaces)":
                continue
            listed = re.search(r"\(one of: ([^)]*)\)", line).group(1).split(", ")
            assert listed == choices + CLI_WIDENED.get((command, field), []), (command, flag, listed, choices)
            checked += 1
    assert checked > 20


def test_method_lists_are_identical_everywhere(spec, monkeypatch):
    from recovery import METHODS

    methods = list(METHODS)
    assert {"learned", "bayes"} <= set(methods)
    for path in ENDPOINTS[:-1]:       # /v1/render renders given spectra: no estimate
        assert _enum(_form_fields(spec, path)["method"]) == methods, path
    assert _readme_rows()["method"][1] == methods
    for command in ("analyze", "white-balance", "batch"):
        line = _flag_help(_cli_help(command, monkeypatch), "--method")
        assert re.search(r"\(one of: ([^)]*)\)", line).group(1).split(", ") == methods
    with TestClient(app) as c:
        assert c.get("/v1/models").json()["methods"] == methods


def test_sampling_query_parameters_are_the_declared_ones(spec):
    """``GET /v1/sampling``'s query parameters are the fields of the
    ``Sampling`` model (SPECTRAL's rule fields), with their declared types;
    the rule's name is required, and a missing one is the service's 422."""
    from service.schemas import Sampling
    from service.schemas.options import option_fields

    params = {p["name"]: p for p in spec["paths"]["/v1/sampling"]["get"]["parameters"]}
    fields = option_fields(Sampling)
    assert set(params) == set(fields) == {"strategy", "n", "channel", "degrees", "illuminant"}
    assert all(p["in"] == "query" for p in params.values())
    assert params["strategy"]["required"] and not any(params[k].get("required") for k in fields if k != "strategy")
    client = TestClient(app, base_url="http://127.0.0.1:8000")
    r = client.get("/v1/sampling")
    assert r.status_code == 422 and r.json()["error"] == "invalid_parameter" and "strategy" in r.json()["detail"]
    r = client.get("/v1/sampling", params={"strategy": "gauss-ac1c2", "channel": "Q"})
    assert r.status_code == 422 and "channel" in r.json()["detail"]


def test_the_pages_method_words_come_from_the_registry_and_match_the_shipped_model():
    """The page says "The light was estimated by WORDS" with the registry's
    words (``GET /v1/models`` ``method_words``; app.js keeps no copy), and
    what they say of the learnt model's training data is the shipped model's
    own record."""
    from recovery import learned as L
    from recovery.methods import METHODS

    client = TestClient(app, base_url="http://127.0.0.1:8000")
    words = client.get("/v1/models").json()["method_words"]
    assert words == {k: m.words for k, m in METHODS.items()} and all(words.values())
    info = L.load_model().info
    assert f"{sum(info['benchmarks'].values()):,} real photographs of {len(info['cameras'])} cameras" in words["learned"]
    with open(os.path.join(ROOT, "service", "static", "app.js"), encoding="utf-8") as f:
        js = f.read()
    assert "let METHOD_WORDS = {};" in js and "models.method_words" in js
    assert not re.search(r'"learned":\s*"the learnt', js)         # no second copy of the words
