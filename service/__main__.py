"""``python -m service`` (installed as ``wandell-serve``): run the API with
uvicorn on the embedded defaults (127.0.0.1:8000), ``--host``/``--port`` or
``WANDELL_HOST``/``WANDELL_PORT``; ``--help`` prints the usage.

Connections that send nothing are closed: uvicorn times the idle gap after
a response (``timeout_keep_alive``, ``WANDELL_KEEP_ALIVE_TIMEOUT``) but not a
connection that never completes a request's headers, which it would keep
open for ever (slowloris). :class:`IdleClosingH11Protocol` gives those the
same deadline; a body that stalls is cut off by the upload middleware
(``WANDELL_BODY_TIMEOUT``, :mod:`service.limits`).
"""

from __future__ import annotations

from uvicorn.protocols.http.h11_impl import H11Protocol


class IdleClosingH11Protocol(H11Protocol):
    """uvicorn's h11 protocol, closing a connection whose next request's
    headers are not complete ``timeout_keep_alive`` seconds after it opened
    or after the previous response."""

    _header_deadline = None

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
        self._arm_header_deadline()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing():
            self._arm_header_deadline()

    def connection_lost(self, exc) -> None:
        if self._header_deadline is not None:
            self._header_deadline.cancel()
            self._header_deadline = None
        super().connection_lost(exc)


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

    import uvicorn

    from .settings import get_settings

    s = get_settings()
    uvicorn.run("service.app:app", host=args.host or s.host, port=s.port if args.port is None else args.port,
                timeout_keep_alive=s.keep_alive_timeout, http=IdleClosingH11Protocol)


if __name__ == "__main__":
    main()
