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
:func:`service.deps.checked_upload` (:func:`~service.deps.read_upload` for small parts).

``POST /v1/batches`` takes many files, so its body allowance is the upload
limit times the batch limit; there the multipart stream is also followed as
it arrives (:class:`_PartCounter`): a file part that passes the upload
limit, or a file beyond the batch limit (``max_batch_items``, and at most
:data:`FORM_MAX_FILES`, the form parser's own), is refused at once with 413
``file_too_large`` / ``too_many_items``, before the rest is spooled to disk.

A body that stops arriving (no byte for ``Settings.body_timeout`` seconds,
``WANDELL_BODY_TIMEOUT``) is cut off with a 408 ``body_timeout``; one that
keeps trickling is cut off ``Settings.body_deadline`` seconds
(``WANDELL_BODY_DEADLINE``) after its first byte was awaited, with a 408
``body_deadline``: a slow or stalled upload cannot hold a connection and a
spooled file indefinitely (one byte every 20 s did, issue 28).
Every cut-off answer says ``Connection: close``, so the server drops the
connection instead of waiting for the rest of the body.
"""

from __future__ import annotations

import logging
import time

import anyio

from .errors import error_response
from .settings import get_settings

__all__ = ["COALESCE_BYTES", "FORM_MAX_FILES", "FRAMING", "SendDeadlineMiddleware", "UploadLimitMiddleware"]

#: Bytes allowed on top of the upload limit for multipart boundaries, part
#: headers and the small form fields.
FRAMING = 1024 * 1024

#: Files Starlette's form parser accepts in one request (its ``max_files``);
#: more are refused here as ``too_many_items`` (413), not its plain 400.
FORM_MAX_FILES = 1000

#: The body is handed on in pieces of about this size: the server receives
#: 64 KiB at a time, and Starlette's form parser writes each piece it gets to
#: the spooled file on a worker thread, some 750 thread hops for a 48 MB DNG
#: (issue 19); joined to 1 MiB they are about 50.
COALESCE_BYTES = 1024 * 1024


class _CutOff(Exception):
    """The body is refused part-way: ``status``, ``code``, ``detail``."""

    def __init__(self, status: int, code: str, detail: str):
        super().__init__(detail)
        self.status, self.code, self.detail = status, code, detail


class _PartCounter:
    """Follows a multipart body as it arrives (python-multipart, callbacks
    only, nothing stored) and raises :class:`_CutOff` as soon as one file
    part exceeds ``max_bytes`` or the request holds more than ``max_files``
    files. A body it cannot parse is left to the form parser's own errors."""

    def __init__(self, content_type: bytes, max_bytes: int, max_files: int):
        from python_multipart.multipart import MultipartParser, parse_options_header

        _, params = parse_options_header(content_type)
        boundary = params.get(b"boundary")
        self.max_bytes, self.max_files = max_bytes, max_files
        self.files = self.size = 0
        self.header = b""
        self.name = ""
        self.is_file = False
        self.failed = boundary is None
        self.parser = None if self.failed else MultipartParser(boundary, {
            "on_part_begin": self._begin, "on_header_field": self._field, "on_header_value": self._value,
            "on_header_end": self._header_end, "on_headers_finished": self._headers_done,
            "on_part_data": self._data})
        self._field_name = b""

    def _begin(self):
        self.size, self.is_file, self.name = 0, False, ""

    def _field(self, data, start, end):
        self._field_name += data[start:end]

    def _value(self, data, start, end):
        self.header += data[start:end]

    def _header_end(self):
        from python_multipart.multipart import parse_options_header

        if self._field_name.lower() == b"content-disposition":
            _, params = parse_options_header(self.header)
            filename = params.get(b"filename")
            if filename:
                self.is_file = True
                self.name = filename.decode("utf-8", "replace")[:100]
        self._field_name, self.header = b"", b""

    def _headers_done(self):
        if self.is_file:
            self.files += 1
            if self.files > self.max_files:
                raise _CutOff(413, "too_many_items", f"more than {self.max_files} files in one batch "
                              "(the batch limit)")

    def _data(self, data, start, end):
        if self.is_file:
            self.size += end - start
            if self.size > self.max_bytes:
                raise _CutOff(413, "file_too_large", f"{self.name!r} exceeds the upload limit of "
                              f"{self.max_bytes} bytes (stopped reading)")

    def feed(self, chunk: bytes) -> None:
        if self.failed or not chunk:
            return
        try:
            self.parser.write(chunk)
        except _CutOff:
            raise
        except Exception:  # malformed framing: the form parser answers it
            self.failed = True


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

        counter = None
        if scope.get("path") == "/v1/batches" and scope.get("method") == "POST":
            ctype = dict(scope.get("headers") or ()).get(b"content-type", b"")
            if ctype.lower().startswith(b"multipart/"):
                counter = _PartCounter(ctype, upload, min(max(1, settings.max_batch_items), FORM_MAX_FILES))
        timeout = settings.body_timeout if settings.body_timeout > 0 else None
        deadline = time.monotonic() + settings.body_deadline if settings.body_deadline > 0 else None

        received = 0
        body_done = False
        cut: _CutOff | None = None
        started = False

        async def receive_one():
            nonlocal received, cut, body_done
            if cut is not None:
                raise cut
            left = None if deadline is None else deadline - time.monotonic()
            if body_done or (timeout is None and left is None):
                message = await receive()
            else:
                wait = min(t for t in (timeout, left) if t is not None)
                try:
                    with anyio.fail_after(max(0.0, wait)):
                        message = await receive()
                except TimeoutError:
                    if left is not None and wait == left:
                        cut = _CutOff(408, "body_deadline", "the request body did not arrive within "
                                      f"{settings.body_deadline:g} s (WANDELL_BODY_DEADLINE); the upload was stopped")
                    else:
                        cut = _CutOff(408, "body_timeout", f"no part of the request body arrived for {timeout:g} s "
                                      "(WANDELL_BODY_TIMEOUT); the upload was stopped")
                    raise cut from None
            if message["type"] == "http.request":
                body = message.get("body", b"")
                received += len(body)
                body_done = not message.get("more_body", False)
                if received > allowed:
                    cut = _CutOff(413, "file_too_large", f"request body exceeds the upload limit of {upload} "
                                  "bytes (stopped reading)")
                    raise cut
                if counter is not None:
                    try:
                        counter.feed(body)
                    except _CutOff as e:
                        cut = e
                        raise
            return message

        pending = None

        async def counting_receive():
            """:func:`receive_one`'s body pieces joined up to
            :data:`COALESCE_BYTES` (what arrived is counted and checked
            piece by piece, as it comes)."""
            nonlocal pending
            if pending is not None:
                message, pending = pending, None
                return message
            message = await receive_one()
            if message["type"] != "http.request" or not message.get("more_body", False):
                return message
            parts = [message.get("body", b"")]
            size = len(parts[0])
            while size < COALESCE_BYTES:
                nxt = await receive_one()
                if nxt["type"] != "http.request":
                    pending = nxt            # a disconnect: after the body so far
                    break
                body = nxt.get("body", b"")
                parts.append(body)
                size += len(body)
                if not nxt.get("more_body", False):
                    return {"type": "http.request", "body": b"".join(parts), "more_body": False}
            return {"type": "http.request", "body": b"".join(parts), "more_body": True}

        async def answer_cut():
            nonlocal started
            if not started:
                started = True
                await error_response(cut.status, cut.code, cut.detail, headers={"Connection": "close"})(
                    scope, receive, send)

        async def guarded_send(message):
            nonlocal started
            if cut is not None:
                # whatever the app made of the interrupted body (FastAPI turns
                # a failing receive into a 400 "error parsing the body"), the
                # client is told the real reason, once
                await answer_cut()
                return
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except _CutOff:
            await answer_cut()


log = logging.getLogger("wandell.limits")


class _SendStalled(BaseException):
    """The client stopped taking the answer: raised out of the app's
    ``send`` so that every response's clean-up runs (a temporary answer is
    removed, a held image released) on the way out. A ``BaseException`` so
    that no application error handler turns it into an answer."""


class SendDeadlineMiddleware:
    """Give up an answer whose client stops reading it.

    Each piece of a response body (at most 1 MiB: the file and memory
    answers' chunk) must be taken by the connection within
    ``Settings.send_timeout`` seconds (``WANDELL_SEND_TIMEOUT``; 0 = no
    limit): the send waits while the socket's buffer is full, so a client
    that stops reading made it wait for ever, holding the answer's temporary
    file or image (issue 28: ten such readers held 425 MB of TMPDIR). Past
    the deadline the response is abandoned: the exception unwinds the app
    (its ``finally`` clean-ups run), the connection is closed by the server
    (an incomplete response), and one line is logged.
    """

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        timeout = get_settings().send_timeout
        if timeout <= 0:
            await self.app(scope, receive, send)
            return
        stalled = False

        async def timed_send(message):
            nonlocal stalled
            if stalled:
                raise _SendStalled()
            if message["type"] != "http.response.body":
                await send(message)
                return
            try:
                with anyio.fail_after(timeout):
                    await send(message)
            except TimeoutError:
                stalled = True
                raise _SendStalled() from None

        try:
            await self.app(scope, receive, timed_send)
        except BaseException:
            if not stalled:
                raise
            log.warning("%s %s: the client took no part of the answer for %g s (WANDELL_SEND_TIMEOUT); "
                        "the answer was given up", scope.get("method"), scope.get("path"), timeout)
