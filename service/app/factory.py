"""The learnest HTTP service (FastAPI).  `create_app()` is the factory uvicorn runs
(`learnest serve`, or `uvicorn --factory learnest.service.app.factory:create_app`); OpenAPI docs at /docs.
It puts together the JSON routes (service.api) and the web pages (service.web), which know nothing of each
other's assembly.

Start-up: Alembic `upgrade head`, blob folder, executor (local process pool or Dask), job runner (fails the
jobs a crashed server left running), scheduler when LEARNEST_SCHEDULE_SECONDS > 0.
"""
from __future__ import annotations

import importlib.metadata
from contextlib import asynccontextmanager

from fastapi import Depends, FastAPI, HTTPException, Request
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from ..api.deps import documented_token
from ..api.docs import install_docs
from ..api.errors import install_error_handlers
from ..api.request_guard import RequestGuard
from ..api.routes import diagnoses, evaluations, flights, jobs, models, tokens
from ..api.server import FORM_FIELD_BYTES, FORM_FIELDS, BodyDeadline
from ..api.throttle import KeyThrottle
from ..config import Settings
from ..jobs.decoding import DecodePool
from ..jobs.executors import Executor
from ..jobs.scheduler import Scheduler
from ..jobs.services import open_services, sweep_orphan_blobs
from ..web import access_pages, manual, pages, registry_pages


def create_app(settings: Settings | None = None, *, executor: Executor | None = None,
               decoder: DecodePool | None = None, scheduler: bool = True) -> FastAPI:
    """`executor`, `decoder`: an already running executor / upload decoder pool to share (not shut down with
    the app); None: make them from the settings.  `scheduler=False` never starts the scheduler thread (tests
    drive `Scheduler.tick`)."""
    settings = settings or Settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        services = open_services(settings, executor, decoder)
        sweep_orphan_blobs(services.db, services.blobs)  # the server's start, not every CLI call's
        services.decoder.start()
        app.state.services = services
        app.state.scheduler = None
        if scheduler and settings.schedule_seconds > 0:
            app.state.scheduler = Scheduler(services, settings.schedule_seconds, settings.schedule_alias)
            app.state.scheduler.start()
        try:
            yield
        finally:
            if app.state.scheduler is not None:
                app.state.scheduler.stop()
            services.close()

    app = FastAPI(title="learnest", version=_version(), lifespan=lifespan, docs_url=None, redoc_url=None,
                  form_limits={"max_fields": FORM_FIELDS, "max_part_size": FORM_FIELD_BYTES},
                  description="Upload Crazyflie flight logs, train KNODE models into a registry, and batch-"
                              "evaluate KNODE-UKF / KNODE-MHE against Savitzky-Golay references. Once the "
                              "server has LEARNEST_API_KEY or any token (`learnest tokens create`), every route "
                              "but /health needs a token, as `Authorization: Bearer TOKEN` or `X-API-Key: "
                              "TOKEN`: read for GET, write for uploads, training, evaluation and diagnosis, "
                              "admin for deletes, tokens and the audit log.")
    app.add_middleware(BodySizeLimit, max_bytes=settings.max_upload_bytes)
    app.add_middleware(BodyDeadline, timeout_s=settings.body_timeout_s, min_rate=settings.body_min_rate,
                       max_s=settings.body_max_s)
    # failed tokens per client network: the guard and the sign-in page count into the same throttle
    app.state.key_throttle = KeyThrottle(settings.key_failures, settings.key_failure_window_s)
    # outermost: runs first (host, cross-site and token checks before any body is read; scopes: api.access)
    app.add_middleware(RequestGuard, allowed_hosts=settings.allowed_host_names, api_key=settings.api_key,
                       throttle=app.state.key_throttle, public_reads=settings.public_reads)
    app.add_middleware(SecurityHeaders)   # on every answer, the guard's refusals too
    install_error_handlers(app)
    for router in (flights.router, models.router, models.compare_router, jobs.router, evaluations.router,
                   diagnoses.router, tokens.router):
        app.include_router(router, dependencies=[Depends(documented_token)])
    app.include_router(pages.router)  # the HTML pages for people (/, /ui/..., report.html): service/web/
    app.include_router(registry_pages.router)  # evaluations list, version pages, compare, delete pages
    app.include_router(access_pages.router)  # sign in, sign out, the admin page (tokens, audit log)
    app.include_router(manual.router)  # the user manual (docs/, built with MkDocs) at /manual
    # follow_symlink: a strict editable install (the development setup) links these files into its package
    # folder; a wheel has no links, so this changes nothing there
    app.mount("/static", StaticFiles(packages=[("learnest.service.web", "static")], follow_symlink=True),
              name="static")
    install_docs(app)  # /docs and /redoc with packaged assets (no CDN)

    # async: answered on the event loop, never queued behind uploads and pages in the worker threads
    @app.get("/health", tags=["service"])
    async def health(request: Request) -> dict:
        services = request.app.state.services
        return {"status": "ok", "version": _version(), "executor": services.executor.describe(),
                "database": services.db.engine.dialect.name}

    return app


def _version() -> str:
    try:
        return importlib.metadata.version("learnest")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


# -- upload size limit ----------------------------------------------------------------------------------
class BodySizeLimit:
    """413 for a request body above max_bytes: at once from Content-Length, else while it streams in
    (chunked uploads), before the multipart parser writes it anywhere."""

    def __init__(self, app, max_bytes: int):
        self.app, self.max_bytes = app, max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or []).get(b"content-length", b"")
        if declared.isdigit() and int(declared) > self.max_bytes:
            return await self._reject(receive, send)
        received = 0

        async def limited_receive():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    raise HTTPException(413, self._message())  # FastAPI passes HTTPExceptions through
            return message

        await self.app(scope, limited_receive, send)

    def _message(self) -> str:
        return f"upload too large: the limit is {self.max_bytes / 2**20:g} MB (LEARNEST_MAX_UPLOAD_MB)"

    async def _reject(self, receive: Receive, send: Send) -> None:
        response = JSONResponse({"detail": self._message()}, status_code=413, headers={"Connection": "close"})
        await response({"type": "http"}, receive, send)


# -- security headers -----------------------------------------------------------------------------------
SECURITY_HEADERS = [(b"x-frame-options", b"DENY"), (b"content-security-policy", b"frame-ancestors 'none'"),
                    (b"x-content-type-options", b"nosniff")]


class SecurityHeaders:
    """ASGI middleware: every answer says it may not be framed (X-Frame-Options, CSP frame-ancestors) and that
    its type is the one declared (X-Content-Type-Options).  Why: a page of another site could otherwise frame a
    delete confirmation and have the user click its button, which posts from this server's own origin (the
    cross-site check cannot see it).  No page of ours is framed, so none is refused anything it needs."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                present = {name.lower() for name, _ in message.get("headers", [])}
                extra = [(name, value) for name, value in SECURITY_HEADERS if name not in present]
                message = {**message, "headers": [*message.get("headers", []), *extra]}
            await send(message)

        await self.app(scope, receive, send_with_headers)
