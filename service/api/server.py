"""How `learnest serve` runs uvicorn: timeouts for slow or idle clients and a concurrency limit.  Without them,
idle, partial-header and 1-byte-per-5-s connections stay open for as long as the client likes, each holding a
socket and, once its headers are in, a worker thread.  `service.local.serving.uvicorn_options` gives uvicorn
the protocol below by import path and the settings' limits.

- Headers: uvicorn closes an idle keep-alive connection (``timeout_keep_alive``) but has no limit on how
  long a request's headers may take to arrive, nor on a new connection that never sends anything.
  `DeadlineH11Protocol` (uvicorn's h11 protocol plus one timer) closes a connection whose next request's
  headers are not complete within ``LEARNEST_HEADER_TIMEOUT_S`` of the connection opening or of the last
  response.  It also refuses headers past ``LEARNEST_MAX_HEADER_BYTES`` in all with 431 (h11's own limit
  counts only the bytes it holds while waiting, so headers sent in one packet passed it), and a request with
  both Content-Length and Transfer-Encoding with 400 (two framings: what request smuggling through a proxy
  relies on).
- Clients: ``LEARNEST_MAX_CLIENT_CONNECTIONS`` connections at once per client network (`throttle.client_network`:
  an IPv4 /24, an IPv6 /64); a further one gets 503 and is closed, so one client cannot hold every slot of
  ``limit_concurrency`` (the configured proxies are exempt: every client comes through them).
- Body: `BodyDeadline` (ASGI middleware) gives a body ``LEARNEST_BODY_TIMEOUT_S`` plus one second per
  ``LEARNEST_BODY_MIN_RATE`` bytes received (the rule of Apache's mod_reqtimeout: a slow but steady upload
  finishes, a trickle does not), never more than ``LEARNEST_BODY_MAX_S`` in all; past it the request gets a
  408 and its connection is closed.  It applies to receiving a request's body only, never to sending a
  response: a slow download runs to its end.
- Answers: a client that takes no byte of an answer for ``LEARNEST_SEND_TIMEOUT_S`` (its socket full, the
  server's write buffer not shrinking) is dropped by `DeadlineH11Protocol` (the connection aborted): a
  stalled reader no longer holds a socket, a worker's stream and the file it reads.  One that reads, however
  slowly, is never cut off.
- Proxies: X-Forwarded-For is believed only from ``LEARNEST_TRUSTED_PROXIES`` (none by default), so the
  client address - what the failed-key throttle counts - is the connection's peer unless a configured proxy
  names it (uvicorn alone believes the header from 127.0.0.1).
- Concurrency: uvicorn's ``limit_concurrency`` answers 503 beyond that many connections and tasks;
  ``h11_max_incomplete_event_size`` caps the bytes of a request line plus headers held while they arrive.
"""
from __future__ import annotations

import asyncio
import time
from collections import Counter
from functools import lru_cache
from http import HTTPStatus

import h11
from starlette.exceptions import HTTPException
from starlette.formparsers import MultiPartParser
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

from ..config import Settings
from .throttle import client_network


@lru_cache(maxsize=1)
def _settings() -> Settings:
    # The protocol class is named to uvicorn by import path (its worker processes import it), so it reads its
    # settings from the environment like the app does; `learnest serve --header-timeout-s` sets it there.
    return Settings()


class HeaderCheckedConnection(h11.Connection):
    """h11's server connection that refuses a request whose head is larger than ``max_head_bytes`` in all, or
    that declares both Content-Length and Transfer-Encoding.  The refusal (status, message) is kept in
    `refusal` for the protocol's answer; h11 sees a protocol error."""

    def __init__(self, max_head_bytes: int) -> None:
        super().__init__(h11.SERVER, max_head_bytes)
        self.max_head_bytes = max_head_bytes
        self.refusal: tuple[int, str] | None = None

    def next_event(self):
        event = super().next_event()
        if isinstance(event, h11.Request):
            self.refusal = request_head_problem(event, self.max_head_bytes)
            if self.refusal is not None:
                raise h11.RemoteProtocolError(self.refusal[1], error_status_hint=self.refusal[0])
        return event


def request_head_problem(request: h11.Request, max_head_bytes: int) -> tuple[int, str] | None:
    """(status, why) when a request's head must be refused, else None: 431 for more than ``max_head_bytes`` of
    request line and headers, 400 for Content-Length together with Transfer-Encoding."""
    names = [name.lower() for name, _ in request.headers.raw_items()]
    size = len(request.method) + len(request.target) + 11 + sum(len(name) + len(value) + 4 for name, value
                                                                 in request.headers.raw_items())
    if size > max_head_bytes:
        return 431, (f"request headers too large: {size} bytes, the limit is {max_head_bytes} "
                     "(LEARNEST_MAX_HEADER_BYTES)")
    if b"content-length" in names and b"transfer-encoding" in names:
        return 400, "Content-Length together with Transfer-Encoding: send one framing of the body"
    return None


