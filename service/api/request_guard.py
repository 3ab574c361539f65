"""Requests for other host names, writes a browser sends from another site, and requests without the token
their route needs are refused before any route runs.

DNS rebinding: a page on evil.example whose name re-resolves to 127.0.0.1 reaches a server on localhost
with ``Host: evil.example``.  Only the names in ``LEARNEST_ALLOWED_HOSTS`` are served (default: the
loopback names; ``*`` serves any, for deployments behind a proxy that checks names itself).

Cross-site writes (CSRF): a page on any site could make the user's browser POST to ``/ui/...`` and start
jobs.  Browsers label such requests: ``Origin`` on every cross-origin POST (or ``Sec-Fetch-Site:
cross-site``, or at least a ``Referer``).  A write whose origin is not this server is refused, and the web
session's cookie is SameSite=Strict, so another site's form never carries it.  Clients that are not browsers
(curl, scripts) send none of these headers and are not affected; their token guards them.

Tokens (service.api.access has the scope of every route, service.api.auth tells who a request is): checked
here, before the route reads the body - FastAPI parses a multipart body, spooling every file to a temp folder,
before it runs the route's dependencies, so an unauthenticated 158 MB upload would be written in full before
its 401.  The JSON API takes the token in ``Authorization: Bearer`` or ``X-API-Key``; the web session's cookie
counts for reads everywhere and for the forms' posts (/ui/...), never for the JSON API's writes.  A network
that sent too many wrong tokens gets 429 for its next wrong ones (service.api.throttle); a right token always
passes.  A browser asking for a page without a token is sent to the sign-in page.
"""
from __future__ import annotations

import html
import json
from collections.abc import Callable
from urllib.parse import quote, urlsplit

import anyio.to_thread
from starlette.datastructures import Headers
from starlette.requests import cookie_parser
from starlette.types import ASGIApp, Receive, Scope, Send

from ..storage.database import Database
from ..storage.tokens import Principal
from .access import PUBLIC, required_scope
from .auth import SESSION_COOKIE, Authenticator, Identity, current_principal, presented_token
from .throttle import KeyThrottle, client_address

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
FORM_PREFIX = "/ui/"   # the web forms: their posts may carry the session cookie
SIGN_IN = "/ui/signin"
CLOSE = (b"connection", b"close")


def app_database(scope: Scope) -> Database | None:
    """The registry of the app serving ``scope`` (its started Services), or None before it has one."""
    services = getattr(getattr(scope.get("app"), "state", None), "services", None)
    return getattr(services, "db", None)


