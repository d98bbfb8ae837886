"""Issue 29, item 4: the REST API describes itself. The JSON answers have
response models (``service.schemas.responses``) that ``/openapi.json``
shows, every key a real answer carries is declared there, downloads are
declared with the media types they send, the description is Markdown
without Sphinx roles, and an unknown form or query field is a 422 naming it
(the web page's own forms still pass)."""

from __future__ import annotations

import io
import json
import re
import time
import typing

import numpy as np
import pytest
from pydantic import BaseModel

from service.schemas import responses as R

from .conftest import isolated_app_client, scene_dng_bytes


@pytest.fixture(scope="module")
def dng() -> bytes:
    return scene_dng_bytes(96, 128)


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    yield from isolated_app_client(tmp_path_factory.mktemp("store"))


def _model_of(annotation):
    """The BaseModel inside an annotation (``X | None``, ``list[X]``), if any."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for a in typing.get_args(annotation):
        m = _model_of(a)
        if m is not None:
            return m
    return None


def undeclared(model: type[BaseModel], doc, where: str = "") -> list[str]:
    """Keys of ``doc`` (recursively, into nested models and lists of them)
    that ``model`` does not declare."""
    if isinstance(doc, list):
        return [k for i, d in enumerate(doc) for k in undeclared(model, d, f"{where}[{i}]")]
    out = []
    for k, v in doc.items():
        f = model.model_fields.get(k)
        if f is None:
            out.append(f"{where}.{k}")
            continue
        sub = _model_of(f.annotation)
        if sub is not None and isinstance(v, (dict, list)):
            out += undeclared(sub, v, f"{where}.{k}")
    return out


def _check(model, doc):
    assert undeclared(model, doc) == []
    model.model_validate(doc)   # the declared types hold too


def test_undeclared_finds_a_missing_key():
    """The check is not blind: a key the model does not declare, nested too."""
    assert undeclared(R.CameraInfo, {"name": "x", "source": "generic", "channels": 3, "approximate": True,
                                     "notes": [], "lens": "?"}) == [".lens"]
    assert undeclared(R.BatchProgress, {"items": [{"index": 0, "colour": 1}]}) == [".items[0].colour"]


def test_analyze_white_balance_and_surfaces_answers_are_their_models(client, dng):
    f = {"file": ("a.dng", dng)}
    r = client.post("/v1/analyze", files=f, data={"method": "bayes", "spatial": "true", "region_size": "32"})
    assert r.status_code == 200, r.text
    assert "light_map" in r.json()
    _check(R.AnalyzeResult, r.json())
    r = client.post("/v1/analyze", files=f, data={"neutral": "[10, 10, 40, 40]"})
    assert r.status_code == 200 and "neutral" in r.json(), r.text
    _check(R.AnalyzeResult, r.json())
    r = client.post("/v1/white-balance", files=f, data={"response": "json"})
    assert r.status_code == 200, r.text
    _check(R.WhiteBalanceResult, r.json())
    r = client.post("/v1/surfaces", files=f, data={"points": "[[10, 10]]", "rects": "[[0, 0, 10, 10]]",
                                                   "grid": "2x2"})
    assert r.status_code == 200, r.text
    _check(R.SurfacesResult, r.json())


def test_render_report_is_its_model(client):
    buf = io.BytesIO()
    np.save(buf, np.random.default_rng(0).uniform(0.05, 0.9, (4, 5, 31)))
    r = client.post("/v1/render", files={"file": ("c.npy", buf.getvalue())},
                    data={"wavelengths": ",".join(str(x) for x in range(400, 710, 10)), "illuminant": "FL11",
                          "response": "json"})
    assert r.status_code == 200, r.text
    _check(R.RenderReport, r.json())


def test_batch_answers_are_their_models(client, dng):
    r = client.post("/v1/batches", files=[("files", ("a.dng", dng)), ("files", ("b.dng", b"not a raw"))],
                    data={"format": "png"})
    assert r.status_code == 202, r.text
    _check(R.BatchCreated, r.json())
    bid = r.json()["id"]
    t_end = time.monotonic() + 120
    while not (doc := client.get(f"/v1/batches/{bid}").json())["settled"] and time.monotonic() < t_end:
        time.sleep(0.2)
    assert doc["settled"] and doc["counts"]["done"] == 1 and doc["counts"]["failed"] == 1, doc
    _check(R.BatchProgress, doc)
    d = client.get(doc["items"][0]["url"])
    assert d.status_code == 200 and d.headers["content-type"] == "image/png"


def test_openapi_shows_fields_media_types_and_markdown(client):
    spec = client.get("/openapi.json").json()
    comps = spec["components"]["schemas"]

    def json_schema(path, method="post"):
        c = spec["paths"][path][method]["responses"]
        ok = c.get("200") or c.get("202")
        ref = ok["content"]["application/json"]["schema"]["$ref"].split("/")[-1]
        return comps[ref]

    for path, method, fields in (("/v1/analyze", "post", {"illuminant", "camera", "diagnostics", "as_shot"}),
                                 ("/v1/white-balance", "post", {"correction_matrix", "illuminant"}),
                                 ("/v1/surfaces", "post", {"surfaces", "wavelengths"}),
                                 ("/v1/render", "post", {"nodes_nm", "error", "bands_read"}),
                                 ("/v1/batches", "post", {"id", "url", "counts"}),
                                 ("/v1/batches/{batch_id}", "get", {"settled", "items", "counts"})):
        assert fields <= set(json_schema(path, method)["properties"]), path
    ill = comps["Illuminant"]["properties"]
    assert "description" in ill["cct"] and "Ohno" in ill["cct"]["description"]
    for path in ("/v1/batches/{batch_id}/items/by-index/{index}", "/v1/batches/{batch_id}/items/by-name/{name}",
                 "/v1/batches/{batch_id}/items/{item}"):
        content = spec["paths"][path]["get"]["responses"]["200"]["content"]
        assert set(content) == {"image/tiff", "image/png", "image/jpeg", "image/x-adobe-dng"}, (path, content)
    assert set(spec["paths"]["/v1/batches/{batch_id}/zip"]["get"]["responses"]["200"]["content"]) == {
        "application/zip"}
    text = spec["info"]["description"] + "".join(
        op.get("description", "") for ops in spec["paths"].values() for op in ops.values())
    assert not re.search(r":(func|mod|class|data|attr|meth):`", text), "Sphinx roles in the API description"


def test_a_misspelled_form_field_is_a_422_naming_it(client, dng):
    r = client.post("/v1/white-balance", files={"file": ("a.dng", dng)}, data={"taget": "A"})
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["error"] == "unknown_field" and "'taget'" in body["detail"] and "did you mean 'target'" in body["detail"]
    assert "accepts:" in body["detail"] and "exposure" in body["detail"]
    r = client.get("/v1/sampling", params={"strategy": "uniform", "n": 4, "chanel": "XYZ"})
    assert r.status_code == 422 and "'chanel'" in r.json()["detail"] and "'channel'" in r.json()["detail"]


def test_the_web_pages_own_forms_still_pass(client, dng):
    """The fields service/static/app.js sends on each endpoint are accepted."""
    f = {"file": ("a.dng", dng)}
    opts = {"camera": "", "method": "auto", "quality": "fast"}
    assert client.post("/v1/analyze", files=f, data={**opts, "neutral": "[10, 10]"}).status_code == 200
    for wb in ({"wb": "camera", "format": "jpeg", "max_side": "1024"},
               {**opts, "wb": "corrected", "target": "D65", "format": "jpeg", "max_side": "1024"}):
        assert client.post("/v1/preview", files=f, data=wb).status_code == 200
    r = client.post("/v1/white-balance", files=f, data={**opts, "format": "xmp", "white": "estimate",
                                                        "target": "D65"})
    assert r.status_code == 200, r.text
    r = client.post("/v1/batches", files=[("files", ("a.dng", dng))],
                    data={**opts, "format": "jpeg", "target": "D65", "lighting": "per-image"})
    assert r.status_code == 202, r.text


def _refs(obj) -> set[str]:
    """The component names an OpenAPI fragment refers to."""
    if isinstance(obj, dict):
        out = {obj["$ref"].split("/")[-1]} if isinstance(obj.get("$ref"), str) else set()
        return out.union(*(_refs(v) for v in obj.values()))
    if isinstance(obj, list):
        return set().union(*(_refs(v) for v in obj))
    return set()


def response_components(spec) -> set[str]:
    """Every component schema an answer's body or header uses, nested ones too."""
    comps = spec["components"]["schemas"]
    todo = _refs([op.get("responses", {}) for ops in spec["paths"].values() for op in ops.values()])
    seen: set[str] = set()
    while todo:
        name = todo.pop()
        if name not in seen:
            seen.add(name)
            todo |= _refs(comps[name]) - seen
    return seen


