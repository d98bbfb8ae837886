"""Issue 13, item 7: /docs works offline and the OpenAPI document says what
every parameter means, accepts and looks like."""

from __future__ import annotations

import re

import pytest
from fastapi.testclient import TestClient

from service.app import app


@pytest.fixture(scope="module")
def client():
    with TestClient(app) as c:
        yield c


@pytest.fixture(scope="module")
def spec(client):
    r = client.get("/openapi.json")
    assert r.status_code == 200
    return r.json()


def test_docs_page_loads_only_from_this_app(client):
    r = client.get("/docs")
    assert r.status_code == 200 and "SwaggerUIBundle" in r.text
    urls = re.findall(r"""(?:src|href)\s*=\s*["']([^"']+)["']""", r.text)
    urls += re.findall(r"""url:\s*['"]([^'"]+)['"]""", r.text)
    assert urls
    for u in urls:
        assert not re.match(r"^(https?:)?//", u), f"/docs fetches {u} from another host"
    for u in (u for u in urls if u.startswith("/") and not u.startswith("/openapi")):
        a = client.get(u)
        assert a.status_code == 200 and len(a.content) > 10_000, u
        assert a.headers["content-type"].split(";")[0] in ("text/javascript", "text/css"), u


def test_unknown_docs_asset_is_a_json_404(client):
    r = client.get("/docs-assets/../../etc/passwd")
    assert r.status_code == 404
    r = client.get("/docs-assets/index.html")
    assert r.status_code == 404 and set(r.json()) >= {"error", "detail"}


def _fields(spec):
    comps = spec["components"]["schemas"]
    for path, ops in spec["paths"].items():
        for m, op in ops.items():
            for p in op.get("parameters", []):
                yield path, m, p["name"], p.get("schema", {}), p
            for c in op.get("requestBody", {}).get("content", {}).values():
                sch = comps.get(c["schema"].get("$ref", "").split("/")[-1], {})
                for name, prop in sch.get("properties", {}).items():
                    yield path, m, name, prop, prop


def test_every_parameter_has_a_description_and_examples(spec):
    missing = [(path, name) for path, m, name, sch, holder in _fields(spec)
               if not holder.get("description")]
    assert not missing, missing
    from service.openapi_docs import PARAMS

    # examples are in the descriptions (issue 19, item 3: see the next test)
    no_example = [(path, name) for path, m, name, sch, holder in _fields(spec)
                  if PARAMS.get(name, (None, None, None))[2] and "Examples: `" not in holder["description"]]
    assert not no_example, no_example
    neutral = next(h for p, m, n, s, h in _fields(spec) if p == "/v1/analyze" and n == "neutral")
    assert "Examples: `[1200, 2040]`, `[100, 200, 140, 260]`, `[[1200, 2040], [1500, 800, 1540, 860]]`." in \
        neutral["description"]


def _keywords(obj, key):
    if isinstance(obj, dict):
        return (1 if key in obj else 0) + sum(_keywords(v, key) for v in obj.values())
    if isinstance(obj, list):
        return sum(_keywords(v, key) for v in obj)
    return 0


def test_no_example_becomes_a_value_in_try_it_out(spec):
    """Issue 19, item 3: Swagger UI 5 fills "Try it out" with each field's
    first example (and an optional form field without one with "string", 0
    or the first choice), then sends it: every try was a 422 or ran with
    other options than the defaults. No field carries an example keyword;
    an optional form field without a value of its own defaults to "" (sent
    empty, which FastAPI reads as absent), the others to their default."""
    for path, m, name, sch, holder in _fields(spec):
        assert _keywords(sch, "examples") == _keywords(sch, "example") == 0, (path, name, sch)
        assert "examples" not in holder and "example" not in holder, (path, name)
    comps = spec["components"]["schemas"]
    from service.openapi_docs import _is_file

    for path, ops in spec["paths"].items():
        for op in ops.values():
            for c in op.get("requestBody", {}).get("content", {}).values():
                sch = comps[c["schema"]["$ref"].split("/")[-1]]
                for name, prop in sch["properties"].items():
                    if name not in sch.get("required", []) and not _is_file(prop):
                        assert "default" in prop, (path, name, prop)


@pytest.mark.parametrize("path,name,values", [
    ("/v1/white-balance", "format", {"tiff", "png", "png16", "jpeg", "xmp"}),
    ("/v1/white-balance", "method", {"auto", "maloney-wandell", "gray-world"}),
    ("/v1/white-balance", "output", {"sRGB", "linear-sRGB", "Display P3"}),
    ("/v1/preview", "wb", {"camera", "corrected"}),
    ("/v1/surfaces", "format", {"json", "csv"}),
])
def test_fixed_choices_are_enumerated(spec, path, name, values):
    for p, m, n, sch, holder in _fields(spec):
        if p == path and n == name:
            enum = set(sch.get("enum") or next((s.get("enum") for s in sch.get("anyOf", []) if s.get("enum")), []))
            assert values <= enum, (path, name, enum)
            return
    pytest.fail(f"{path} has no {name}")


def test_white_balance_declares_images_header_and_errors(spec):
    op = spec["paths"]["/v1/white-balance"]["post"]
    ok = op["responses"]["200"]
    assert {"image/tiff", "image/png", "image/jpeg"} <= set(ok["content"])
    assert "X-Illuminant" in ok["headers"] and "exposure" in ok["headers"]["X-Illuminant"]["description"]
    for code in ("413", "415", "422"):
        r = op["responses"][code]
        assert r["description"] and r["content"]["application/json"]["schema"]["$ref"].endswith("/ErrorBody")
    err = spec["components"]["schemas"]["ErrorBody"]
    assert set(err["required"]) == {"error", "detail"}
