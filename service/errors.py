"""The service's one error type and its responses: every failure the client
caused is a 4xx with a JSON body ``{"error": code, "detail": text}``
(docs/DESIGN.md); nothing else escapes as a 500 with an HTML page.

:class:`ServiceError` is raised by every layer of the service (decoding,
option validation, the pipeline, the batch jobs, the CLI); the recovery
errors (:mod:`recovery.errors`) are mapped to it by :func:`service_error`.
Importing this module does not import the web stack: the FastAPI handlers
import it when they are installed.
"""

from __future__ import annotations

import logging

log = logging.getLogger("service")

__all__ = ["ServiceError", "service_error", "error_response", "install_error_handlers", "disk_full"]


class ServiceError(Exception):
    """A request the service refuses.

    Parameters
    ----------
    status : int
        The HTTP status to answer with: 403, 404, 413 (too large), 415 (a
        format the service does not read) or 422 (readable, unusable).
    code : str
        Machine-readable error code (``empty_file``, ``unsupported_format``,
        ``corrupt_file``, ``too_many_pixels``, ``invalid_parameter``,
        ``bad_csv``, ``unknown_camera``, ...).
    detail : str
        What was wrong, in words a user can act on.
    extra : dict, optional
        Machine-readable fields added to the body beside ``error`` and
        ``detail`` (e.g. when an expired batch was removed).
    """

    def __init__(self, status: int, code: str, detail: str, *, extra: dict | None = None):
        super().__init__(detail)
        self.status = int(status)
        self.code = str(code)
        self.detail = str(detail)
        self.extra = dict(extra or {})

    def __repr__(self) -> str:
        return f"ServiceError({self.status}, {self.code!r}, {self.detail!r})"

    def __str__(self) -> str:
        return self.detail


def service_error(exc: BaseException) -> ServiceError | None:
    """The :class:`ServiceError` an exception answers as: itself, a recovery
    error as a 422 with its code, anything else ``None`` (a bug)."""
    if isinstance(exc, ServiceError):
        return exc
    from recovery.errors import RecoveryError  # here: the CLI's start-up imports no numerical library

    if isinstance(exc, RecoveryError):
        return ServiceError(getattr(exc, "status", 422), exc.code, str(exc))
    return None


def disk_full(exc: BaseException | None) -> bool:
    """Whether ``exc`` (or what caused it: ``__cause__``/``__context__``)
    is a file system out of space or quota: ``ENOSPC``/``EDQUOT``, numpy's
    errno-less ``OSError("Not enough free space to write ...")`` (tifffile
    writes through ``ndarray.tofile``), or SQLite's "database or disk is full"."""
    import errno

    seen = 0
    while exc is not None and seen < 16:
        if isinstance(exc, OSError) and (exc.errno in (errno.ENOSPC, errno.EDQUOT)
                                         or "not enough free space" in str(exc).lower()):
            return True
        if type(exc).__name__ == "OperationalError" and "full" in str(exc).lower():
            return True
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return False


#: The answer when the server's temporary space (``TMPDIR``: spooled uploads,
#: the white-balance output before it is streamed) is full.
INSUFFICIENT_STORAGE = ("the server's temporary space (TMPDIR) is full: the upload or its result could not be "
                        "written; nothing was kept, try again when space is freed")


def error_response(status: int, code: str, detail, headers: dict | None = None, extra: dict | None = None):
    from fastapi.responses import JSONResponse

    body = {"error": code, "detail": detail}
    body.update((k, v) for k, v in (extra or {}).items() if k not in body)
    return JSONResponse(status_code=status, content=body, headers=headers)


#: OpenAPI schema of every error body (DESIGN.md: ``{"error": code, "detail": text}``).
ERROR_BODY_SCHEMA = {
    "title": "ErrorBody",
    "type": "object",
    "required": ["error", "detail"],
    "properties": {
        "error": {"type": "string", "title": "Error", "description": "machine-readable code"},
        "detail": {"type": "string", "title": "Detail", "description": "what was wrong, in words"},
    },
}


def document_error_responses(app) -> None:
    """Make the app's OpenAPI schema say what its errors really look like.

    FastAPI documents a 422 with its own ``HTTPValidationError`` body (a list
    of validation errors), but the handlers below answer every client error
    with ``{"error", "detail"}``. The generated schema is rewritten once, for
    every operation (so endpoints added later are covered too): the 422
    response and a ``4XX`` range response both point at ``ErrorBody``.
    """
    from fastapi.openapi.utils import get_openapi

    def openapi() -> dict:
        if app.openapi_schema:
            return app.openapi_schema
        schema = get_openapi(title=app.title, version=app.version, description=app.description,
                             routes=app.routes)
        schema.setdefault("components", {}).setdefault("schemas", {})["ErrorBody"] = ERROR_BODY_SCHEMA
        ref = {"description": "client error", "content": {"application/json": {
            "schema": {"$ref": "#/components/schemas/ErrorBody"}}}}
        for item in schema.get("paths", {}).values():
            for method, op in item.items():
                if not isinstance(op, dict) or "responses" not in op:
                    continue
                op["responses"]["422"] = dict(ref, description="invalid request or unusable upload")
                op["responses"].setdefault("4XX", ref)
        app.openapi_schema = schema
        return schema

    app.openapi = openapi


def install_error_handlers(app) -> None:
    """Map every exception type to its JSON error body (and document it)."""
    from fastapi import Request
    from fastapi.exceptions import RequestValidationError
    from starlette.exceptions import HTTPException as StarletteHTTPException

    from recovery.errors import RecoveryError

    document_error_responses(app)

    @app.exception_handler(ServiceError)
    @app.exception_handler(RecoveryError)
    async def _service(_: Request, exc: Exception):
        err = service_error(exc)
        return error_response(err.status, err.code, err.detail, getattr(err, "headers", None),
                              getattr(err, "extra", None))

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, exc: RequestValidationError):
        parts = []
        for e in exc.errors():
            loc = ".".join(str(x) for x in e.get("loc", ()) if x not in ("body", "query", "form"))
            msg = str(e.get("msg"))
            if "Expected UploadFile" in msg:   # was "Expected UploadFile, received: <class 'str'>" (probe round 7)
                name = str(next((x for x in e.get("loc", ()) if x not in ("body", "query", "form")), loc))
                msg = (f"must be a file: a form part with a file name (curl -F {name}=@PHOTO.dng); a text field or "
                       "a part without a file name (or with an empty one) was given")
            parts.append(f"{loc}: {msg}")
        return error_response(422, "invalid_parameter", "; ".join(parts) or "invalid request")

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, exc: StarletteHTTPException):
        if exc.status_code == 400 and disk_full(exc.__cause__):   # FastAPI: "error parsing the body"
            log.error("upload not spooled, TMPDIR is full: %s", exc.__cause__)
            return error_response(507, "insufficient_storage", INSUFFICIENT_STORAGE)
        code = {404: "not_found", 405: "method_not_allowed", 413: "too_large"}.get(exc.status_code, "http_error")
        return error_response(exc.status_code, code, str(exc.detail))

    @app.exception_handler(Exception)
    async def _internal(_: Request, exc: Exception):  # a bug, never a bad upload
        if disk_full(exc):             # not a bug: the disk (TMPDIR) is full
            log.error("request failed, TMPDIR is full: %s", exc)
            return error_response(507, "insufficient_storage", INSUFFICIENT_STORAGE)
        log.exception("internal error")
        return error_response(500, "internal_error", f"{type(exc).__name__}: the service failed; please report")