def test_every_response_model_has_real_examples_that_validate(client):
    """Issue 29, item 4: ``/docs`` shows an example for every JSON answer
    (analyze, white-balance and its X-Illuminant header, surfaces, render,
    batches and their items, errors), and each example is its own model's:
    it validates and declares no undeclared key, so an example cannot drift
    from the model (and the model not from the real answers, above)."""
    spec = client.get("/openapi.json").json()
    comps = spec["components"]["schemas"]
    used = response_components(spec)
    models = {n for n, m in vars(R).items() if isinstance(m, type) and issubclass(m, R._Answer) and m is not R._Answer}
    assert models <= used, models - used            # every response model is in the document
    assert {"AnalyzeResult", "WhiteBalanceResult", "IlluminantHeader", "EstimateSummary", "SurfacesResult",
            "RenderReport", "BatchCreated", "BatchProgress", "BatchItem", "BatchDeleted", "BatchList", "ErrorBody",
            "Health", "CameraList", "ModelsInfo", "SamplingRule", "PreviewInfo"} <= used
    for name in sorted(used):
        examples = comps[name].get("examples")
        assert examples, f"{name} has no example"
        for ex in examples:
            model = getattr(R, name, None)
            if model is not None:
                _check(model, ex)
            else:
                assert name == "ErrorBody", name
                assert set(ex) == {"error", "detail"} and all(isinstance(v, str) and v for v in ex.values())
    # each error answer shows an error of its own kind (a 413 is not shown as a misspelled field)
    kinds = {"413": {"file_too_large", "too_large", "too_many_pixels"}, "415": {"not_camera_raw", "unsupported_format"},
             "422": {"unknown_field", "invalid_parameter"}, "4XX": {"not_found"}}
    for path, ops in spec["paths"].items():
        for op in ops.values():
            for code, r in op["responses"].items():
                media = r.get("content", {}).get("application/json", {})
                if media.get("schema", {}).get("$ref", "").endswith("/ErrorBody"):
                    assert media.get("example", {}).get("error") in kinds[code], (path, code, media.get("example"))
    header = spec["paths"]["/v1/white-balance"]["post"]["responses"]["200"]["headers"]["X-Illuminant"]
    assert [r["$ref"].split("/")[-1] for r in header["schema"]["contentSchema"]["anyOf"]] == [
        "IlluminantHeader", "EstimateSummary"]
    _check(R.IlluminantHeader, json.loads(header["example"]))


