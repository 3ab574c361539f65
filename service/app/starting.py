"""The app `learnest serve` runs: it listens at once and loads the service behind it.

Importing the service (the estimators, torch, CasADi, SQLAlchemy) and opening its database take seconds; uvicorn
listens only once its app is imported and started, so a client saw nothing at all until then (12 s to the first
`/health` on a loaded machine). `create_app` here imports nothing heavy: its lifespan starts a thread that
imports `learnest.service.app.factory`, builds that app and runs its start-up (migrations, executor, job runner),
then starts building the manual in the background (the slowest first answer: half a minute on a loaded machine;
started after the service, not beside it, which would slow the service's start by as much). While it loads:

- ``/health`` answers at once, 503 with ``{"status": "starting", ...}`` (a load balancer or a script waiting for
  200 waits on; a person with curl learns what is going on);
- ``/`` and the manual's pages (``/manual...``) answer at once with a page that reloads itself until the service
  is there (the manual's then says whether the manual is still being built);
- every other request waits for the service (up to `WAIT_S`) and is then answered by it, so a client that does
  not poll `/health` first sees a slow answer, never an error.

When the service cannot start (a database of a newer schema, a bad setting), the error is logged and the server
stops, as uvicorn stops when an app's start-up fails.
"""
from __future__ import annotations

import asyncio
import importlib
import importlib.metadata
import json
import logging
import os
import signal
import threading
import time
from typing import Any

SERVICE_APP = "learnest.service.app.factory:create_app"
WAIT_S = 120.0   # how long a request waits for the service to load before it gets 503
RELOAD_S = 2     # the start page reloads itself this often, s

log = logging.getLogger("uvicorn.error")   # uvicorn's own log: a start-up failure shows where uvicorn's would


class StartingApp:
    """ASGI app: `/health` and `/` at once while `SERVICE_APP` loads in a thread; then everything by it."""

    def __init__(self, service_app: str = SERVICE_APP, *, stop_on_failure: bool = True,
                 build_manual: bool = True) -> None:
        self.service_app, self.stop_on_failure, self.build_manual = service_app, stop_on_failure, build_manual
        self.app: Any = None            # the service, once started
        self.error: BaseException | None = None
        self.started = time.monotonic()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._settled: asyncio.Event | None = None   # set (on the server's loop) when the service is up or failed
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] == "lifespan":
            await self._lifespan(receive, send)
            return
        if self.app is None and self.error is None and scope["type"] == "http" and _answered_while_starting(scope):
            await self._starting_answer(scope["path"], send)
            return
        if self.app is None and self._settled is not None:
            try:
                await asyncio.wait_for(self._settled.wait(), timeout=WAIT_S)
            except TimeoutError:
                pass
        if self.app is None:
            if scope["type"] == "http":
                await _answer(send, 503, "application/json", json.dumps({"detail": self._not_up()}))
            return
        await self.app(scope, receive, send)

    # -- the service, loaded in a thread ------------------------------------------------------------------
    async def _lifespan(self, receive, send) -> None:
        while True:
            message = await receive()
            if message["type"] == "lifespan.startup":
                self._loop, self._settled = asyncio.get_running_loop(), asyncio.Event()
                self._thread = threading.Thread(target=self._load, name="learnest-service-start", daemon=True)
                self._thread.start()
                await send({"type": "lifespan.startup.complete"})
            elif message["type"] == "lifespan.shutdown":
                self._stop.set()
                if self._thread is not None:
                    await asyncio.to_thread(self._thread.join)
                await send({"type": "lifespan.shutdown.complete"})
                return

    def _load(self) -> None:
        """In the start thread: import and build the service, run its start-up, serve until the server stops."""
        try:
            module, name = self.service_app.split(":")
            app = getattr(importlib.import_module(module), name)()
            # its start-up and shut-down run on this thread's own loop: they are blocking work (the database's
            # migrations, the job runner's threads), which the server's loop must not wait for
            asyncio.run(self._run_service(app))
        except BaseException as error:   # noqa: BLE001 - any failure stops the server, with its reason logged
            self.error = error
            log.error("learnest could not start: %s", error, exc_info=error)
            self._settle()
            if self.stop_on_failure and not self._stop.is_set():
                os.kill(os.getpid(), signal.SIGTERM)   # uvicorn stops as it does on Ctrl-C

    async def _run_service(self, app) -> None:
        async with app.router.lifespan_context(app):
            self.app = app
            self._settle()
            log.info("learnest is up: %.1f s after the server started listening", time.monotonic() - self.started)
            if self.build_manual:
                _build_manual_in_background()
            while not self._stop.wait(0.2):
                pass

    def _settle(self) -> None:
        if self._loop is not None and self._settled is not None:
            self._loop.call_soon_threadsafe(self._settled.set)

    # -- the answers while it loads -------------------------------------------------------------------------
    def _not_up(self) -> str:
        if self.error is not None:
            return f"learnest could not start: {self.error}"
        return f"learnest is still starting after {WAIT_S:g} s"

    async def _starting_answer(self, path: str, send) -> None:
        seconds = time.monotonic() - self.started
        if path == "/health":
            body = {"status": "starting", "version": _version(), "starting_for_s": round(seconds, 1),
                    "detail": "loading the estimators and opening the database; other requests wait for it"}
            await _answer(send, 503, "application/json", json.dumps(body), retry_after=RELOAD_S)
            return
        page = (f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>learnest is starting</title>"
                f"<meta http-equiv='refresh' content='{RELOAD_S}'></head><body style='font-family:sans-serif'>"
                f"<h1>learnest is starting</h1><p>Loading the estimators and opening the database "
                f"({seconds:.0f} s so far; usually under 30 s). This page reloads itself.</p></body></html>")
        await _answer(send, 503, "text/html; charset=utf-8", page, retry_after=RELOAD_S)


def _answered_while_starting(scope) -> bool:
    path = scope["path"]
    return path in ("/health", "/") or path == "/manual" or path.startswith("/manual/")


def _build_manual_in_background() -> None:
    """Start building the manual (`learnest.service.web.manual`) now, not on its first visitor's request."""
    from ..config import Settings
    from ..web import manual

    manual.build_in_background(Settings().home)


async def _answer(send, status: int, content_type: str, body: str, retry_after: int | None = None) -> None:
    data = body.encode()
    headers = [(b"content-type", content_type.encode()), (b"content-length", str(len(data)).encode()),
               (b"cache-control", b"no-store")]
    if retry_after is not None:
        headers.append((b"retry-after", str(retry_after).encode()))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": data})


def _version() -> str:
    try:
        return importlib.metadata.version("learnest")
    except importlib.metadata.PackageNotFoundError:   # pragma: no cover - a checkout never installed
        return "unknown"


def create_app() -> StartingApp:
    """The factory `learnest serve` gives uvicorn (``learnest.service.app.starting:create_app``)."""
    return StartingApp()
