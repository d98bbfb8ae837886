"""The API's documentation, served offline (issue 13, item 7).

``/docs`` is FastAPI's Swagger UI page with its script and style sheet served
by the app itself from the ``swagger-ui-bundle-v2`` package (Swagger UI 5,
which reads the OpenAPI 3.1 FastAPI writes): nothing is fetched from another
host. :func:`enrich` completes the generated OpenAPI document: every
parameter gets a description, its enumeration where the choices are fixed,
and examples; uploads declare their 413/415/422 answers (``{"error",
"detail"}``); ``/v1/white-balance`` declares its image media types and the
``X-Illuminant`` header; the JSON headers (``X-Illuminant``, ``X-Preview``,
``X-Render-Report``) are declared with their models and a real example,
and each error answer with a real error of its kind.
"""

from __future__ import annotations

import json
import os

from .schemas.examples import EXAMPLES

#: The two Swagger UI files the page needs, and their media types.
SWAGGER_FILES = {"swagger-ui-bundle.js": "text/javascript; charset=utf-8",
                 "swagger-ui.css": "text/css; charset=utf-8"}
SWAGGER_PREFIX = "/docs-assets"


def _option_params() -> dict:
    """The request options' entries, from their models (:mod:`service.schemas`)."""
    from .schemas.fields import CONCERNS

    out = {}
    for _, fields, _ in CONCERNS:
        for name, opt in fields.items():
            out.setdefault(name, (opt.description, list(opt.choices) if opt.choices else None,
                                  list(opt.examples) or None))
    return out


#: name -> (description, enum or None, examples); a router's own description
#: wins. The request options come from their models (service.schemas): their
#: form fields carry description, examples and choices (``x-choices``).
PARAMS = {**_option_params(),
    "file": ("the image: a camera RAW (DNG, CR2, NEF, ARW, ... anything LibRaw reads) or a linear 16-bit "
             "TIFF/PNG", None, None),
    "sensitivities": ("optional camera sensitivities CSV: wavelength (nm), then one column per channel", None, None),
    "folder": ("a folder relative to WANDELL_BATCH_ROOT (instead of files)", None, ["shoot-2026-05"]),
    "files": ("several image files (instead of folder)", None, None),
    "batch_id": ("the batch id answered by POST /v1/batches", None, ["3f9c1d2e"]),
    "item": ("an item's name, or its index in the batch (0-based); 409 when it is one item's name and "
             "another's index", None, [0]),
    "strategy": ("a sampling rule (GET /v1/sampling lists them), auto or full", None, ["auto", "full"]),
    "n": ("number of samples, 1..64", None, [8]),
    "wavelengths": ("the cube's wavelengths in nm, comma-separated, strictly increasing", None,
                    ["400,410,420,430,440,450,460,470,480,490,500"]),
    "illuminant": ("a CIE illuminant name to light the reflectances with", None, ["D65", "A"]),
    "light_file": ("optional light spectrum CSV: wavelength (nm), power", None, None),
    "channel": ("which colour-matching channel the rule is built for", ["A", "C1", "C2", "XYZ"], ["XYZ"]),
    "degrees": ("Borges' degree sequence for x, y, z, each 0..12", None, ["2,2,2"]),
    "adapt": ("refine the sampling until max_error is met", None, [False]),
    "max_error": ("the largest colour error accepted when adapt is true (CIELAB units)", None, [1.0]),
}

#: (path, name) -> enumeration where one name means different sets (the
#: option models' fields say their own, as ``x-choices``).
ENUMS: dict = {}

#: The error body's schema is service.errors' ``ErrorBody`` (added to the document there).
ERROR_REF = "#/components/schemas/ErrorBody"
_ERRORS = {
    "413": "too large: the upload is over WANDELL_MAX_UPLOAD_BYTES or the image over WANDELL_MAX_PIXELS "
           "(error file_too_large, too_large, too_many_pixels)",
    "415": "not a format the service reads: not a camera RAW or a linear 16-bit TIFF/PNG (e.g. an 8-bit JPEG, "
           "or 'not a camera RAW: a scanned 8-bit RGB image')",
    "422": "a bad option (error invalid_parameter and the accepted values), or a truncated/corrupt or unusable "
           "file (corrupt_file, no_color_matrix, unusable_neutral, ...)",
}

X_ILLUMINANT = ("JSON: the estimate (method, camera, illuminant camera_rgb/wb_multipliers/cct/duv, and "
                "xy/chromaticity_basis of the CCT/Duv and Camera Raw's temperature/tint/temperature_basis), warnings, "
                "timings_ms, correction_matrix, white (estimate, as-shot or neutral), neutral (where the white "
                "came from) and rendering: rendering (dng-matrix or spectral), color_source, exposure {rule: "
                "auto (LibRaw's auto-brightness: the 99th percentile of the brightest display channel is white) "
                "or user, ev}, curve (libraw: LibRaw's BT.709 tone as a display shows it), tone, white_xy, "
                "temperature, tint. With format=xmp: the estimate in short (method, camera_rgb, wb_multipliers, "
                "cct, duv, xy, confidence and the sidecar's temperature/tint)")


