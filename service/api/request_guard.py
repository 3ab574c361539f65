"""Requests for other host names, and writes a browser sends from another site, are refused before any
route runs (issue 10).

DNS rebinding: a page on evil.example whose name re-resolves to 127.0.0.1 reaches a server on localhost
with ``Host: evil.example``.  Only the names in ``LEARNEST_ALLOWED_HOSTS`` are served (default: the
loopback names; ``*`` serves any, for deployments behind a proxy that checks names itself).

Cross-site writes (CSRF): with no API key (the default), a page on any site could make the user's browser
POST to ``/ui/...`` and start jobs.  Browsers label such requests: ``Origin`` on every cross-origin POST
(or ``Sec-Fetch-Site: cross-site``, or at least a ``Referer``).  A write whose origin is not this server
is refused.  Clients that are not browsers (curl, scripts) send none of these headers and are not
affected; the API key guards them when it is set.
"""
from __future__ import annotations

import json
from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


class RequestGuard:
    """ASGI middleware: 400 for a Host not in ``allowed_hosts``, 403 for a cross-site unsafe request.

    Parameters
    ----------
    app : ASGI app
    allowed_hosts : tuple of str
        Host names served (no port); ``"*"`` serves any.
    """

    def __init__(self, app: ASGIApp, allowed_hosts: tuple[str, ...]):
        self.app = app
        self.allowed = frozenset(name.lower() for name in allowed_hosts)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = Headers(scope=scope)
        host = headers.get("host", "")
        name = host_name(host)
        if "*" not in self.allowed and name not in self.allowed:
            await _refuse(send, 400, f"host {name!r} is not served here (served: {', '.join(sorted(self.allowed))}); "
                                     "set LEARNEST_ALLOWED_HOSTS to serve it")
            return
        if scope["method"] not in SAFE_METHODS:
            problem = cross_site_problem(headers, host)
            if problem:
                await _refuse(send, 403, problem)
                return
        await self.app(scope, receive, send)


def host_name(host: str) -> str:
    """The name in a Host header, without the port: ``"localhost:8000"`` -> ``"localhost"``,
    ``"[::1]:8000"`` -> ``"::1"``."""
    host = host.strip().lower()
    if host.startswith("["):
        return host[1:host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


def cross_site_problem(headers: Headers, host: str) -> str | None:
    """Why an unsafe request came from another site (None if it did not, or if it says nothing)."""
    origin = headers.get("origin")
    if origin is not None:
        if origin == "null" or urlsplit(origin).netloc.lower() != host.lower():
            return f"cross-site request refused: it comes from {origin}, not from this server ({host})"
        return None
    if headers.get("sec-fetch-site") == "cross-site":
        return "cross-site request refused (Sec-Fetch-Site: cross-site)"
    referer = headers.get("referer")
    if referer and urlsplit(referer).netloc.lower() != host.lower():
        return f"cross-site request refused: it comes from {urlsplit(referer).netloc}, not from this server ({host})"
    return None


async def _refuse(send: Send, status: int, detail: str) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]})
    await send({"type": "http.response.body", "body": body})
