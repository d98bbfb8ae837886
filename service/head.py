"""HEAD wherever GET is served (RFC 9110, section 9.1: "All general-purpose
servers MUST support the methods GET and HEAD"; 9.3.2: HEAD is GET without
the content).

FastAPI's ``@router.get`` routes answer GET only, so uptime monitors and
load-balancer health checks that probe with HEAD, and download tools that
ask for a result's size first, got 405. :func:`allow_head` adds HEAD to
every GET route of the app: the same handler runs, with the same status
and headers (``Content-Length`` included); uvicorn sends no body for HEAD,
and Starlette's ``FileResponse`` (result downloads) does not read the file.
The OpenAPI schema keeps documenting GET only (HEAD is implied by it).
"""

from __future__ import annotations

__all__ = ["allow_head"]


def allow_head(app) -> None:
    """Add HEAD to the methods of every route of ``app`` that serves GET,
    and keep HEAD out of the generated OpenAPI schema."""
    from fastapi.routing import APIRoute

    def walk(routes):
        for route in routes:
            included = getattr(route, "original_router", None)     # FastAPI >= 0.165 keeps included routers
            if included is not None:
                walk(included.routes)
            elif isinstance(route, APIRoute) and "GET" in route.methods:
                route.methods.add("HEAD")       # in place: the routers' effective routes share this set

    walk(app.routes)
    inner = app.openapi

    def openapi() -> dict:
        import warnings

        if app.openapi_schema:
            return app.openapi_schema
        with warnings.catch_warnings():     # HEAD shares GET's operation id; its operations are dropped below
            warnings.filterwarnings("ignore", message="Duplicate Operation ID")
            schema = inner()
        for item in schema.get("paths", {}).values():
            item.pop("head", None)
        return schema

    app.openapi = openapi
