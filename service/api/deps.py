"""Dependencies injected into the routes and pages (FastAPI `Depends`): the services of the running app, who
the request is (the request guard found out, service.api.request_guard); and the 202 answer every job-backed
resource (evaluations, diagnoses) shares."""
from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Path, Query, Request, Security
from fastapi.responses import JSONResponse
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from ..config import Settings
from ..jobs.services import Services
from ..storage.blobs import BlobStore
from ..storage.database import Database
from ..storage.tables import Job
from ..storage.tokens import ANONYMOUS, Principal
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


def principal(request: Request) -> Principal | None:
    """Who the request is (None where the guard needed nobody: public routes)."""
    return getattr(request.state, "principal", None)


def creator(request: Request) -> str | None:
    """The name a row made by this request records as its maker: the token's (None without one)."""
    who = principal(request)
    return who.name if who is not None and who.signed_in else None


def actor(request: Request) -> str:
    """Who the audit log names for this request's change: the token's name, or anonymous."""
    who = principal(request)
    return who.name if who is not None else ANONYMOUS


# Only for the OpenAPI page: both ways of sending a token, so /docs offers them ("Authorize").  The request
# guard has checked the token before any route runs.
_bearer = HTTPBearer(auto_error=False, description="a learnest token: `learnest tokens create NAME --scope ...`")
_key_header = APIKeyHeader(name="X-API-Key", auto_error=False, description="the same token, in this header")


def documented_token(bearer: HTTPAuthorizationCredentials | None = Security(_bearer),
                     key: str | None = Security(_key_header)) -> None:
    """Declares the token schemes in the OpenAPI schema; checks nothing (the guard does)."""


def pending(what: str, row, job: Job) -> JSONResponse:
    """202: the resource exists but its job has not finished."""
    return JSONResponse({f"{what}_id": row.id, "job_id": job.id, "state": job.state, "progress": job.progress},
                        status_code=202)
