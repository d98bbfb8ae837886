"""A local service a web page cannot drive, as a pure ASGI middleware.

The service listens on loopback and has no accounts, so what keeps other
web pages out is the browser's same-origin rule, and that holds only if the
server checks two headers itself:

* ``Host``: a DNS-rebinding page (``attacker.example`` re-pointed at
  127.0.0.1) is same-origin with the service as far as the browser is
  concerned, but its requests carry ``Host: attacker.example``. Only the
  bound host (``Settings.host``), ``localhost``, ``127.0.0.1``, ``[::1]``
  and the names in ``WANDELL_ALLOWED_HOSTS`` are served; anything else is a
  400 ``{"error": "host_not_allowed"}`` before the app sees the request.
* ``Origin``: a page on any other origin may still *send* a form POST (the
  browser does not ask first for a multipart form) and start a batch. A
  request with a method other than GET/HEAD/OPTIONS whose ``Origin`` is
  present and is neither the service's own (``scheme://Host``) nor listed
  in ``WANDELL_ALLOWED_ORIGINS`` is a 403 ``{"error": "cross_origin"}``.
  Clients that are not browsers send no ``Origin`` and are not affected.

Every response also carries ``X-Content-Type-Options: nosniff`` and
``X-Frame-Options: DENY`` (the page sets its own Content-Security-Policy,
``frame-ancestors 'none'``, in :mod:`service.routers.web`).
"""

from __future__ import annotations

import re
from functools import lru_cache

from .errors import error_response
from .settings import Settings, get_settings

__all__ = ["HostOriginMiddleware", "allowed_hosts", "host_name"]

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
SECURITY_HEADERS = [(b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"DENY")]


#: A ``Host`` header (RFC 9110 section 7.2, RFC 3986 section 3.2.2): a
#: bracketed IPv6 literal, or a name/IPv4 of unreserved characters, then an
#: optional ``:port`` of digits; nothing else (no userinfo ``@``, no text
#: after the ``]``).
_HOST_RE = re.compile(r"\[(?P<v6>[0-9a-f:.]+)\](?::\d{0,5})?|(?P<name>[a-z0-9._~-]+)(?::\d{0,5})?")


def host_name(host: str, strict: bool = False) -> str | None:
    """``"127.0.0.1:8000"`` -> ``"127.0.0.1"``, ``"[::1]:80"`` -> ``"::1"``, lower case.

    ``strict`` (a request's ``Host`` header): ``None`` unless the whole
    value is one host and an optional port (:data:`_HOST_RE`), so
    ``127.0.0.1:8000@evil.com`` and ``[::1]evil.com`` match no allowed name.

    >>> host_name("127.0.0.1:8000@evil.com", strict=True) is None, host_name("[::1]:80", strict=True)
    (True, '::1')
    """
    host = host.strip().lower()
    if strict:
        m = _HOST_RE.fullmatch(host)
        return None if m is None else (m.group("v6") or m.group("name"))
    if host.startswith("["):
        return host[1:host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


@lru_cache(maxsize=8)
def _allowed(settings: Settings) -> tuple[frozenset, frozenset]:
    hosts = {"localhost", "127.0.0.1", "::1", host_name(settings.host)}
    hosts |= {host_name(h) for h in settings.allowed_hosts.split(",") if h.strip()}
    origins = {o.strip().lower().rstrip("/") for o in settings.allowed_origins.split(",") if o.strip()}
    return frozenset(hosts), frozenset(origins)


def allowed_hosts(settings: Settings | None = None) -> frozenset:
    """The host names served (see the module docstring)."""
    return _allowed(settings or get_settings())[0]


class HostOriginMiddleware:
    """400 for a Host not allowed, 403 for a cross-origin state-changing
    request, security headers on every response."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        hosts, origins = _allowed(get_settings())
        headers = {k.lower(): v for k, v in scope.get("headers") or ()}
        host = headers.get(b"host", b"").decode("latin-1")
        if host_name(host, strict=True) not in hosts:
            shown = host[:100] if host else "(none)"
            await error_response(400, "host_not_allowed", f"Host {shown!r} is not served here; allowed: "
                                 f"{sorted(hosts)} (WANDELL_ALLOWED_HOSTS adds names)")(scope, receive,
                                                                                        _with_headers(send))
            return
        origin = headers.get(b"origin")
        if origin is not None and scope.get("method", "GET").upper() not in SAFE_METHODS:
            o = origin.decode("latin-1").strip().lower().rstrip("/")
            own = f"{scope.get('scheme', 'http')}://{host.lower()}"
            if o != own and o not in origins:
                await error_response(403, "cross_origin", f"requests that change state are accepted from this "
                                     f"service's own page only, not from origin {o[:100]!r} "
                                     "(WANDELL_ALLOWED_ORIGINS adds origins)")(scope, receive, _with_headers(send))
                return
        await self.app(scope, receive, _with_headers(send))


def _with_headers(send):
    async def wrapped(message):
        if message["type"] == "http.response.start":
            present = {k.lower() for k, _ in message.get("headers") or ()}
            message = dict(message)
            message["headers"] = list(message.get("headers") or ()) + [
                (k, v) for k, v in SECURITY_HEADERS if k not in present]
        await send(message)

    return wrapped
