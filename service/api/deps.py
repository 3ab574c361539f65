"""Dependencies injected into the routes and pages (FastAPI `Depends`): the services of the running app and
the API-key check for writes; and the 202 answer every job-backed resource (evaluations, diagnoses) shares."""
from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Header, HTTPException, Path, Query, Request
from fastapi.responses import JSONResponse

from ..config import Settings
from ..jobs.services import Services
from ..storage.blobs import BlobStore
from ..storage.database import Database
from ..storage.tables import Job
from .schemas import MAX_ROW_ID

# Ids and offsets are SQL BIGINTs: a larger number names nothing, and SQLite raises OverflowError on it (a
# 500).  The rule is the request bodies' (schemas.MAX_ROW_ID): checked at the boundary, a 422 that says the range.
RowId = Annotated[int, Path(ge=1, le=MAX_ROW_ID)]
Offset = Annotated[int, Query(ge=0, le=MAX_ROW_ID)]


def get_services(request: Request) -> Services:
    """The Services the app opened at startup (``app.state.services``)."""
    return request.app.state.services


def get_db(services: Services = Depends(get_services)) -> Database:
    """The app's database."""
    return services.db


def get_blobs(services: Services = Depends(get_services)) -> BlobStore:
    """The app's blob store."""
    return services.blobs


def get_settings(services: Services = Depends(get_services)) -> Settings:
    """The app's settings."""
    return services.settings


def require_api_key(x_api_key: str | None = Header(None, description="required for writes when the server "
                                                                       "has LEARNEST_API_KEY set"),
                    settings: Settings = Depends(get_settings)) -> None:
    """Let a write through when the server needs no API key or X-API-Key holds it; otherwise 401."""
    if not key_matches(settings, x_api_key):
        raise HTTPException(401, "missing or wrong API key: send it in the X-API-Key header",
                            headers={"WWW-Authenticate": "X-API-Key"})


def key_matches(settings: Settings, key: str | None) -> bool:
    """True when the server needs no API key, or `key` is it (compared in constant time)."""
    if settings.api_key is None:
        return True
    return bool(key) and hmac.compare_digest(str(key).encode(), settings.api_key.encode())


def pending(what: str, row, job: Job) -> JSONResponse:
    """202: the resource exists but its job has not finished."""
    return JSONResponse({f"{what}_id": row.id, "job_id": job.id, "state": job.state, "progress": job.progress},
                        status_code=202)
