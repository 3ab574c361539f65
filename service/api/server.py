"""How `learnest serve` runs uvicorn: timeouts for slow or idle clients and a concurrency limit.  Without them,
idle, partial-header and 1-byte-per-5-s connections stay open for as long as the client likes, each holding a
socket and, once its headers are in, a worker thread.

- Headers: uvicorn closes an idle keep-alive connection (``timeout_keep_alive``) but has no limit on how
  long a request's headers may take to arrive, nor on a new connection that never sends anything.
  `DeadlineH11Protocol` (uvicorn's h11 protocol plus one timer) closes a connection whose next request's
  headers are not complete within ``LEARNEST_HEADER_TIMEOUT_S`` of the connection opening or of the last
  response.
- Body: `BodyDeadline` (ASGI middleware) gives a body ``LEARNEST_BODY_TIMEOUT_S`` plus one second per
  ``LEARNEST_BODY_MIN_RATE`` bytes received (the rule of Apache's mod_reqtimeout: a slow but steady upload
  finishes, a trickle does not); past it the request gets a 408 and its connection is closed.  It applies
  to receiving a request's body only, never to sending a response: a slow download runs to its end.
- Answers: a client that takes no byte of an answer for ``LEARNEST_SEND_TIMEOUT_S`` (its socket full, the
  server's write buffer not shrinking) is dropped by `DeadlineH11Protocol` (the connection aborted): a
  stalled reader no longer holds a socket, a worker's stream and the file it reads.  One that reads, however
  slowly, is never cut off.
- Proxies: X-Forwarded-For is believed only from ``LEARNEST_TRUSTED_PROXIES`` (none by default), so the
  client address - what the failed-key throttle counts - is the connection's peer unless a configured proxy
  names it (uvicorn alone believes the header from 127.0.0.1).
- Concurrency: uvicorn's ``limit_concurrency`` answers 503 beyond that many connections and tasks;
  ``h11_max_incomplete_event_size`` caps the bytes of a request line plus headers.
"""
from __future__ import annotations

import asyncio
import time
from functools import lru_cache
from typing import Any

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

from ..config import Settings


@lru_cache(maxsize=1)
def _timeouts_from_settings() -> tuple[float, float]:
    # The protocol class is named to uvicorn by import path (its worker processes import it), so it reads its
    # settings from the environment like the app does; `learnest serve --header-timeout-s` sets them there.
    settings = Settings()
    return settings.header_timeout_s, settings.send_timeout_s


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
    _header_timer: asyncio.TimerHandle | None = None
    _send_timer: asyncio.TimerHandle | None = None
    _send_buffered = 0

    def _header_timeout_s(self) -> float:
        return self.header_timeout_s if self.header_timeout_s is not None else _timeouts_from_settings()[0]

    def _send_timeout_s(self) -> float:
        return self.send_timeout_s if self.send_timeout_s is not None else _timeouts_from_settings()[1]

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._arm_header_timer()

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm_header_timer()
        self._disarm_send_timer()
        super().connection_lost(exc)

    def pause_writing(self) -> None:
        super().pause_writing()
        self._arm_send_timer()

    def resume_writing(self) -> None:
        self._disarm_send_timer()
        super().resume_writing()

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


MIN_WAIT_S = 0.05   # BodyDeadline: the shortest wait for a part of the body, s


class BodyDeadline:
    """ASGI middleware: a request body must arrive within ``timeout_s`` plus one second per ``min_rate``
    bytes received, else 408 (with ``Connection: close``: the rest of the body is not waited for).

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
    """

    def __init__(self, app: ASGIApp, timeout_s: float, min_rate: float) -> None:
        self.app, self.timeout_s, self.min_rate = app, timeout_s, min_rate

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
            remaining = start + self.timeout_s + received / self.min_rate - time.monotonic()
            try:
                # past the deadline a part the server already holds is still taken (a route that reads late
                # is not the client's delay): the wait is never shorter than MIN_WAIT_S
                message = await asyncio.wait_for(receive(), timeout=max(remaining, MIN_WAIT_S))
            except TimeoutError:
                # an HTTPException passes FastAPI's handlers as this status (as the upload size limit's 413)
                raise HTTPException(408, f"request body too slow: it must arrive within {self.timeout_s:g} s plus "
                                         f"1 s per {self.min_rate:g} bytes (LEARNEST_BODY_TIMEOUT_S, "
                                         "LEARNEST_BODY_MIN_RATE)", headers={"Connection": "close"}) from None
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


def uvicorn_options(settings: Settings) -> dict[str, Any]:
    """The keyword arguments of `uvicorn.run` / `uvicorn.Config` that the settings decide."""
    proxies = settings.trusted_proxy_addresses
    # uvicorn believes X-Forwarded-For from 127.0.0.1 unless told otherwise: on loopback anyone could then
    # choose the address the key throttle counts.  Believed only from the configured proxies.
    return {"proxy_headers": bool(proxies), "forwarded_allow_ips": ",".join(proxies) if proxies else "",
            "http": "learnest.service.api.server:DeadlineH11Protocol",
            "timeout_keep_alive": settings.keep_alive_s,
            "limit_concurrency": settings.limit_concurrency or None,
            "h11_max_incomplete_event_size": settings.max_header_bytes,
            "timeout_graceful_shutdown": settings.graceful_shutdown_s}
