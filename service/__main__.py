"""``python -m service`` (installed as ``wandell-serve``): run the API with
uvicorn on the embedded defaults (127.0.0.1:8000), ``--host``/``--port`` or
``WANDELL_HOST``/``WANDELL_PORT``; ``--help`` prints the usage.

Connections that send nothing are closed: uvicorn times the idle gap after
a response (``timeout_keep_alive``, ``WANDELL_KEEP_ALIVE_TIMEOUT``) but not a
connection that never completes a request's headers, which it would keep
open for ever (slowloris). :class:`IdleClosingH11Protocol` gives those the
same deadline; a body that stalls is cut off by the upload middleware
(``WANDELL_BODY_TIMEOUT``, ``WANDELL_BODY_DEADLINE``, :mod:`service.limits`).

Open connections are capped (``WANDELL_MAX_CONNECTIONS``, by default half of
what the process's file-descriptor limit leaves after 100 for the server's
own files): a connection past the cap is answered at once with a 503
``too_many_connections`` (JSON, ``Retry-After``) and closed, so slow clients
cannot use up the descriptors and leave the server unable to accept
anything (issue 28: 1,100 uploads trickling a byte every 20 s did, with a
traceback logged per refused accept). Should the descriptors run out all
the same, asyncio's "socket.accept() out of system resource" error is
logged at most once a minute (:class:`_RateLimitedAcceptErrors`).
"""

from __future__ import annotations

import json
import logging
import time

from uvicorn.protocols.http.h11_impl import H11Protocol


def connection_cap(configured: int, nofile: int | None = None) -> int:
    """The open-connection cap: ``configured`` when positive, else
    ``(RLIMIT_NOFILE soft - 100) // 2`` (each connection may hold its socket
    and a spooled upload or answer file; 100 are left for the server's own:
    the store, the pool's pipes, the logs), at least 8."""
    if configured > 0:
        return configured
    if nofile is None:
        import resource

        nofile = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
        if nofile == resource.RLIM_INFINITY:
            nofile = 65536
    return max(8, (int(nofile) - 100) // 2)


def _busy_answer(cap: int) -> bytes:
    body = json.dumps({"error": "too_many_connections",
                       "detail": f"the server has {cap} connections open, its limit (WANDELL_MAX_CONNECTIONS); "
                                 "try again shortly"}).encode()
    return (b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: application/json\r\nretry-after: 5\r\n"
            b"connection: close\r\ncontent-length: " + str(len(body)).encode() + b"\r\n\r\n" + body)


class IdleClosingH11Protocol(H11Protocol):
    """uvicorn's h11 protocol, closing a connection whose next request's
    headers are not complete ``timeout_keep_alive`` seconds after it opened
    or after the previous response."""

    _header_deadline = None
    #: open connections allowed (set by :func:`main` from the settings; None = no cap)
    max_connections: int | None = None

    def _arm_header_deadline(self) -> None:
        if self._header_deadline is not None:
            self._header_deadline.cancel()
        self._header_deadline = self.loop.call_later(self.timeout_keep_alive, self._header_deadline_passed)

    def _header_deadline_passed(self) -> None:
        self._header_deadline = None
        idle = self.cycle is None or self.cycle.response_complete
        if idle and not self.transport.is_closing():
            self.transport.close()

    def connection_made(self, transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        cap = self.max_connections
        if cap is not None and len(self.connections) > cap:
            self._refuse(cap)
            return
        self._arm_header_deadline()

    _refused = False

    def _refuse(self, cap: int) -> None:
        """Answer 503 and close with a short linger: the answer is sent, the
        sending side shut, and what the client sends meanwhile read and
        dropped for up to a second (closing a socket with unread data resets
        it, and the client could lose the answer)."""
        self._refused = True
        self.transport.write(_busy_answer(cap))
        if self.transport.can_write_eof():
            self.transport.write_eof()
        self.loop.call_later(1.0, self.transport.close)

    def data_received(self, data: bytes) -> None:
        if self._refused:
            return
        super().data_received(data)

    def eof_received(self):
        if self._refused:
            self.transport.close()
            return None
        return super().eof_received()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_header_deadline()

    def connection_lost(self, exc) -> None:
        if self._header_deadline is not None:
            self._header_deadline.cancel()
            self._header_deadline = None
        super().connection_lost(exc)


class _RateLimitedAcceptErrors(logging.Filter):
    """Let asyncio's accept-failure error (EMFILE/ENFILE: "socket.accept()
    out of system resource", logged with a traceback each time the loop
    retries) through at most once per ``interval`` seconds, saying how many
    were held back."""

    def __init__(self, interval: float = 60.0):
        super().__init__()
        self.interval, self.last, self.held = interval, -float("inf"), 0

    def filter(self, record: logging.LogRecord) -> bool:
        if "out of system resource" not in str(record.msg):
            return True
        now = time.monotonic()
        if now - self.last < self.interval:
            self.held += 1
            return False
        if self.held:
            record.msg = f"{record.msg} ({self.held} more held back in the last {self.interval:g} s)"
        self.last, self.held = now, 0
        record.exc_info = None       # the traceback says nothing the message does not
        return True


def _parser():
    import argparse

    ap = argparse.ArgumentParser(
        prog="wandell-serve",
        description="Run the Wandell colour recovery service (the REST API, the page at / and the API docs at "
                    "/docs) with uvicorn. Stop it with Ctrl-C.",
        epilog="Every setting is an environment variable WANDELL_<NAME> (service/settings.py): for example "
               "WANDELL_HOST, WANDELL_PORT, WANDELL_MAX_UPLOAD_BYTES, WANDELL_MAX_CONCURRENT_WORK, "
               "WANDELL_DATA_DIR, WANDELL_KEEP_ALIVE_TIMEOUT. Also run as: python -m service.")
    ap.add_argument("--host", help="address to listen on (default: WANDELL_HOST, else 127.0.0.1)")
    ap.add_argument("--port", type=int, help="port to listen on (default: WANDELL_PORT, else 8000)")
    return ap


def main(argv=None) -> None:
    args = _parser().parse_args(argv)       # --help prints the usage and exits 0: no server

    # before anything starts a thread (the app's imports, uvicorn): glibc gives each new thread an
    # arena of its own, and what they keep scattered a trim does not give back (service.workers)
    from .workers import limit_malloc_arenas

    limit_malloc_arenas()

    import uvicorn

    from .settings import settings_or_exit

    s = settings_or_exit("python -m service")     # a WANDELL_* variable out of range: exit 2 naming it
    IdleClosingH11Protocol.max_connections = connection_cap(s.max_connections)
    logging.getLogger("asyncio").addFilter(_RateLimitedAcceptErrors())
    uvicorn.run("service.app:app", host=args.host or s.host, port=s.port if args.port is None else args.port,
                timeout_keep_alive=s.keep_alive_timeout, http=IdleClosingH11Protocol)


if __name__ == "__main__":
    main()
