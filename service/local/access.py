"""Tokens and the audit log from the command line (`learnest tokens`, `learnest audit`), on the registry the
server uses (LEARNEST_HOME or LEARNEST_DATABASE_URL): what the /tokens and /audit routes do, as the person at
the server's machine (the audit log names them ``local:USER``)."""
from __future__ import annotations

from sqlalchemy import inspect

from ..config import Settings
from ..storage import audit, tokens
from ..storage.database import Database
from .services import cli_settings, registry_database

NOTHING_YET = "no token has been made under {home} (LEARNEST_HOME) yet: `learnest tokens create NAME --scope admin`"


def create_token(name: str, scope: str, settings: Settings | None = None) -> tuple[str, dict]:
    """Make a token (the registry is created and migrated first if need be: this is how a server is set up);
    -> (the token, shown once; its row as JSON)."""
    database = Database((settings or cli_settings()).url)
    try:
        database.migrate()
        token, row = tokens.create_token(database, name, scope)
    finally:
        database.dispose()
    return token, tokens.token_dict(row)


def list_tokens(settings: Settings | None = None) -> list[dict]:
    """Every token made, revoked ones too, as JSON (never the tokens)."""
    settings = settings or cli_settings()
    with registry_database(settings, NOTHING_YET.format(home=settings.home)) as db:
        return [tokens.token_dict(row) for row in tokens.list_tokens(db)]


def revoke_token(which: str, settings: Settings | None = None) -> dict:
    """Revoke the token of that id, or the unrevoked token of that name; its row as JSON."""
    settings = settings or cli_settings()
    with registry_database(settings, NOTHING_YET.format(home=settings.home)) as db:
        return tokens.token_dict(tokens.revoke_token(db, which))


def audit_entries(limit: int, settings: Settings | None = None) -> dict:
    """{"items": the newest ``limit`` entries as JSON, "total"}."""
    settings = settings or cli_settings()
    with registry_database(settings, f"nothing is stored under {settings.home} (LEARNEST_HOME) yet") as db:
        total, rows = audit.list_entries(db, limit)
    return {"total": total, "items": [audit.entry_dict(row) for row in rows]}


def any_access_token(settings: Settings) -> bool:
    """Whether the registry holds a token (revoked ones too); False when there is no registry yet, or one of a
    schema from before tokens.  Reads only: never creates or migrates anything."""
    if settings.database_url is None and not (settings.home / "learnest.db").is_file():
        return False
    database = Database(settings.url)
    try:
        if not inspect(database.engine).has_table("api_tokens"):
            return False
        return tokens.tokens_exist(database)
    finally:
        database.dispose()
