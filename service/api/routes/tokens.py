"""/tokens, /audit and /whoami: people's API tokens (admin), the audit log (admin), and who a token is.

The scope of each route is in service.api.access; the request guard checked it before these run.
"""
from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from fastapi import APIRouter, Depends, Query, Request
from pydantic import BaseModel, Field

from ...storage import audit, tokens
from ...storage.database import Database
from ..deps import RowId, actor, get_db, principal
from ..schemas import Strict

router = APIRouter(tags=["access"])


class TokenIn(Strict):
    name: str = Field(max_length=64, description="who holds it: a letter, then letters, digits or . _ @ -")
    scope: Literal["read", "write", "admin"] = Field(description="read: every GET; write: also uploads, "
                                                                 "training, evaluation, diagnosis, aliases, "
                                                                 "cancelling; admin: also deletes and tokens")


class TokenOut(BaseModel):
    id: int
    name: str
    scope: str
    created_at: datetime
    created_by: str | None
    revoked_at: datetime | None
    revoked_by: str | None


class TokenCreated(TokenOut):
    token: str = Field(description="the token itself: shown this once, only its SHA-256 is kept")


class AuditOut(BaseModel):
    id: int
    at: datetime
    actor: str = Field(description="the token's name (api-key: LEARNEST_API_KEY; local:USER: the command line)")
    action: str = Field(description="flight.delete, version.delete, evaluation.delete, alias.set, alias.delete, "
                                    "token.create, token.revoke")
    target: str
    detail: dict[str, Any] | None


class AuditPage(BaseModel):
    items: list[AuditOut]
    total: int


class WhoAmI(BaseModel):
    name: str = Field(description="the token's name, or anonymous (no token: an open server, or public reads)")
    scope: str
    signed_in: bool


@router.get("/tokens", response_model=list[TokenOut])
def list_tokens(db: Database = Depends(get_db)):
    """Every token made, revoked ones too (never the tokens themselves)."""
    return [tokens.token_dict(row) for row in tokens.list_tokens(db)]


@router.post("/tokens", status_code=201, response_model=TokenCreated,
             responses={409: {"description": "a token of that name is not revoked"}})
def create_token(body: TokenIn, request: Request, db: Database = Depends(get_db)):
    """Make a token for a person or a machine; the answer holds the token, which is never shown again."""
    token, row = tokens.create_token(db, body.name, body.scope, actor=actor(request))
    return {**tokens.token_dict(row), "token": token}


@router.delete("/tokens/{token_id}", response_model=TokenOut,
               responses={404: {"description": "no such token"}, 409: {"description": "revoked already"}})
def revoke_token(token_id: RowId, request: Request, db: Database = Depends(get_db)):
    """Revoke a token: it fails from the next request on, on every worker, and its web sessions end.  Its row
    stays (the audit log names it)."""
    return tokens.token_dict(tokens.revoke_token(db, token_id, actor=actor(request)))


@router.get("/audit", response_model=AuditPage)
def audit_log(limit: int = Query(100, ge=1, le=1000), offset: int = Query(0, ge=0, le=2**62),
              db: Database = Depends(get_db)):
    """Deletions, alias moves and token changes, newest first: who (the token's name), what, when."""
    total, rows = audit.list_entries(db, limit, offset)
    return {"items": [audit.entry_dict(row) for row in rows], "total": total}


@router.get("/whoami", response_model=WhoAmI)
def whoami(request: Request):
    """The token this request carries: its name and scope."""
    who = principal(request)
    if who is None:
        return {"name": tokens.ANONYMOUS, "scope": "admin", "signed_in": False}
    return {"name": who.name, "scope": who.scope, "signed_in": who.signed_in}
