"""REST form fields and query parameters from the option models
(:mod:`service.schemas.options`).

:func:`form` makes a FastAPI dependency whose parameters are one
``Form(...)`` per model field (:func:`query`: one ``Query(...)``, for the
``GET`` endpoints) (name, wire type, default, description,
examples, accepted values) and whose value is the validated model. It is a
generated signature rather than ``Annotated[Model, Form()]`` because an
endpoint takes several models beside its uploads, narrows some choices
(``/v1/preview``'s 8-bit formats) and keeps the field types its clients
send (``exposure`` is text, ``region_size`` an integer), and because the
checks must answer with the service's ``{"error", "detail"}`` 422 before the
upload is read. The accepted values go to the OpenAPI document as
``x-choices``; :func:`service.openapi_docs.enrich` turns them into the
field's ``enum`` on the right branch and moves examples into descriptions.
"""

from __future__ import annotations

import difflib
import inspect

from fastapi import Form, Query, Request

from ..errors import ServiceError
from .options import option_fields

__all__ = ["form", "query", "reject_unknown_fields"]


def form(model, *, include=None, exclude=(), choices=None, defaults=None, prefix: str = "", fixed=None,
         describe=None, lazy=()):
    """A dependency answering a validated ``model`` from the request's form.

    ``include``/``exclude``: which fields are form fields (the others keep
    their model default, or ``fixed[name]``); ``choices``: narrower accepted
    values per field (enumerated and checked); ``defaults``: another default
    on this endpoint; ``prefix``: put before every description (``corrected
    only: ``); ``describe``: another description per field (no prefix); ``lazy``: fields
    whose check the endpoint runs itself when it matters (:meth:`~service.schemas.options.OptionModel.check`)."""
    return _dependency(Form, "form", model, include, exclude, choices, defaults, prefix, fixed, describe, lazy)


def query(model, *, include=None, exclude=(), choices=None, defaults=None, prefix: str = "", fixed=None,
          describe=None, lazy=()):
    """A dependency answering a validated ``model`` from the request's query
    string: :func:`form`'s arguments, one ``Query(...)`` per field (a
    default of ``...`` makes a parameter required)."""
    return _dependency(Query, "query", model, include, exclude, choices, defaults, prefix, fixed, describe, lazy)


def _dependency(param, kind, model, include, exclude, choices, defaults, prefix, fixed, describe, lazy):
    choices, defaults, fixed, describe = choices or {}, defaults or {}, fixed or {}, describe or {}
    params = []
    for name, opt in option_fields(model).items():
        if (include is not None and name not in include) or name in exclude or name in fixed:
            continue
        default = defaults.get(name, opt.given_default)
        accepted = choices.get(name, opt.choices)
        extra = {"x-choices": list(accepted)} if accepted else None
        params.append(inspect.Parameter(
            name, inspect.Parameter.KEYWORD_ONLY, annotation=opt.wire_type,
            default=param(default, description=describe[name] if name in describe else prefix + opt.description,
                         examples=list(opt.examples) or None, json_schema_extra=extra)))

    async def dependency(**values):
        given = {k: v for k, v in {**values, **fixed}.items() if v is not None}
        return model.model_validate(given, context={"choices": choices, "lazy": tuple(lazy)})

    dependency.__signature__ = inspect.Signature(params)
    dependency.__name__ = f"{model.__name__}_{kind}"
    return dependency


def _declared(dependant, query: set, body: set, many: set) -> None:
    """The query and body (form) field names a route's dependency tree
    declares; ``many``: those that take a list (given once per value)."""
    query.update(f.alias for f in dependant.query_params)
    body.update(f.alias for f in dependant.body_params)
    many.update(f.alias for f in (*dependant.query_params, *dependant.body_params)
                if "list[" in str(f.field_info.annotation))
    for sub in dependant.dependencies:
        _declared(sub, query, body, many)


_ACCEPTED: dict = {}   # id(route) -> (route, query names, form names, names that take a list)


def _accepted(route) -> tuple[set, set, set]:
    got = _ACCEPTED.get(id(route))
    if got is None or got[0] is not route:
        query, body, many = set(), set(), set()
        _declared(route.dependant, query, body, many)
        got = _ACCEPTED[id(route)] = (route, query, body, many)
    return got[1], got[2], got[3]


def _repeated(items, many: set) -> list[str]:
    """Names given more than once that take one value (FastAPI keeps the
    last one: ``method=auto&method=bayes`` ran bayes with a 200)."""
    from collections import Counter

    return sorted(k for k, n in Counter(k for k, _ in items).items() if n > 1 and k not in many)


def _repeated_text(where: str, names: list[str]) -> str:
    return (f"{where} field{'s' if len(names) > 1 else ''} {', '.join(map(repr, names))} given more than once; "
            "each takes one value: give it once")


def _unknown_text(where: str, names: list[str], accepted: set) -> str:
    parts = []
    for n in names:
        close = difflib.get_close_matches(n, sorted(accepted), n=1)
        parts.append(repr(n) + (f" (did you mean {close[0]!r}?)" if close else ""))
    ok = ", ".join(sorted(accepted)) or "none"
    return f"unknown {where} field{'s' if len(names) > 1 else ''} {', '.join(parts)}; this endpoint accepts: {ok}"


async def reject_unknown_fields(request: Request) -> None:
    """A dependency of every documented route (issue 29, item 4): a query
    parameter or form field the route does not declare is a 422
    ``unknown_field`` naming it (and the closest accepted name) and listing
    the accepted ones, instead of being ignored (``taget=A`` rendered D65
    with a 200). The form is the one FastAPI has parsed already (Starlette
    keeps it on the request), so nothing is read twice. Routes left out of
    the OpenAPI document (the web page, its assets) are not checked. A
    field that takes one value given twice is a 422 ``repeated_field``
    (FastAPI would keep the last one)."""
    route = request.scope.get("route")
    if route is None or not getattr(route, "include_in_schema", False) or not hasattr(route, "dependant"):
        return
    query, body, many = _accepted(route)
    unknown = sorted({k for k in request.query_params.keys() if k not in query})
    if unknown:
        raise ServiceError(422, "unknown_field", _unknown_text("query", unknown, query))
    if repeated := _repeated(request.query_params.multi_items(), many):
        raise ServiceError(422, "repeated_field", _repeated_text("query", repeated))
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if body and ctype in ("multipart/form-data", "application/x-www-form-urlencoded"):
        form_data = await request.form()
        unknown = sorted({k for k in form_data.keys() if k not in body})
        if unknown:
            raise ServiceError(422, "unknown_field", _unknown_text("form", unknown, body))
        if repeated := _repeated(form_data.multi_items(), many):
            raise ServiceError(422, "repeated_field", _repeated_text("form", repeated))
