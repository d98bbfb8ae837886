"""Request-body size limit as a pure ASGI middleware.

The upload limit (``Settings.max_upload_bytes``, ``WANDELL_MAX_UPLOAD_BYTES``)
must hold however the body arrives. A declared ``Content-Length`` above it is
refused before anything is read; a body without one (chunked transfer
encoding) is counted as it is received and refused as soon as it passes the
limit, so the multipart parser never spools more than the limit to disk.
Either way the answer is a 413 ``{"error": "file_too_large", "detail": ...}``.

The allowance is the upload limit plus :data:`FRAMING` bytes of multipart
framing and form fields for the whole body (as before this middleware);
each file field is checked against the limit on its own in
:func:`service.deps.read_upload`.
"""

from __future__ import annotations

from .errors import error_response
from .settings import get_settings

__all__ = ["FRAMING", "UploadLimitMiddleware"]

#: Bytes allowed on top of the upload limit for multipart boundaries, part
#: headers and the small form fields.
FRAMING = 1024 * 1024


class _BodyTooLarge(Exception):
    pass


class UploadLimitMiddleware:
    """Refuse request bodies over ``max_upload_bytes + FRAMING`` with a 413,
    whether declared (``Content-Length``) or streamed."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        settings = get_settings()
        upload = settings.max_upload_bytes
        allowed = upload + FRAMING
        if scope.get("path") == "/v1/batches":  # several files, each checked on its own as it is saved
            allowed = upload * max(1, settings.max_batch_items) + FRAMING
        length = dict(scope.get("headers") or ()).get(b"content-length")
        if length is not None:
            try:
                n = int(length)
            except ValueError:
                await error_response(400, "bad_content_length", "Content-Length is not an integer")(
                    scope, receive, send)
                return
            if n > allowed:
                await error_response(413, "file_too_large", f"request body of {n} bytes exceeds the upload "
                                     f"limit of {upload} bytes")(scope, receive, send)
                return

        received = 0
        exceeded = False
        started = False

        async def counting_receive():
            nonlocal received, exceeded
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > allowed:
                    exceeded = True
                    raise _BodyTooLarge()
            return message

        too_large = error_response(413, "file_too_large", f"request body exceeds the upload limit of {upload} "
                                   "bytes (stopped reading)")

        async def guarded_send(message):
            nonlocal started
            if exceeded:
                # whatever the app made of the interrupted body (FastAPI turns
                # a failing receive into a 400 "error parsing the body"), the
                # client is told the real reason, once
                if not started:
                    started = True
                    await too_large(scope, receive, send)
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except _BodyTooLarge:
            if not started:
                started = True
                await too_large(scope, receive, send)
