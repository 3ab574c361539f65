"""Requests for other host names, and writes a browser sends from another site, are refused before any
route runs.

DNS rebinding: a page on evil.example whose name re-resolves to 127.0.0.1 reaches a server on localhost
with ``Host: evil.example``.  Only the names in ``LEARNEST_ALLOWED_HOSTS`` are served (default: the
loopback names; ``*`` serves any, for deployments behind a proxy that checks names itself).

Cross-site writes (CSRF): with no API key (the default), a page on any site could make the user's browser
POST to ``/ui/...`` and start jobs.  Browsers label such requests: ``Origin`` on every cross-origin POST
(or ``Sec-Fetch-Site: cross-site``, or at least a ``Referer``).  A write whose origin is not this server
is refused.  Clients that are not browsers (curl, scripts) send none of these headers and are not
affected; the API key guards them when it is set.

The API key of every write is checked here too, before the route reads its body: FastAPI parses a multipart
body - spooling every file to a temp folder - before it runs the route's dependencies, so an unauthenticated
158 MB upload would be written in full before its 401.  The JSON API's writes carry the key in the X-API-Key
header.  The web forms (/ui/...) carry it in the ``learnest_api_key`` cookie or a form field:
for the field, only the start of the body is read (at most FORM_PEEK_BYTES, within the body deadline), and in
a multipart form the field must come before the files (the upload form puts it first), so no file byte is
read before the key is known good.  A network that sent too many wrong keys gets 429 for its next wrong ones
(service.api.throttle); the right key always passes.
"""
from __future__ import annotations

import asyncio
import hmac
import json
import re
import time
from urllib.parse import parse_qsl, urlsplit

