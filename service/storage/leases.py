"""Leases: named database locks with an expiry, behind "exactly one scheduler" and job ownership.

A lease is a row (name, owner, expires_at) taken or renewed with one conditional UPDATE, so it behaves the
same on SQLite and PostgreSQL and across machines; whoever holds an unexpired lease owns what it names.
"""
from __future__ import annotations

import time

from sqlalchemy import delete, select, update
from sqlalchemy.exc import IntegrityError

from .database import Database, dml_rowcount
from .tables import Lease


def acquire_lease(db: Database, name: str, owner: str, ttl_s: float) -> bool:
    """Take or renew the lease `name` for `owner` for ttl_s seconds; False if someone else holds it."""
    now = time.time()
    with db.transaction() as session:
        taken = dml_rowcount(session.execute(
            update(Lease).where(Lease.name == name, (Lease.owner == owner) | (Lease.expires_at < now))
            .values(owner=owner, expires_at=now + ttl_s)))
        if taken:
            return True
    try:
        with db.transaction() as session:
            session.add(Lease(name=name, owner=owner, expires_at=now + ttl_s))
        return True
    except IntegrityError:  # it exists and is held by someone else
        return False


def release_lease(db: Database, name: str, owner: str) -> None:
    """Drop lease ``name`` if ``owner`` holds it."""
    with db.transaction() as session:
        session.execute(delete(Lease).where(Lease.name == name, Lease.owner == owner),
                        execution_options={"synchronize_session": False})


def lease_holder(db: Database, name: str) -> str | None:
    """The owner of lease ``name`` if it has not expired, else None."""
    with db.transaction() as session:
        lease = session.scalar(select(Lease).where(Lease.name == name))
        return lease.owner if lease is not None and lease.expires_at >= time.time() else None
