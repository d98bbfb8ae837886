"""Property-based run of the whole OpenAPI schema (issue 6): every operation
the app documents, a bounded number of generated requests each, through the
ASGI app in-process.

Checks, for every response:

* never a 5xx (schemathesis ``not_a_server_error``);
* the body conforms to the response schema the operation declares for that
  status (``response_schema_conformance``; the service documents its error
  body ``{"error", "detail"}`` for 422 and the 4XX range, see
  :func:`service.errors.document_error_responses`);
* any JSON body, and the ``X-Illuminant`` header, parse under strict JSON
  (no NaN or Inf: DESIGN.md, "never NaN in JSON"); a 4xx JSON body has a
  string ``error`` and ``detail``.

The operations are read from the schema at collection time, so endpoints
added later (batches, render, sampling, the web page) are covered without
editing this file. A multipart ``file`` field is, for half of the examples
(a Hypothesis boolean), replaced by a small valid DNG from
:mod:`testing.dngwriter`, so the generated options reach the estimator and
the encoder instead of stopping at the decoder (then generated ``None``
values are left out rather than sent as the string ``"null"``). ``WANDELL_SCHEMATHESIS_EXAMPLES``
sets the examples per operation (default 40, sized to keep the run under a
minute on 2 shared cores).
"""

from __future__ import annotations

import io
import json
import os

import pytest

schemathesis = pytest.importorskip("schemathesis")

from hypothesis import HealthCheck, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from schemathesis.checks import not_a_server_error  # noqa: E402
from schemathesis.specs.openapi.checks import response_schema_conformance  # noqa: E402

from service.app import app  # noqa: E402
from testing.dngwriter import scene_dng  # noqa: E402

EXAMPLES = int(os.environ.get("WANDELL_SCHEMATHESIS_EXAMPLES", "40"))

schema = schemathesis.openapi.from_asgi("/openapi.json", app)
# the schema now carries examples (issue 13, item 7); schemathesis cannot run its
# examples phase in a test that also takes @schema.given(), so this test fuzzes
# (and covers) only; the examples are checked by tests/test_docs.py
schema.config.phases.update(phases=["coverage", "fuzzing"])


def _small_dng() -> bytes:
    # 48 x 64 is above LibRaw's 22-pixel minimum and decodes in milliseconds
    buf = io.BytesIO()
    scene_dng(buf, "Nikon 5100 (NPL)", "D50", 48, 64, seed=3)
    return buf.getvalue()


DNG = _small_dng()


def _strict_json(text: str):
    def bad(name):
        raise ValueError(f"non-finite number {name} in JSON")
    return json.loads(text, parse_constant=bad)


def _header(response, name: str):
    for k, v in response.headers.items():
        if k.lower() == name.lower():
            return v[0] if isinstance(v, list) else v
    return None


def json_is_strict_and_errors_are_shaped(ctx, response, case):
    """No NaN/Inf in a JSON body or the X-Illuminant header; a 4xx JSON body
    names the error (``error`` and ``detail`` strings)."""
    ctype = (_header(response, "content-type") or "").lower()
    if ctype.startswith("application/json"):
        body = _strict_json(response.content.decode("utf-8"))
        if 400 <= response.status_code < 500:
            assert isinstance(body, dict) and isinstance(body.get("error"), str) \
                and isinstance(body.get("detail"), str), f"4xx body without error/detail: {body!r}"
    xi = _header(response, "x-illuminant")
    if xi is not None:
        _strict_json(xi)
    return None


CHECKS = [not_a_server_error, response_schema_conformance, json_is_strict_and_errors_are_shaped]


@schema.parametrize()
@schema.given(real_file=st.booleans())
@settings(max_examples=EXAMPLES, deadline=None, database=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_every_operation_answers_without_server_errors(case, real_file):
    if real_file and isinstance(case.body, dict) and "file" in case.body:
        # a valid image, and the optional fields that were generated as
        # "absent" left out (a None would be sent as the string "null" and
        # every such request would stop at option validation)
        case.body = {k: v for k, v in case.body.items()
                     if v is not None and not (k == "sensitivities" and not isinstance(v, bytes))}
        case.body["file"] = DNG
    case.call_and_validate(checks=CHECKS)


def test_schema_documents_the_error_body_on_every_operation():
    """The rewrite of the OpenAPI schema reached every operation (so the
    conformance check above validates real error bodies, not FastAPI's
    list-of-validation-errors shape the handlers never send)."""
    doc = app.openapi()
    ops = [(p, m, op) for p, item in doc["paths"].items() for m, op in item.items() if isinstance(op, dict)]
    assert ops
    for p, m, op in ops:
        for code in ("422", "4XX"):
            ref = op["responses"][code]["content"]["application/json"]["schema"]["$ref"]
            assert ref == "#/components/schemas/ErrorBody", (p, m, code)
    assert doc["components"]["schemas"]["ErrorBody"]["required"] == ["error", "detail"]