class DeadlineH11Protocol(H11Protocol):
    """uvicorn's h11 protocol that closes a connection whose request headers do not arrive in time, and aborts
    one whose client stops taking the answer.

    The header timer starts when the connection opens and again after each response; it stops when a
    request's headers are complete (a new request/response cycle begins).  While a request is being answered
    there is no header timer (the body has its own deadline, `BodyDeadline`).  The send timer runs while the
    transport's write buffer is over its high-water mark (the client's socket is full): when it passes and
    the buffer did not shrink, the connection is aborted; when it shrank, it starts again.
    """

    header_timeout_s: float | None = None   # None: LEARNEST_HEADER_TIMEOUT_S (a subclass may fix it)
    send_timeout_s: float | None = None     # None: LEARNEST_SEND_TIMEOUT_S (a subclass may fix it)
    max_client_connections: int | None = None   # None: LEARNEST_MAX_CLIENT_CONNECTIONS (a subclass may fix it)
    trusted_proxies: tuple[str, ...] | None = None   # None: LEARNEST_TRUSTED_PROXIES
    _header_timer: asyncio.TimerHandle | None = None
    _send_timer: asyncio.TimerHandle | None = None
    _send_buffered = 0
    _network: str | None = None   # the client network this connection is counted in
    open_per_network: Counter[str] = Counter()   # this process's open connections per client network

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.conn = HeaderCheckedConnection(self.config.h11_max_incomplete_event_size or _settings().max_header_bytes)

    def _header_timeout_s(self) -> float:
        return self.header_timeout_s if self.header_timeout_s is not None else _settings().header_timeout_s

    def _send_timeout_s(self) -> float:
        return self.send_timeout_s if self.send_timeout_s is not None else _settings().send_timeout_s

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        if not self._admit_client():
            return
        self._arm_header_timer()

    def _admit_client(self) -> bool:
        """Count the connection in its client network, or answer 503 and close it when that network has its
        ``max_client_connections`` open already."""
        cap = self.max_client_connections if self.max_client_connections is not None else \
            _settings().max_client_connections
        proxies = self.trusted_proxies if self.trusted_proxies is not None else _settings().trusted_proxy_addresses
        if not cap or self.client is None or self.client[0] in proxies:
            return True
        network = client_network(self.client[0])
        if self.open_per_network[network] >= cap:
            self.logger.warning("refusing a connection: %s has %d open (LEARNEST_MAX_CLIENT_CONNECTIONS)", network,
                                cap)
            body = (f"too many connections from {network}: at most {cap} at once "
                    "(LEARNEST_MAX_CLIENT_CONNECTIONS)").encode()
            self.transport.write(b"HTTP/1.1 503 Service Unavailable\r\ncontent-type: text/plain; charset=utf-8\r\n"
                                 b"connection: close\r\ncontent-length: " + str(len(body)).encode() + b"\r\n\r\n"
                                 + body)
            self.transport.close()
            return False
        self._network = network
        self.open_per_network[network] += 1
        return True

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm_header_timer()
        self._disarm_send_timer()
        if self._network is not None:
            self.open_per_network[self._network] -= 1
            if self.open_per_network[self._network] <= 0:
                del self.open_per_network[self._network]
            self._network = None
        super().connection_lost(exc)

    def pause_writing(self) -> None:
        super().pause_writing()
        self._arm_send_timer()

    def resume_writing(self) -> None:
        self._disarm_send_timer()
        super().resume_writing()

    def send_400_response(self, msg: str) -> None:
        refusal = getattr(self.conn, "refusal", None)
        if refusal is None:
            super().send_400_response(msg)
            return
        status, detail = refusal   # a head `HeaderCheckedConnection` refused: say which limit
        self.logger.info("refusing a request: %s", detail)
        body = detail.encode()
        self.transport.write(self.conn.send(h11.Response(status_code=status, reason=HTTPStatus(status).phrase, headers=[
            (b"content-type", b"text/plain; charset=utf-8"), (b"content-length", str(len(body)).encode()),
            (b"connection", b"close")])) or b"")
        self.transport.write(self.conn.send(h11.Data(data=body)) or b"")
        self.transport.write(self.conn.send(h11.EndOfMessage()) or b"")
        self.transport.close()

    def handle_events(self) -> None:
        cycle = self.cycle
        super().handle_events()
        if self.cycle is not cycle:  # a request's headers are complete
            self._disarm_header_timer()

    def on_response_complete(self) -> None:
        # armed first: the pipelined request super() may start at once disarms it in handle_events
        self._arm_header_timer()
        super().on_response_complete()
        if self.transport.is_closing():
            self._disarm_header_timer()

    def _arm_header_timer(self) -> None:
        self._disarm_header_timer()
        self._header_timer = self.loop.call_later(self._header_timeout_s(), self._header_deadline_passed)

    def _disarm_header_timer(self) -> None:
        if self._header_timer is not None:
            self._header_timer.cancel()
            self._header_timer = None

    def _header_deadline_passed(self) -> None:
        self._header_timer = None
        waiting_for_headers = self.cycle is None or self.cycle.response_complete
        if waiting_for_headers and not self.transport.is_closing():
            self.logger.info("closing a connection whose request headers took longer than %g s (LEARNEST_HEADER_"
                             "TIMEOUT_S)", self._header_timeout_s())
            self.transport.close()

    def _arm_send_timer(self) -> None:
        self._disarm_send_timer()
        self._send_buffered = self.transport.get_write_buffer_size()
        self._send_timer = self.loop.call_later(self._send_timeout_s(), self._send_deadline_passed)

    def _disarm_send_timer(self) -> None:
        if self._send_timer is not None:
            self._send_timer.cancel()
            self._send_timer = None

    def _send_deadline_passed(self) -> None:
        self._send_timer = None
        if self.transport.get_write_buffer_size() < self._send_buffered:   # it reads, slowly: not stalled
            self._arm_send_timer()
            return
        self.logger.info("dropping a client that took no byte of its answer for %g s (LEARNEST_SEND_TIMEOUT_S)",
                         self._send_timeout_s())
        self.transport.abort()   # close() would wait for the buffer to drain, which a stalled client never lets