def swagger_path() -> str | None:
    """The folder of the packaged Swagger UI, or ``None`` without the package."""
    try:
        import swagger_ui_bundle
    except ImportError:
        return None
    return getattr(swagger_ui_bundle, "swagger_ui_path", None) or getattr(swagger_ui_bundle, "swagger_ui_5_path",
                                                                          None)


def _is_file(schema: dict) -> bool:
    """An upload field (binary, possibly optional or a list)."""
    parts = [schema] + list(schema.get("anyOf", []))
    parts += [p.get("items", {}) for p in parts if p.get("type") == "array"]
    return any(p.get("format") == "binary" or p.get("contentMediaType") == "application/octet-stream"
               for p in parts)


def _pop_examples(schema: dict, desc_holder: dict) -> list:
    """Remove every example keyword from a field (its schema, the branches of
    an ``anyOf``, the parameter object) and return the values, in order."""
    found: list = []
    for holder in [desc_holder, schema] + list(schema.get("anyOf", [])):
        ex = holder.pop("examples", None)
        if isinstance(ex, list):
            found += ex
        elif isinstance(ex, dict):   # a parameter's OpenAPI Example Objects
            found += [v.get("value") for v in ex.values() if isinstance(v, dict) and "value" in v]
        if "example" in holder:
            found.append(holder.pop("example"))
    return found


def _example_text(values: list) -> str:
    shown = []
    for v in values:
        t = v if isinstance(v, str) else json.dumps(v)
        if t not in shown:
            shown.append(t)
    return ", ".join(f"`{t}`" for t in shown)


def _fill(schema: dict, path: str, name: str, desc_holder: dict, form: bool = False) -> None:
    """Description, enumeration and examples of one field.

    Examples go into the description, never into ``example``/``examples``:
    Swagger UI 5 fills "Try it out" with a field's first example (for a
    form field even an optional one, and sends it), so an example there
    becomes a value: ``neutral=1200,2040`` or ``surface_dim=2`` on every
    try, a 422 or a run with other options than the defaults (issue 19,
    item 3). A field's ``default`` stays: it is what the service does
    without the field."""
    desc, enum, examples = PARAMS.get(name, (None, None, None))
    own = desc_holder.pop("x-choices", None) or schema.pop("x-choices", None)
    enum = own or ENUMS.get((path, name), enum)
    if not desc_holder.get("description") and desc:
        desc_holder["description"] = desc
    target = schema
    if "anyOf" in schema:          # Optional[...]: enumerate on the string branch
        target = next((s for s in schema["anyOf"] if s.get("type") in ("string", "integer")), schema)
    if enum and "enum" not in target and target.get("type") == "string":
        target["enum"] = list(enum)
    if form and "default" not in schema and {"type": "null"} in schema.get("anyOf", []) and not _is_file(schema):
        # an optional form field without a value of its own: Swagger UI fills
        # it with its schema's sample ("string", 0, the first choice; a null
        # default is sent as the text "null"). An empty default is sent not
        # at all, and FastAPI reads an empty form field as an absent one.
        schema["default"] = ""
    declared = _pop_examples(schema, desc_holder)
    shown = declared or list(examples or [])
    if shown and not _is_file(schema):
        text = desc_holder.get("description") or ""
        desc_holder["description"] = (text.rstrip(". ") + ". " if text else "") + "Examples: " + \
            _example_text(shown) + "."