class RequestGuard:
    """ASGI middleware: 400 for a Host not in ``allowed_hosts``, 403 for a cross-site unsafe request, 401 (or,
    for a browser's page, a redirect to sign in) for a request without the token its route needs, 403 for a
    token whose scope is too narrow - all before the request's body is read.  The request's `Principal` is
    left in ``scope["state"]["principal"]`` for the routes.

    Parameters
    ----------
    app : ASGI app
    allowed_hosts : tuple of str
        Host names served (no port); ``"*"`` serves any.
    api_key : str, optional
        LEARNEST_API_KEY, an admin token (None: only the registry's tokens).
    throttle : KeyThrottle, optional
        Counts wrong tokens per client network; past its limit a wrong token gets 429 with Retry-After.
    public_reads : bool
        LEARNEST_PUBLIC_READS: reads need no token.
    database : callable, optional
        ``database(scope)`` -> the registry (default: the serving app's, `app_database`).
    """

    def __init__(self, app: ASGIApp, allowed_hosts: tuple[str, ...], api_key: str | None = None,
                 throttle: KeyThrottle | None = None, public_reads: bool = False,
                 database: Callable[[Scope], Database | None] = app_database):
        self.app = app
        self.allowed = frozenset(name.lower() for name in allowed_hosts)
        self.auth = Authenticator(api_key, public_reads, database)
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
        safe = scope["method"] in SAFE_METHODS
        if not safe:
            problem = cross_site_problem(headers, host)
            if problem:
                await _refuse(send, 403, problem)
                return
        needed = required_scope(scope["method"], scope["path"])
        if needed != PUBLIC:
            cookie = cookie_parser(headers.get("cookie", "")).get(SESSION_COOKIE)
            session = cookie if safe or scope["path"].startswith(FORM_PREFIX) else None
            identity = await anyio.to_thread.run_sync(self.auth.identify, scope, presented_token(headers), session)
            if not await self._admitted(scope, headers, send, identity, needed):
                return
            scope.setdefault("state", {})["principal"] = identity.principal
            reset = current_principal.set(identity.principal)
            try:
                await self.app(scope, receive, send)
            finally:
                current_principal.reset(reset)
            return
        await self.app(scope, receive, send)

    async def _admitted(self, scope: Scope, headers: Headers, send: Send, identity: Identity, needed: str) -> bool:
        """Whether ``identity`` may make this request; if not, the refusal is sent."""
        principal = identity.principal
        if principal is not None and principal.allows(needed):
            return True
        if principal is not None and principal.signed_in:
            await self._forbidden(scope, send, principal, needed)
            return False
        # no token (public reads let it read, not this), or a wrong one
        if not identity.failed and _wants_page(scope, headers):
            await _to_sign_in(scope, send, identity.stale_session)   # a person without a session: no guess
            return False
        # only wrong tokens are throttled (a request without one guesses nothing), and a right token passes, so
        # no one can lock its owner out
        if identity.failed and self.throttle is not None:
            address = client_address(scope)
            wait = self.throttle.retry_after(address)
            if wait is not None:
                await _refuse(send, 429, self.throttle.message(wait), [(b"retry-after", str(wait).encode()), CLOSE])
                return False
            self.throttle.failed(address)
        problem = ("the token is not valid (unknown or revoked)" if identity.failed
                   else "this server needs a token")
        if scope["path"].startswith(FORM_PREFIX):
            await _refuse_page(send, 401, problem)
        else:
            await _refuse(send, 401, f"{problem}: send it as 'Authorization: Bearer TOKEN' or in the X-API-Key "
                                     "header (`learnest tokens create NAME --scope read|write|admin` makes one)",
                          [(b"www-authenticate", b'Bearer realm="learnest"'), CLOSE])
        return False

    async def _forbidden(self, scope: Scope, send: Send, principal: Principal, needed: str) -> None:
        detail = f"{scope['method']} {scope['path']} needs a token of scope {needed}; {principal.name!r} has scope " \
                 f"{principal.scope}"
        if scope["path"].startswith(FORM_PREFIX) or scope["path"] == "/":
            await _refuse_page(send, 403, detail)
        else:
            await _refuse(send, 403, detail, [CLOSE])


def _wants_page(scope: Scope, headers: Headers) -> bool:
    """A browser navigating to a page (a GET that accepts HTML): sent to sign in rather than given a 401."""
    return scope["method"] in ("GET", "HEAD") and "text/html" in headers.get("accept", "")


async def _to_sign_in(scope: Scope, send: Send, clear_cookie: bool) -> None:
    """303 to the sign-in page, which comes back here after (``next``: this path and query, local only)."""
    query = scope.get("query_string", b"").decode("latin-1")
    here = scope["path"] + (f"?{query}" if query else "")
    location = f"{SIGN_IN}?next={quote(here, safe='')}"
    extra = [(b"set-cookie", f"{SESSION_COOKIE}=; Max-Age=0; Path=/; HttpOnly; SameSite=Strict".encode())
             ] if clear_cookie else []
    await send({"type": "http.response.start", "status": 303,
                "headers": [(b"location", location.encode("latin-1")), (b"content-length", b"0"), *extra]})
    await send({"type": "http.response.body", "body": b""})


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


async def _refuse_page(send: Send, status: int, detail: str) -> None:
    """A form's or page's refusal, as a page a browser shows, with the way to sign in (the body is not read:
    Connection: close).  ``detail`` is escaped: it may hold the request's path."""
    body = (f"<!doctype html><html><head><meta charset='utf-8'><title>{status}</title></head><body>"
            f"<h1>{status}</h1><p>{html.escape(detail)}</p><p><a href='{SIGN_IN}'>sign in</a> with a token that "
            f"may do this &middot; <a href='/'>learnest</a></p></body></html>").encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/html; charset=utf-8"),
                            (b"content-length", str(len(body)).encode()), CLOSE]})
    await send({"type": "http.response.body", "body": body})


async def _refuse(send: Send, status: int, detail: str, headers: list[tuple[bytes, bytes]] | None = None) -> None:
    """Answer without reading the request's body (with Connection: close, the server need not drain it)."""
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *(headers or [])]})
    await send({"type": "http.response.body", "body": body})
