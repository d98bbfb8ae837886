"""``python -m service``: run the API with uvicorn on the embedded defaults
(127.0.0.1:8000).

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


def main() -> None:
    import uvicorn

    from .settings import get_settings

    s = get_settings()
    uvicorn.run("service.app:app", host=s.host, port=s.port, timeout_keep_alive=s.keep_alive_timeout,
                http=IdleClosingH11Protocol)


if __name__ == "__main__":
    main()
