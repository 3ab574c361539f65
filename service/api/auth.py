"""Who a request is: its token (``Authorization: Bearer TOKEN`` or ``X-API-Key: TOKEN``) or its web session
(the ``learnest_session`` cookie), looked up in the registry on every request.

No cache of tokens or sessions: a token revoked through any server worker, or the command line, fails on the
very next request everywhere.  The one thing kept in memory is that tokens exist once one was seen: token rows
are never deleted, so that can only ever turn true (and while it is false, every request asks again).

A server with neither LEARNEST_API_KEY nor any token is open, as before tokens existed: every request is
`anonymous` with every right (`learnest serve` refuses such a server on a non-loopback address unless told
``--insecure``).
"""
from __future__ import annotations

from collections.abc import Callable
from contextvars import ContextVar
from dataclasses import dataclass

from starlette.datastructures import Headers
from starlette.types import Scope

from ..storage import tokens
from ..storage.database import Database
from ..storage.tokens import ANONYMOUS, Principal

SESSION_COOKIE = "learnest_session"   # HttpOnly, SameSite=Strict: the web sign-in's session id
KEY_HEADER = "x-api-key"
OPEN = Principal(ANONYMOUS, "admin", signed_in=False)      # everyone, on a server without tokens
PUBLIC_READER = Principal(ANONYMOUS, "read", signed_in=False)
# who the request being answered is, for the pages' header (set by the guard around the route; the routes
# themselves read ``request.state.principal``)
current_principal: ContextVar[Principal | None] = ContextVar("learnest_principal", default=None)


@dataclass(frozen=True)
class Identity:
    """What a request proved: ``principal`` (None: nothing valid), and whether it presented a token that
    failed (``failed``: counted by the throttle) or a session that is over (``stale_session``: the cookie is
    cleared)."""

    principal: Principal | None
    failed: bool = False
    stale_session: bool = False


def presented_token(headers: Headers) -> str | None:
    """The token of ``Authorization: Bearer TOKEN``, else of ``X-API-Key``; None without either."""
    authorization = headers.get("authorization", "")
    scheme, _, value = authorization.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    return headers.get(KEY_HEADER) or None


class Authenticator:
    """Tells who a request is (`identify`), with the registry's tokens and LEARNEST_API_KEY.

    Parameters
    ----------
    api_key : str, optional
        LEARNEST_API_KEY: an admin token kept outside the registry.
    public_reads : bool
        LEARNEST_PUBLIC_READS: a request without a token may read.
    database : callable
        ``database(scope)`` -> the registry's Database, or None where there is none (a bare ASGI app in a test).
    """

    def __init__(self, api_key: str | None, public_reads: bool,
                 database: Callable[[Scope], Database | None]) -> None:
        self.api_key, self.public_reads, self.database = api_key, public_reads, database
        self._tokens_seen = False

    def protected(self, db: Database | None) -> bool:
        """Whether requests need a token: LEARNEST_API_KEY is set or a token was ever made."""
        if self.api_key is not None or self._tokens_seen:
            return True
        self._tokens_seen = db is not None and tokens.tokens_exist(db)
        return self._tokens_seen

    def identify(self, scope: Scope, token: str | None, session_id: str | None) -> Identity:
        """Who the request is (blocking: it reads the database; run it off the event loop)."""
        db = self.database(scope)
        if not self.protected(db):
            return Identity(OPEN)
        if token is not None:
            principal = self._principal(db, tokens.hash_token(token))
            return Identity(principal, failed=principal is None)
        if session_id:
            token_hash = tokens.session_token_hash(db, session_id) if db is not None else None
            principal = self._principal(db, token_hash) if token_hash else None
            if principal is not None:
                return Identity(principal)
            return Identity(PUBLIC_READER if self.public_reads else None, stale_session=True)
        return Identity(PUBLIC_READER if self.public_reads else None)

    def _principal(self, db: Database | None, token_hash: str) -> Principal | None:
        if db is None:   # no registry: LEARNEST_API_KEY alone
            return tokens.principal_of_key(token_hash, self.api_key)
        return tokens.principal_of(db, token_hash, self.api_key)
