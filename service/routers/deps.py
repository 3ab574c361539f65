"""Dependencies injected into the routes (FastAPI `Depends`): the services of the running app and the
API-key check for writes."""
from __future__ import annotations

import hmac

from fastapi import Depends, Header, HTTPException, Request

from service.blobs import BlobStore
from service.db import Database, Settings
from service.jobs import Services


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