from starlette.datastructures import Headers
from starlette.requests import cookie_parser
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from .throttle import KeyThrottle, client_address

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
FORM_PREFIX = "/ui/"   # web form posts: the key comes in the form or the cookie (service.web.forms)
KEY_HEADER = "x-api-key"
KEY_COOKIE = "learnest_api_key"   # the web forms' cookie (service.web.forms keeps a typed key in it)
KEY_FIELD = "api_key"             # the forms' field
FORM_PEEK_BYTES = 1 << 20         # of a form's body read to find its key field (a form without files: ~1 kB)
MULTIPART_PEEK_BYTES = 64 << 10   # of a multipart form's body read to find the key field before the files


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
        Counts wrong keys per client network; past its limit a wrong key gets 429 with Retry-After.
    """

    def __init__(self, app: ASGIApp, allowed_hosts: tuple[str, ...], api_key: str | None = None,
                 throttle: KeyThrottle | None = None, peek_timeout_s: float = 30.0):
        self.app = app
        self.allowed = frozenset(name.lower() for name in allowed_hosts)
        self.api_key = api_key
        self.throttle = throttle
        self.peek_timeout_s = peek_timeout_s   # for the start of a form's body (the body deadline's)

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
            if self.api_key is not None:
                address = client_address(scope)
                form = scope["path"].startswith(FORM_PREFIX)
                if form:   # the forms' key: the cookie, else the form's field (service.web.forms)
                    matches = self._key_matches(cookie_parser(headers.get("cookie", "")).get(KEY_COOKIE))
                    if not matches:
                        try:
                            key, receive = await self._form_key(headers, receive)
                        except TimeoutError:
                            await _refuse(send, 408, "request body too slow (LEARNEST_BODY_TIMEOUT_S)",
                                          [(b"connection", b"close")])
                            return
                        matches = self._key_matches(key)
                else:
                    matches = self._key_matches(headers.get(KEY_HEADER))
                if not matches:
                    # only wrong keys are throttled: the right one passes, so no one can lock its owner out
                    wait = self.throttle.retry_after(address) if self.throttle else None
                    if wait is not None and self.throttle is not None:
                        await _refuse(send, 429, self.throttle.message(wait),
                                      [(b"retry-after", str(wait).encode()), (b"connection", b"close")])
                        return
                    if self.throttle:
                        self.throttle.failed(address)
                    if form:
                        await _refuse_page(send, 401, "missing or wrong API key: type it into the form's API key "
                                                      "field")
                    else:
                        await _refuse(send, 401, "missing or wrong API key: send it in the X-API-Key header",
                                      [(b"www-authenticate", b"X-API-Key"), (b"connection", b"close")])
                    return
        await self.app(scope, receive, send)

    def _key_matches(self, key: str | None) -> bool:
        if self.api_key is None:
            return True
        return bool(key) and hmac.compare_digest(str(key).encode(), self.api_key.encode())

    async def _form_key(self, headers: Headers, receive: Receive) -> tuple[str | None, Receive]:
        """(the form's key field or None, a receive that gives the app the whole body again).  Reads only the
        start of the body: a url-encoded form up to FORM_PEEK_BYTES, a multipart one until its key field, a
        file part, or MULTIPART_PEEK_BYTES; TimeoutError past the body deadline."""
        kind = headers.get("content-type", "").split(";", 1)[0].strip().lower()
        boundary = _boundary(headers.get("content-type", "")) if kind == "multipart/form-data" else None
        limit = MULTIPART_PEEK_BYTES if boundary else FORM_PEEK_BYTES
        messages: list[Message] = []
        body, more, key = b"", True, None
        deadline = time.monotonic() + self.peek_timeout_s
        while more and len(body) <= limit:
            message = await asyncio.wait_for(receive(), timeout=max(deadline - time.monotonic(), 0.0))
            messages.append(message)
            if message["type"] != "http.request":
                break
            body += message.get("body", b"")
            more = bool(message.get("more_body", False))
            if boundary is not None:
                found, decided = _multipart_key(body, boundary, complete=not more)
                if decided:
                    key = found
                    break
        else:
            if kind == "application/x-www-form-urlencoded" and not more:
                key = dict(parse_qsl(body.decode("latin-1"), keep_blank_values=True)).get(KEY_FIELD)

        async def replay() -> Message:
            if messages:
                return messages.pop(0)
            return await receive()

        return key, replay


def _boundary(content_type: str) -> bytes | None:
    match = re.search(r'boundary="?([^";]+)"?', content_type)
    return match[1].encode("latin-1") if match else None


def _multipart_key(body: bytes, boundary: bytes, complete: bool) -> tuple[str | None, bool]:
    """(the key field's value, whether that is decided) from the start of a multipart body: decided when the
    key field is complete, when a file part begins before it (no key before the files), or at the end of the
    body; not yet when the part under way may still be it."""
    delimiter = b"--" + boundary
    position = body.find(delimiter)
    while position >= 0:
        head_start = position + len(delimiter)
        if body[head_start:head_start + 2] == b"--":   # the closing delimiter
            return None, True
        head_end = body.find(b"\r\n\r\n", head_start)
        if head_end < 0:
            return None, complete
        head = body[head_start:head_end].decode("latin-1").lower()
        if "filename=" in head:
            return None, True
        content_end = body.find(b"\r\n" + delimiter, head_end + 4)
        if content_end < 0:
            return None, complete
        if re.search(r'name="?' + KEY_FIELD + r'"?(;|\s|$)', head):
            return body[head_end + 4:content_end].decode("utf-8", "replace"), True
        position = content_end + 2
    return None, complete


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
    """A form's refusal, as a page a browser shows (the body is not read: Connection: close)."""
    body = (f"<!doctype html><html><head><meta charset='utf-8'><title>{status}</title></head><body>"
            f"<h1>{status}</h1><p>{detail}</p><p><a href='/'>learnest</a></p></body></html>").encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"text/html; charset=utf-8"),
                            (b"content-length", str(len(body)).encode()), (b"connection", b"close")]})
    await send({"type": "http.response.body", "body": body})


async def _refuse(send: Send, status: int, detail: str, headers: list[tuple[bytes, bytes]] | None = None) -> None:
    """Answer without reading the request's body (with Connection: close, the server need not drain it)."""
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *(headers or [])]})
    await send({"type": "http.response.body", "body": body})
