"""Dependencies injected into the routes (FastAPI `Depends`): the services of the running app and the
API-key check for writes; and the lookup every job-backed resource (evaluations, diagnoses) shares."""
from __future__ import annotations

import hmac

from fastapi import Depends, Header, HTTPException, Request
from fastapi.responses import JSONResponse

from learnest.errors import Conflict, NotFound

from ..blobs import BlobStore
from ..config import Settings
from ..db import Database, Job
from ..jobs import Services


def get_services(request: Request) -> Services:
    return request.app.state.services


def get_db(services: Services = Depends(get_services)) -> Database:
    return services.db


def get_blobs(services: Services = Depends(get_services)) -> BlobStore:
    return services.blobs


def get_settings(services: Services = Depends(get_services)) -> Settings:
    return services.settings


def require_api_key(x_api_key: str | None = Header(None, description="required for writes when the server "
                                                                       "has LEARNEST_API_KEY set"),
                    settings: Settings = Depends(get_settings)) -> None:
    if settings.api_key is None:
        return
    if x_api_key is None or not hmac.compare_digest(x_api_key.encode(), settings.api_key.encode()):
        raise HTTPException(401, "missing or wrong API key: send it in the X-API-Key header",
                            headers={"WWW-Authenticate": "X-API-Key"})


def row_and_job(db: Database, table, row_id: int, what: str):
    """(row, its job) of a job-backed resource; 404 when there is no such row, 409 when its job failed."""
    with db.transaction() as session:
        row = session.get(table, row_id)
        if row is None:
            raise NotFound(f"{what} {row_id} not found")
        job = session.get(Job, row.job_id)
    if job.state == "failed":
        raise Conflict(f"{what} {row_id} failed: {job.error}")
    return row, job


def pending(what: str, row, job: Job) -> JSONResponse:
    """202: the resource exists but its job has not finished."""
    return JSONResponse({f"{what}_id": row.id, "job_id": job.id, "state": job.state, "progress": job.progress},
                        status_code=202)
