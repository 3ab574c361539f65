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

The API key of the JSON API's writes is checked here too, from the X-API-Key header, before the route reads
anything of the body (issue 10, item 8): FastAPI parses a multipart body - spooling every file to a temp
folder - before it runs the route's dependencies, so an unauthenticated 158 MB upload was written in full
before its 401.  The web forms (/ui/...) carry their key in a form field or a cookie and check it themselves.
"""
from __future__ import annotations

import hmac
import json
from urllib.parse import urlsplit

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Receive, Scope, Send

from .throttle import KeyThrottle, client_address

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
FORM_PREFIX = "/ui/"   # web form posts: the key comes in the form or the cookie (service.web.forms)
KEY_HEADER = "x-api-key"


class RequestGuard:
    """ASGI middleware: 400 for a Host not in ``allowed_hosts``, 403 for a cross-site unsafe request, 401 for
    a write to the JSON API without the API key (before its body is read).

    Parameters
    ----------
    app : ASGI app
    allowed_hosts : tuple of str
        Host names served (no port); ``"*"`` serves any.
    api_key : str, optional
        The key writes need in X-API-Key (None: writes need none).
    throttle : KeyThrottle, optional
        Counts failed keys per client address; a throttled address gets 429 with Retry-After.
    """

    def __init__(self, app: ASGIApp, allowed_hosts: tuple[str, ...], api_key: str | None = None,
                 throttle: KeyThrottle | None = None):
        self.app = app
        self.allowed = frozenset(name.lower() for name in allowed_hosts)
        self.api_key = api_key
        self.throttle = throttle

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
            if self.api_key is not None and not scope["path"].startswith(FORM_PREFIX):
                address = client_address(scope)
                wait = self.throttle.retry_after(address) if self.throttle else None
                if wait is not None and self.throttle is not None:
                    await _refuse(send, 429, self.throttle.message(wait),
                                  [(b"retry-after", str(wait).encode()), (b"connection", b"close")])
                    return
                if not self._key_matches(headers.get(KEY_HEADER)):
                    if self.throttle:
                        self.throttle.failed(address)
                    await _refuse(send, 401, "missing or wrong API key: send it in the X-API-Key header",
                                  [(b"www-authenticate", b"X-API-Key"), (b"connection", b"close")])
                    return
        await self.app(scope, receive, send)

    def _key_matches(self, key: str | None) -> bool:
        if self.api_key is None:
            return True
        return bool(key) and hmac.compare_digest(str(key).encode(), self.api_key.encode())


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


async def _refuse(send: Send, status: int, detail: str, headers: list[tuple[bytes, bytes]] | None = None) -> None:
    """Answer without reading the request's body (with Connection: close, the server need not drain it)."""
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *(headers or [])]})
    await send({"type": "http.response.body", "body": body})