# Form parsing holds in memory only what it must.  Every file part goes to a temp file from its first bytes
# (Starlette's documented knob; its default kept parts under 1 MiB in memory, so a client withholding the
# closing boundary pinned up to the upload limit per request), and a form field is at most FORM_FIELD_BYTES
# (a notes field: 10 000 characters) among at most FORM_FIELDS (a page of checked flights: 100), so an upload in
# progress holds at most FORM_FIELDS x FORM_FIELD_BYTES = 16 MiB in memory.
MultiPartParser.spool_max_size = 1   # bytes; 0 would mean "never roll over to disk"
FORM_FIELD_BYTES = 64 << 10
FORM_FIELDS = 256


MIN_WAIT_S = 0.05   # BodyDeadline: the shortest wait for a part of the body, s


class BodyDeadline:
    """ASGI middleware: a request body must arrive within ``timeout_s`` plus one second per ``min_rate``
    bytes received, and within ``max_s`` in all, else 408 (with ``Connection: close``: the rest of the body is
    not waited for).  The ceiling is what bounds how long an upload holds its spooled parts: without it a
    client that keeps sending could keep its request open for as long as it liked.

    The deadline covers receiving the request's body only.  Once its last part is in (or the response has
    begun), ``receive()`` is the server's own again: a response streams for as long as it takes (a large
    download at a slow client's pace), and a route that listens for the client going away while it streams
    (Starlette's `FileResponse`, `StreamingResponse`) is never cut off by the body's clock.

    Parameters
    ----------
    app : ASGI app
    timeout_s : float
        Seconds a body gets before any of it is counted, s.
    min_rate : float
        Bytes per second that earn one more second each (B/s).
    max_s : float
        Seconds a body gets in all, however fast its bytes came (at least ``timeout_s``), s.
    """

    def __init__(self, app: ASGIApp, timeout_s: float, min_rate: float, max_s: float = float("inf")) -> None:
        self.app, self.timeout_s, self.min_rate = app, timeout_s, min_rate
        self.max_s = max(max_s, timeout_s)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start, received = time.monotonic(), 0
        # no deadline left once the last part of the body arrived or the response began, nor for a request
        # that declares no body (a GET: the server hands the app one empty part, however late it asks)
        headers = dict(scope.get("headers") or [])
        body_done = headers.get(b"content-length", b"0") in (b"", b"0") and b"transfer-encoding" not in headers

        async def timed_receive() -> Message:
            nonlocal received, body_done
            if body_done:
                return await receive()
            now = time.monotonic()
            remaining = start + self.timeout_s + received / self.min_rate - now
            try:
                if now > start + self.max_s:   # the ceiling holds however promptly each part came
                    raise TimeoutError
                # past the rate's deadline a part the server already holds is still taken (a route that reads
                # late is not the client's delay): the wait is never shorter than MIN_WAIT_S
                wait = min(max(remaining, MIN_WAIT_S), start + self.max_s - now + MIN_WAIT_S)
                message = await asyncio.wait_for(receive(), timeout=wait)
            except TimeoutError:
                # an HTTPException passes FastAPI's handlers as this status (as the upload size limit's 413)
                raise HTTPException(408, f"request body too slow: it must arrive within {self.timeout_s:g} s plus "
                                         f"1 s per {self.min_rate:g} bytes, {self.max_s:g} s at most "
                                         "(LEARNEST_BODY_TIMEOUT_S, LEARNEST_BODY_MIN_RATE, LEARNEST_BODY_MAX_S)",
                                    headers={"Connection": "close"}) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if not message.get("more_body", False):
                    body_done = True
            else:   # http.disconnect: nothing more will arrive
                body_done = True
            return message

        async def watched_send(message: Message) -> None:
            nonlocal body_done
            if message["type"] == "http.response.start":
                body_done = True   # whatever of the body the app did not read, it no longer waits for
            await send(message)

        await self.app(scope, timed_receive, watched_send)

