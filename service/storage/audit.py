"""The audit log: deletions and access changes, who made them and when (`tables.AuditEntry`).

An entry is written in the transaction of the change it records, so the change and its entry commit together
or not at all.  Entries name what they record in text (no foreign key): deleting a flight, a version or a
token never removes the entries about it, and nothing in the service deletes entries.
"""
from __future__ import annotations

import getpass

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from .database import Database
from .tables import AuditEntry, utcnow

MAX_TARGET = 300


def local_actor() -> str:
    """Who acts when no token does: the command line on the server's machine, as ``local:USER``."""
    try:
        user = getpass.getuser()
    except (KeyError, OSError):   # no name for this uid (a container)
        user = "unknown"
    return f"local:{user}"


def record(session: Session, actor: str | None, action: str, target: str, detail: dict | None = None) -> AuditEntry:
    """Append an entry in ``session``'s transaction.  ``actor`` None: `local_actor`."""
    entry = AuditEntry(at=utcnow(), actor=actor or local_actor(), action=action, target=target[:MAX_TARGET],
                       detail=detail)
    session.add(entry)
    return entry


def list_entries(db: Database, limit: int = 100, offset: int = 0) -> tuple[int, list[AuditEntry]]:
    """(how many entries there are, ``limit`` of them from ``offset``), newest first."""
    with db.reading() as session:
        total = session.scalar(select(func.count()).select_from(AuditEntry)) or 0
        rows = list(session.scalars(select(AuditEntry).order_by(AuditEntry.id.desc()).limit(limit).offset(offset)))
    return total, rows


def entry_dict(entry: AuditEntry) -> dict:
    """An entry as JSON-ready values (the API's and `learnest audit --json`'s)."""
    return {"id": entry.id, "at": entry.at.isoformat(), "actor": entry.actor, "action": entry.action,
            "target": entry.target, "detail": entry.detail}
