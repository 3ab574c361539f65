"""Errors: a 4xx a person can act on, never a traceback.  One handler per kind of exception: a request
that fails validation (422, naming each field), a `LearnestError` (the status it carries: `InvalidInput`
422, `NotFound` 404, `Conflict` 409), and anything else (500 with an incident id; the log has the rest)."""
from __future__ import annotations

import logging
import uuid

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from learnest.errors import LearnestError

from ..storage.database import database_full, storage_is_full

log = logging.getLogger("learnest.app")


def install_error_handlers(app: FastAPI) -> None:
    """Answer every exception a route raises as JSON ``{"detail": ...}`` with the right status."""
    @app.exception_handler(RequestValidationError)
    async def invalid_request(_request: Request, err: RequestValidationError):
        errors = [{"field": _field(e.get("loc", ())), "message": e.get("msg", "invalid")} for e in err.errors()]
        detail = "; ".join(f"{e['field']}: {e['message']}" if e["field"] else e["message"] for e in errors)
        return JSONResponse({"detail": detail, "errors": errors}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, err: StarletteHTTPException):
        if err.status_code == 400 and _part_header_too_long(err):
            # Starlette says only "Invalid multipart data."; the usual cause is a very long file name
            return JSONResponse({"detail": f"file name too long: a multipart part's header line (which holds the "
                                           f"file name) may have at most {MULTIPART_HEADER_BYTES} bytes, so file "
                                           f"names are limited to about {MULTIPART_HEADER_BYTES - 100} characters"},
                                status_code=400)
        return await http_exception_handler(request, err)

    @app.exception_handler(LearnestError)
    async def learnest_error(_request: Request, err: LearnestError):
        # an error may say when to come back (DecodeBusy: 503 with Retry-After)
        return JSONResponse({"detail": str(err)}, status_code=err.status, headers=getattr(err, "headers", None))

    @app.exception_handler(Exception)
    async def unexpected(request: Request, err: Exception):
        if storage_is_full(err):   # a full database met outside Database.transaction: 507 all the same
            full = database_full(err)
            return JSONResponse({"detail": str(full)}, status_code=full.status)
        incident = uuid.uuid4().hex[:12]
        log.error("incident %s on %s %s", incident, request.method, request.url.path, exc_info=err)
        # Connection: close - the server drops the connection after a 500; said, the client opens a new one
        # instead of sending its next request into a reset
        return JSONResponse({"detail": f"internal error (incident {incident}; the server log has the details)"},
                            status_code=500, headers={"Connection": "close"})


def _part_header_too_long(err: BaseException) -> bool:
    """True when the multipart parser refused a part's header line as too long (python-multipart's limit)."""
    cause: BaseException | None = err
    for _ in range(5):   # HTTPException <- MultiPartException <- MultipartParseError
        cause = cause.__cause__ or cause.__context__ if cause is not None else None
        if cause is not None and "Maximum header size exceeded" in str(cause):
            return True
    return False


def _multipart_header_bytes() -> int:
    try:
        from python_multipart.multipart import DEFAULT_MAX_HEADER_SIZE
        return int(DEFAULT_MAX_HEADER_SIZE)
    except ImportError:  # pragma: no cover - an older python-multipart
        return 4224


MULTIPART_HEADER_BYTES = _multipart_header_bytes()


def _field(loc) -> str:
    """("body", "epochs") -> "epochs"; ("query", "limit") -> "limit (query)"."""
    parts = [str(p) for p in loc]
    if parts and parts[0] == "body":
        return ".".join(parts[1:]) or "body"
    if len(parts) > 1 and parts[0] in ("query", "path", "header"):
        return f"{'.'.join(parts[1:])} ({parts[0]})"
    return ".".join(parts)
