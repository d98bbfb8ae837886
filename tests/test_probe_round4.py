"""Round 4 of probing the service as a hostile-but-realistic user would
(docs/probe_round4.md): each test is the minimal reproduction of one fault
found, through the real ASGI stack (FastAPI's TestClient), and holds once
the fault is fixed."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.schemas import responses as R
from testing.dngwriter import scene_dng


@pytest.fixture(scope="module")
def dng() -> bytes:
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D65", 64, 96, seed=1)
    return buf.getvalue()


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("WANDELL_DATA_DIR", str(tmp_path_factory.mktemp("store")))
    from service.app import app
    from service.routers import batches
    from service.settings import get_settings

    get_settings.cache_clear()
    batches.stop_runner()
    with TestClient(app, base_url="http://127.0.0.1") as c:
        yield c
    batches.stop_runner()
    mp.undo()
    get_settings.cache_clear()


def _strict(text: str):
    def bad(name):
        raise ValueError(f"non-finite JSON constant {name}")
    return json.loads(text, parse_constant=bad)


@pytest.mark.parametrize("fmt", ["xmp", "dng"])
def test_response_json_answers_json_whatever_the_format(client, dng, fmt):
    """``response=json`` is "the estimate and correction matrix only"
    (README, the field's description), but with ``format=xmp`` or
    ``format=dng`` the answer was the sidecar (application/rdf+xml) or the
    DNG: a client asking for JSON got a file it cannot parse."""
    r = client.post("/v1/white-balance", files={"file": ("s.dng", dng)},
                    data={"format": fmt, "response": "json"})
    assert r.status_code == 200, r.text[:300]
    assert r.headers["content-type"].startswith("application/json"), r.headers["content-type"]
    R.WhiteBalanceResult.model_validate(_strict(r.text))


def test_a_repeated_form_field_is_refused_not_resolved_to_its_last_value(client, dng):
    """``method=auto&method=bayes`` ran bayes with a 200 (FastAPI keeps the
    last value), as a misspelled field was ignored before issue 29: the
    user cannot tell which of the two was used. Now a 422 naming the field;
    a list field (a batch's ``files``) still takes one value per part."""
    f = {"file": ("s.dng", dng)}
    r = client.post("/v1/analyze", files=f, data={"method": ["auto", "bayes"]})
    assert r.status_code == 422, r.text[:300]
    body = _strict(r.text)
    assert body["error"] == "repeated_field" and "'method'" in body["detail"]
    r = client.post("/v1/white-balance", files=[("file", ("a.dng", dng)), ("file", ("b.dng", dng))],
                    data={"format": "png"})
    assert r.status_code == 422 and "'file'" in r.json()["detail"], r.text[:300]
    r = client.delete("/v1/batches/0123456789abcdef?remove=true&remove=false")
    assert r.status_code == 422 and r.json()["error"] == "repeated_field", r.text[:300]
    r = client.post("/v1/batches", files=[("files", ("a.dng", dng)), ("files", ("b.dng", dng))],
                    data={"format": "jpeg"})
    assert r.status_code == 202, r.text[:300]


@pytest.mark.parametrize("dims", [{"light_dim": "auto"}, {"surface_dim": "auto", "spatial": "true"}])
def test_automatic_model_order_on_an_image_with_no_usable_pixel_is_a_422(client, dims):
    """``method=maloney-wandell`` with ``surface_dim`` or ``light_dim``
    ``auto`` (BIC) on an image whose every pixel is masked (all saturated
    here) was a 500: ``recovery.model_order.select_dimensions`` took the
    maximum of an empty array. The same request without ``auto`` was the
    422 ``insufficient_surface_variation`` it is now."""
    from testing.dngwriter import write_dng

    buf = io.BytesIO()
    write_dng(buf, np.full((48, 64), 16383, np.uint16), black_level=512, white_level=16383)
    r = client.post("/v1/analyze", files={"file": ("sat.dng", buf.getvalue())},
                    data={"method": "maloney-wandell", **dims})
    assert r.status_code == 422, r.text[:300]
    assert _strict(r.text)["error"] == "insufficient_surface_variation"
