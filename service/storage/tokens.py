"""API tokens of people, with scopes, and the web sessions signed in with them (`tables.ApiToken`, `WebSession`).

A token is ``lnst_`` + 32 random bytes (``secrets.token_urlsafe``), shown once when it is made; the registry keeps
only its SHA-256.  A keyed or slow hash buys nothing here: the token is random and long, so its hash cannot be
inverted or guessed, and SHA-256 lets a request find its row by the hash alone.  The found hash is compared with
`hmac.compare_digest` too, and the LEARNEST_API_KEY (an admin token outside the registry) is compared by hash in
constant time.

Scopes nest: read < write < admin.  Every look-up reads the database (no cache), so a token revoked by any
process fails at once on every server worker, and so do the web sessions signed in with it.
"""
from __future__ import annotations

import hashlib
import hmac
import re
import secrets
from dataclasses import dataclass
from datetime import timedelta

from sqlalchemy import delete, exists, select

from learnest.errors import Conflict, InvalidInput, NotFound

from . import audit
from .database import Database
from .tables import ApiToken, WebSession, utcnow

SCOPES = ("read", "write", "admin")
TOKEN_PREFIX = "lnst_"
API_KEY_NAME = "api-key"        # who LEARNEST_API_KEY is in the audit log and on the pages
ANONYMOUS = "anonymous"         # who acts on a server without tokens (or reads with LEARNEST_PUBLIC_READS)
NAME_PATTERN = re.compile(r"[A-Za-z][A-Za-z0-9._@-]{0,63}")


@dataclass(frozen=True)
class Principal:
    """Who a request is: a token's ``name`` and ``scope`` (``token_id`` None for the API key and anonymous)."""

    name: str
    scope: str
    token_id: int | None = None
    signed_in: bool = True   # False: nobody signed in (an open server, or public reads)

    def allows(self, needed: str) -> bool:
        """Whether this scope covers ``needed`` (read < write < admin)."""
        return SCOPES.index(self.scope) >= SCOPES.index(needed)


def hash_token(token: str) -> str:
    """SHA-256 (hex) of a token, as the registry keeps it."""
    return hashlib.sha256(token.encode("utf-8", "surrogatepass")).hexdigest()


def check_scope(scope: str) -> str:
    """``scope`` if it is read, write or admin; InvalidInput naming the three otherwise."""
    if scope not in SCOPES:
        raise InvalidInput(f"scope {scope!r}: one of {', '.join(SCOPES)}")
    return scope


def check_token_name(name: str) -> str:
    """A token's name (a person or a machine): a letter, then up to 63 letters, digits or ``. _ @ -``."""
    if not NAME_PATTERN.fullmatch(name or ""):
        raise InvalidInput(f"token name {name!r}: a letter, then at most 63 letters, digits or . _ @ - (e.g. "
                           "alice or ci-runner)")
    if name == API_KEY_NAME:
        raise InvalidInput(f"token name {name!r} is taken by LEARNEST_API_KEY: choose another")
    return name


# -- tokens --------------------------------------------------------------------------------------------
def create_token(db: Database, name: str, scope: str, actor: str | None = None) -> tuple[str, ApiToken]:
    """Make a token named ``name`` with ``scope``; -> (the token, shown once; its row).  Conflict when a token
    of that name is not revoked.  The audit log records who made it."""
    check_token_name(name)
    check_scope(scope)
    token = TOKEN_PREFIX + secrets.token_urlsafe(32)
    with db.transaction() as session:
        if session.scalar(select(exists().where(ApiToken.name == name, ApiToken.revoked_at.is_(None)))):
            raise Conflict(f"a token named {name!r} exists: revoke it first, or choose another name")
        row = ApiToken(name=name, scope=scope, token_hash=hash_token(token), created_at=utcnow(),
                       created_by=actor or audit.local_actor())
        session.add(row)
        session.flush()
        audit.record(session, actor, "token.create", f"token {name}", {"token_id": row.id, "scope": scope})
    return token, row