def test_the_x_illuminant_header_is_its_model(client, dng):
    f = {"file": ("a.dng", dng)}
    for data in ({"format": "png"}, {"format": "xmp"}, {"format": "jpeg", "neutral": "[10, 10, 40, 40]"}):
        r = client.post("/v1/white-balance", files=f, data=data)
        assert r.status_code == 200, r.text
        model = R.EstimateSummary if data["format"] == "xmp" else R.IlluminantHeader
        _check(model, json.loads(r.headers["X-Illuminant"]))


def test_a_bad_example_is_caught():
    """The checks above can fail: a wrong type, a key the model lacks."""
    good = R.AnalyzeResult.model_config["json_schema_extra"]["examples"][0]
    with pytest.raises(Exception):
        _check(R.AnalyzeResult, {**good, "illuminant": {**good["illuminant"], "cct": "warm"}})
    with pytest.raises(AssertionError):
        _check(R.AnalyzeResult, {**good, "colour": 1})


def test_white_balance_json_gives_the_as_shot_white_as_analyze_does(client, dng):
    """The same document type answers the same fields: /v1/white-balance's
    JSON had the as-shot white without its Temperature/Tint and xy."""
    f = {"file": ("a.dng", dng)}
    a = client.post("/v1/analyze", files=f).json()["as_shot"]
    w = client.post("/v1/white-balance", files=f, data={"response": "json"}).json()["as_shot"]
    assert {"temperature", "tint", "xy"} <= set(a)
    assert w == a


def test_reference_answers_and_json_headers_are_their_models(client, dng):
    """/health, /v1/cameras, /v1/models and /v1/sampling (defined and not)
    have their models too, as do the X-Preview and X-Render-Report headers."""
    _check(R.Health, client.get("/health").json())
    _check(R.CameraList, client.get("/v1/cameras").json())
    _check(R.ModelsInfo, client.get("/v1/models").json())
    for params in ({"strategy": "gauss-ac1c2", "n": 4}, {"strategy": "wiener-points", "n": 4, "illuminant": "A"},
                   {"strategy": "quasi-gauss-xyz", "degrees": "4,4,4"}):
        r = client.get("/v1/sampling", params=params)
        assert r.status_code == 200, r.text
        _check(R.SamplingRule, r.json())
    assert r.json()["defined"] is False and "reason" in r.json()
    f = {"file": ("a.dng", dng)}
    for data in ({"wb": "camera"}, {"wb": "corrected"}, {"wb": "corrected", "white": "5000/+5"}):
        r = client.post("/v1/preview", files=f, data=data)
        assert r.status_code == 200, r.text
        _check(R.PreviewInfo, json.loads(r.headers["X-Preview"]))
    buf = io.BytesIO()
    np.save(buf, np.random.default_rng(0).uniform(0.05, 0.9, (4, 5, 31)))
    r = client.post("/v1/render", files={"file": ("c.npy", buf.getvalue())},
                    data={"wavelengths": ",".join(str(x) for x in range(400, 710, 10)), "format": "png"})
    assert r.status_code == 200, r.text
    _check(R.RenderReport, json.loads(r.headers["X-Render-Report"]))
    spec = client.get("/openapi.json").json()
    for path, header, model in (("/v1/render", "X-Render-Report", "RenderReport"),
                                ("/v1/preview", "X-Preview", "PreviewInfo")):
        h = spec["paths"][path]["post"]["responses"]["200"]["headers"][header]
        assert h["schema"]["contentSchema"]["$ref"].endswith("/" + model)
        _check(getattr(R, model), json.loads(h["example"]))
    assert isinstance(json.loads(h["example"])["ms"], float)
    assert isinstance(json.loads(spec["paths"]["/v1/render"]["post"]["responses"]["200"]["headers"][
        "X-Render-Report"]["example"])["tried"], int)              # the header's own example, not the JSON answer