def enrich(spec: dict) -> dict:
    """Complete the generated OpenAPI document in place (see module doc)."""
    comps = spec.setdefault("components", {}).setdefault("schemas", {})
    for path, ops in spec.get("paths", {}).items():
        for method, op in ops.items():
            for p in op.get("parameters", []):
                _fill(p.setdefault("schema", {}), path, p["name"], p)
            body = op.get("requestBody", {}).get("content", {})
            upload = False
            for ct, c in body.items():
                ref = c.get("schema", {}).get("$ref", "")
                sch = comps.get(ref.split("/")[-1], {})
                for name, prop in sch.get("properties", {}).items():
                    _fill(prop, path, name, prop, form=name not in sch.get("required", []))
                    if _is_file(prop):
                        upload = True
            responses = op.setdefault("responses", {})
            codes = ("413", "415", "422") if upload else ("422",)
            for code in codes:
                r = responses.setdefault(code, {})
                r["description"] = _ERRORS[code]
                r["content"] = {"application/json": {"schema": {"$ref": ERROR_REF}}}
    wb = spec.get("paths", {}).get("/v1/white-balance", {}).get("post")
    if wb is not None:
        ok = wb["responses"].setdefault("200", {})
        ok["description"] = ("the corrected image at full resolution (format: tiff 16-bit, png 8-bit, png16, "
                             "jpeg), or a Camera Raw XMP sidecar (format=xmp), or the RAW as a DNG with the "
                             "white balance inside (format=dng), or JSON (response=json)")
        ok["content"] = {"image/tiff": {"schema": {"type": "string", "format": "binary"}},
                         "image/png": {"schema": {"type": "string", "format": "binary"}},
                         "image/jpeg": {"schema": {"type": "string", "format": "binary"}},
                         "application/rdf+xml": {"schema": {"type": "string"}},
                         "image/x-adobe-dng": {"schema": {"type": "string", "format": "binary"}},
                         "application/json": ok.get("content", {}).get("application/json")
                         or {"schema": {"type": "object"}}}   # WhiteBalanceResult, declared by the router
        ok["headers"] = {"X-Illuminant": _header(("IlluminantHeader", "EstimateSummary"), X_ILLUMINANT, comps)}
    for path, name, model, words, example in (
            ("/v1/render", "X-Render-Report", "RenderReport", "JSON: the render report (as response=json answers, "
             "with `tried` the number of rules tried)", 1),
            ("/v1/preview", "X-Preview", "PreviewInfo", "JSON: what the preview shows", 0)):
        op = spec.get("paths", {}).get(path, {}).get("post")
        if op is not None and "200" in op["responses"]:
            op["responses"]["200"]["headers"] = {name: _header((model,), words, comps, example)}
    errors = {code: EXAMPLES[f"ErrorBody {code}"] for code in ("422", "415", "413", "404")
              if f"ErrorBody {code}" in EXAMPLES}
    if "ErrorBody" in comps:
        comps["ErrorBody"] = {**comps["ErrorBody"], "examples": list(errors.values())}
    for ops in spec.get("paths", {}).values():     # each error answer with an example of its own kind
        for op in ops.values():
            for code, r in op.get("responses", {}).items():
                media = r.get("content", {}).get("application/json")
                ex = errors.get("404" if code == "4XX" else code)
                if media is not None and media.get("schema", {}).get("$ref") == ERROR_REF and ex is not None:
                    media["example"] = ex
    return spec


def _header(model_names: tuple[str, ...], description: str, comps: dict, example: int = 0) -> dict:
    """A header whose value is JSON: a string whose content is one of the
    models (OpenAPI 3.1 / JSON Schema ``contentMediaType`` and
    ``contentSchema``), with the first model's example number ``example``
    (a real header) as the header's example."""
    from .schemas import responses

    for name in model_names:
        schema = getattr(responses, name).model_json_schema(ref_template="#/components/schemas/{model}",
                                                            mode="serialization")
        for sub_name, sub in schema.pop("$defs", {}).items():
            comps.setdefault(sub_name, sub)
        comps.setdefault(name, schema)
    refs = [{"$ref": f"#/components/schemas/{n}"} for n in model_names]
    examples = getattr(responses, model_names[0]).model_config["json_schema_extra"]["examples"]
    first = examples[example] if len(examples) > example else {}
    return {"description": f"{description} (schema: {' or '.join(model_names)})",
            "schema": {"type": "string", "contentMediaType": "application/json",
                       "contentSchema": refs[0] if len(refs) == 1 else {"anyOf": refs}},
            "example": json.dumps(first, separators=(",", ":"))}


def install(app) -> None:
    """``/docs`` (offline Swagger UI), its two assets, and the enriched OpenAPI."""
    from fastapi.openapi.docs import get_swagger_ui_html
    from fastapi.responses import Response

    from .errors import ServiceError

    @app.get("/docs", include_in_schema=False)
    def docs():
        if swagger_path() is None:
            raise ServiceError(503, "docs_unavailable", "the swagger-ui-bundle-v2 package is not installed; the "
                           "OpenAPI document is at /openapi.json")
        return get_swagger_ui_html(openapi_url=app.openapi_url, title=f"{app.title}: REST API",
                                   swagger_js_url=f"{SWAGGER_PREFIX}/swagger-ui-bundle.js",
                                   swagger_css_url=f"{SWAGGER_PREFIX}/swagger-ui.css",
                                   swagger_favicon_url="data:,")

    @app.get(SWAGGER_PREFIX + "/{name}", include_in_schema=False)
    def docs_asset(name: str):
        root = swagger_path()
        if name not in SWAGGER_FILES or root is None:
            raise ServiceError(404, "not_found", f"no documentation asset {name!r}; served: {sorted(SWAGGER_FILES)}")
        with open(os.path.join(root, name), "rb") as f:
            return Response(f.read(), media_type=SWAGGER_FILES[name],
                            headers={"Cache-Control": "public, max-age=86400"})

    original = app.openapi

    def openapi():
        if app.openapi_schema is None:
            app.openapi_schema = enrich(original())
        return app.openapi_schema

    app.openapi = openapi