def list_tokens(db: Database) -> list[ApiToken]:
    """Every token made, revoked ones too, oldest first."""
    with db.reading() as session:
        return list(session.scalars(select(ApiToken).order_by(ApiToken.id)))


def revoke_token(db: Database, which: str | int, actor: str | None = None) -> ApiToken:
    """Revoke a token by id or by the name of a token not revoked; its web sessions end with it.  NotFound when
    there is none, Conflict when that id is revoked already."""
    with db.transaction() as session:
        if isinstance(which, int) or str(which).isdigit():
            row = session.get(ApiToken, int(which))
        else:
            row = session.scalar(select(ApiToken).where(ApiToken.name == which, ApiToken.revoked_at.is_(None)))
        if row is None:
            raise NotFound(f"no token {which!r} to revoke (see `learnest tokens list`)")
        if row.revoked_at is not None:
            raise Conflict(f"token {row.id} ({row.name}) was revoked at {row.revoked_at:%Y-%m-%d %H:%M:%S} UTC")
        row.revoked_at, row.revoked_by = utcnow(), actor or audit.local_actor()
        session.execute(delete(WebSession).where(WebSession.token_hash == row.token_hash))
        audit.record(session, actor, "token.revoke", f"token {row.name}", {"token_id": row.id, "scope": row.scope})
    return row


def tokens_exist(db: Database) -> bool:
    """Whether any token was ever made (revoked ones count: revoking the last token must not open the server)."""
    with db.reading() as session:
        return bool(session.scalar(select(exists().where(ApiToken.id.is_not(None)))))


def principal_of_key(token_hash: str, api_key: str | None) -> Principal | None:
    """The admin of LEARNEST_API_KEY when ``token_hash`` is its hash (compared in constant time), else None."""
    if api_key is not None and hmac.compare_digest(token_hash, hash_token(api_key)):
        return Principal(API_KEY_NAME, "admin")
    return None


def principal_of(db: Database, token_hash: str, api_key: str | None) -> Principal | None:
    """Who holds the token hashed to ``token_hash``: LEARNEST_API_KEY (admin) or a token not revoked; None
    for anything else."""
    key = principal_of_key(token_hash, api_key)
    if key is not None:
        return key
    with db.reading() as session:
        row = session.scalar(select(ApiToken).where(ApiToken.token_hash == token_hash))
    if row is None or row.revoked_at is not None or not hmac.compare_digest(row.token_hash, token_hash):
        return None
    return Principal(row.name, row.scope, row.id)


def token_dict(row: ApiToken) -> dict:
    """A token's row as JSON-ready values (never its hash)."""
    return {"id": row.id, "name": row.name, "scope": row.scope, "created_at": row.created_at.isoformat(),
            "created_by": row.created_by, "revoked_at": row.revoked_at.isoformat() if row.revoked_at else None,
            "revoked_by": row.revoked_by}


# -- web sessions --------------------------------------------------------------------------------------
def start_session(db: Database, token_hash: str, hours: float) -> str:
    """A new web session of the token hashed to ``token_hash``; -> the session id (for the cookie only)."""
    session_id = secrets.token_urlsafe(32)
    now = utcnow()
    with db.transaction() as session:
        session.execute(delete(WebSession).where(WebSession.expires_at < now))   # the expired ones go here
        session.add(WebSession(id_hash=hash_token(session_id), token_hash=token_hash, created_at=now,
                               expires_at=now + timedelta(hours=hours)))
    return session_id


def session_token_hash(db: Database, session_id: str) -> str | None:
    """The token hash of an unexpired web session, or None."""
    with db.reading() as session:
        row = session.get(WebSession, hash_token(session_id))
    if row is None or row.expires_at < utcnow():
        return None
    return row.token_hash


def end_session(db: Database, session_id: str) -> None:
    """Sign out: the session is gone (also when it never was)."""
    with db.transaction() as session:
        session.execute(delete(WebSession).where(WebSession.id_hash == hash_token(session_id)))
