"""Storage: settings, SQLAlchemy tables, the Database handle (engine + short transactions + migrations)
and leases (the DB-level locks behind "exactly one scheduler" and job ownership).

SQLite (a file under LEARNEST_HOME) is the default; PostgreSQL when LEARNEST_DATABASE_URL is given.
Tables are created only by the Alembic migrations in service/migrations (the app runs `upgrade head`).
"""
from __future__ import annotations

import fcntl
import json
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypeVar, cast

from alembic.config import Config
from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    CursorResult,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    String,
    Text,
    UniqueConstraint,
    create_engine,
    delete,
    event,
    exists,
    or_,
    select,
    text,
    update,
)
from sqlalchemy.engine import Connection
from sqlalchemy.engine import Result as QueryResult
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, relationship, sessionmaker

from learnest.errors import Conflict, NotFound
from learnest.ingest.flight import json_compatible

MIGRATIONS = Path(__file__).resolve().parent / "migrations"


def utcnow() -> datetime:
    """Naive UTC: SQLite drops time zones, so every timestamp is stored as UTC without one."""
    return datetime.now(UTC).replace(tzinfo=None)


def _json_dumps(value) -> str:
    return json.dumps(json_compatible(value))


# -- tables -------------------------------------------------------------------------------------------
class Base(DeclarativeBase):
    """Declarative base of the service's tables (Alembic migrations create them)."""


class FlightRecord(Base):
    """A stored flight (the row, not the data: ``flight_blob`` holds `learnest.Flight.to_bytes`).

    ``sha256`` of the raw file(s) deduplicates uploads; ``name`` is unique; ``duration_s`` in s,
    ``rate_hz`` in Hz, ``clock_offset_s`` in s; ``quality`` is {"ok", "issues"}.
    """

    __tablename__ = "flights"
    __table_args__ = {"sqlite_autoincrement": True}  # an id is never handed out twice (see 0003)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    sha256: Mapped[str] = mapped_column(String(64), unique=True)   # of the raw file(s): the dedupe key
    name: Mapped[str] = mapped_column(String(200), unique=True)    # unique: evaluate_flights matches by name
    adapter: Mapped[str] = mapped_column(String(40))
    vehicle: Mapped[str | None] = mapped_column(String(200), index=True)
    notes: Mapped[str | None] = mapped_column(Text)
    duration_s: Mapped[float] = mapped_column(Float)
    rate_hz: Mapped[float] = mapped_column(Float)
    samples: Mapped[int] = mapped_column(Integer)
    quality_ok: Mapped[bool] = mapped_column(Boolean, index=True)
    quality: Mapped[dict] = mapped_column(JSON)
    clock_offset_s: Mapped[float | None] = mapped_column(Float)
    flight_blob: Mapped[str] = mapped_column(String(64))          # Flight.to_bytes of the normalized flight
    meta: Mapped[dict] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(DateTime, index=True, default=utcnow)
    files: Mapped[list[FlightFile]] = relationship(order_by="FlightFile.position", cascade="all, delete-orphan",
                                                     lazy="selectin")


class FlightFile(Base):
    """One uploaded raw file; the client's file name is metadata only, never a path."""

    __tablename__ = "flight_files"

    flight_id: Mapped[int] = mapped_column(ForeignKey("flights.id", ondelete="CASCADE"), primary_key=True)
    position: Mapped[int] = mapped_column(Integer, primary_key=True)
    original_name: Mapped[str] = mapped_column(String(255))
    sha256: Mapped[str] = mapped_column(String(64), index=True)   # its blob
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    role: Mapped[str] = mapped_column(String(20))                 # "log" or "sidecar" (NanoBench metadata)


class RegisteredModel(Base):
    """A registered model name; its versions are `ModelVersion` rows."""

    __tablename__ = "registered_models"

    name: Mapped[str] = mapped_column(String(100), primary_key=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class ModelVersion(Base):
    """Immutable once "ready"; "training" and "failed" rows hold the reserved number and the reason."""

    __tablename__ = "model_versions"
    __table_args__ = (UniqueConstraint("name", "version", name="uq_model_versions_name_version"),
                      {"sqlite_autoincrement": True})

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(ForeignKey("registered_models.name"), index=True)
    version: Mapped[int] = mapped_column(Integer)
    status: Mapped[str] = mapped_column(String(20), default="training")
    job_id: Mapped[int | None] = mapped_column(Integer)
    # no foreign key: the lineage must survive the deletion of the training flight
    training_flight_id: Mapped[int | None] = mapped_column(Integer)
    training_flight_sha256: Mapped[str | None] = mapped_column(String(64))
    training_flight_name: Mapped[str | None] = mapped_column(String(200))
    parent: Mapped[str | None] = mapped_column(String(120))
    hyperparameters: Mapped[dict] = mapped_column(JSON)
    prior: Mapped[dict | None] = mapped_column(JSON)
    losses: Mapped[list | None] = mapped_column(JSON)
    training_seconds: Mapped[float | None] = mapped_column(Float)
    metrics: Mapped[dict | None] = mapped_column(JSON)
    code_version: Mapped[dict | None] = mapped_column(JSON)
    library_versions: Mapped[dict | None] = mapped_column(JSON)
    weights_blob: Mapped[str | None] = mapped_column(String(64))
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    ready_at: Mapped[datetime | None] = mapped_column(DateTime)


class ModelAlias(Base):
    """A movable alias (``production``, ...) of a model, pointing at one version number."""

    __tablename__ = "model_aliases"

    name: Mapped[str] = mapped_column(ForeignKey("registered_models.name"), primary_key=True)
    alias: Mapped[str] = mapped_column(String(100), primary_key=True)
    version: Mapped[int] = mapped_column(Integer)
    updated_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Job(Base):
    """A background job: ``kind`` training/evaluation/diagnosis, ``state`` queued -> running -> succeeded |
    failed, ``progress`` 0..1, ``owner`` the server process running it."""

    __tablename__ = "jobs"
    __table_args__ = {"sqlite_autoincrement": True}  # an id is never handed out twice (see 0003)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    kind: Mapped[str] = mapped_column(String(20))
    state: Mapped[str] = mapped_column(String(20), index=True, default="queued")
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    error: Mapped[str | None] = mapped_column(Text)
    result: Mapped[dict | None] = mapped_column(JSON)
    payload: Mapped[dict | None] = mapped_column(JSON)
    owner: Mapped[str | None] = mapped_column(String(200))       # the server process running it (leases)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(DateTime)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime)


class Evaluation(Base):
    """An evaluation of one model version on stored flights; ``report`` has `evaluate_flights`' shape."""

    __tablename__ = "evaluations"
    __table_args__ = {"sqlite_autoincrement": True}  # an id is never handed out twice (see 0003)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id"))
    model_ref: Mapped[str] = mapped_column(String(220))
    model_version_id: Mapped[int] = mapped_column(ForeignKey("model_versions.id"))
    flight_ids: Mapped[list] = mapped_column(JSON)
    settings: Mapped[dict] = mapped_column(JSON)
    report: Mapped[dict | None] = mapped_column(JSON)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Diagnosis(Base):
    """A `learnest diagnose` run as a job: its report and, when asked for, the version it registered."""

    __tablename__ = "diagnoses"
    __table_args__ = {"sqlite_autoincrement": True}  # an id is never handed out twice (see 0003)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[int] = mapped_column(ForeignKey("jobs.id"))
    flight_ids: Mapped[list] = mapped_column(JSON)               # the first is the fitting flight
    model_ref: Mapped[str | None] = mapped_column(String(220))   # "name:version" analysed (None: trained here)
    register_as: Mapped[str | None] = mapped_column(String(100))
    settings: Mapped[dict] = mapped_column(JSON)                 # methods, epochs
    report: Mapped[dict | None] = mapped_column(JSON)
    registered: Mapped[dict | None] = mapped_column(JSON)        # {"name", "version", "parent"}
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Result(Base):
    """Per-flight evaluation cache: one row per (flight content, model version, estimator settings)."""

    __tablename__ = "results"
    __table_args__ = (UniqueConstraint("flight_sha256", "model_version_id", "settings_key",
                                       name="uq_results_flight_model_settings"), {"sqlite_autoincrement": True})

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    flight_sha256: Mapped[str] = mapped_column(String(64))
    model_version_id: Mapped[int] = mapped_column(ForeignKey("model_versions.id"), index=True)
    settings_key: Mapped[str] = mapped_column(String(64))
    flight_id: Mapped[int | None] = mapped_column(Integer)
    state: Mapped[str] = mapped_column(String(20))               # "succeeded" | "failed"
    entry: Mapped[dict] = mapped_column(JSON)                    # the flight's entry of the report
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Lease(Base):
    """A named lock with an expiry: whoever holds an unexpired lease owns the thing it names."""

    __tablename__ = "leases"

    name: Mapped[str] = mapped_column(String(200), primary_key=True)
    owner: Mapped[str] = mapped_column(String(200))
    expires_at: Mapped[float] = mapped_column(Float)              # unix time


# -- which blobs the rows name ------------------------------------------------------------------------
def referenced_blobs(db: Database) -> set[str]:
    """Every blob sha a row names: normalized flights, their raw files, model weights."""
    with db.transaction() as session:
        return {sha for column in (FlightRecord.flight_blob, FlightFile.sha256, ModelVersion.weights_blob)
                for sha in session.scalars(select(column).where(column.is_not(None))) if sha is not None}


def blob_is_referenced(db: Database, sha: str) -> bool:
    """Whether a flight, a raw file or a model version names blob ``sha``."""
    with db.transaction() as session:
        return bool(session.scalar(select(or_(exists().where(FlightRecord.flight_blob == sha),
                                              exists().where(FlightFile.sha256 == sha),
                                              exists().where(ModelVersion.weights_blob == sha)))))


# -- the database handle ------------------------------------------------------------------------------
class Database:
    """Engine + session factory.  Use `with db.transaction() as session:` for short units of work: on
    SQLite every transaction takes the write lock up front (BEGIN IMMEDIATE), so holding one while doing
    slow work would block every other writer."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.is_sqlite = url.startswith("sqlite")
        if self.is_sqlite:
            self._prepare_sqlite_file()
            self.engine = create_engine(url, connect_args={"timeout": 60, "check_same_thread": False},
                                        json_serializer=_json_dumps)
            _sqlite_pragmas(self.engine)
        else:
            self.engine = create_engine(url, pool_pre_ping=True, json_serializer=_json_dumps)
        self._sessions = sessionmaker(self.engine, expire_on_commit=False)

    def _prepare_sqlite_file(self) -> None:
        path = self.sqlite_path
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)

    @property
    def sqlite_path(self) -> Path | None:
        """The SQLite file of a ``sqlite:///`` URL; None for in-memory SQLite and other databases."""
        prefix = "sqlite:///"
        if not self.url.startswith(prefix) or self.url == prefix or ":memory:" in self.url:
            return None
        return Path(self.url[len(prefix):].split("?", 1)[0])

    def session(self) -> Session:
        """A new session (the caller commits and closes it); prefer `transaction`."""
        return self._sessions()

    @contextmanager
    def transaction(self) -> Iterator[Session]:
        """A session in a transaction: committed on exit, rolled back on an exception."""
        with self._sessions.begin() as session:
            yield session

    def migrate(self) -> None:
        """Alembic `upgrade head`, serialized across processes (several uvicorn workers start at once)."""
        from alembic import command

        config = Config()
        config.set_main_option("script_location", str(MIGRATIONS))
        with self._migration_lock(), self.engine.connect() as connection:
            if self.is_sqlite:
                # A migration may rebuild a table (SQLite cannot ALTER it): with foreign keys enforced,
                # dropping the old copy would cascade-delete the rows that point at it.  The pragma only
                # takes effect outside a transaction, so it is set on the driver's connection first.
                _driver_connection(connection).execute("PRAGMA foreign_keys=OFF")
            try:
                with connection.begin():
                    if not self.is_sqlite:  # PostgreSQL: held until this transaction ends
                        connection.execute(text("SELECT pg_advisory_xact_lock(7261034)"))
                    config.attributes["connection"] = connection
                    command.upgrade(config, "head")
                    if self.is_sqlite and connection.exec_driver_sql("PRAGMA foreign_key_check").first():
                        raise RuntimeError("migration left rows whose foreign keys point nowhere")
            finally:
                if self.is_sqlite:
                    _driver_connection(connection).execute("PRAGMA foreign_keys=ON")

    def require_current_schema(self) -> None:
        """Raise `Conflict` unless the schema is at the newest migration; reads never migrate.

        Migrating is a write that belongs to whoever runs the service (`learnest serve` does it at start);
        a read (loading a model for `learnest evaluate`) against an older schema says so instead.
        """
        from alembic.migration import MigrationContext
        from alembic.script import ScriptDirectory

        config = Config()
        config.set_main_option("script_location", str(MIGRATIONS))
        head = ScriptDirectory.from_config(config).get_current_head()
        with self.engine.connect() as connection:
            current = MigrationContext.configure(connection).get_current_revision()
        if current != head:
            raise Conflict(f"the database is at schema revision {current or 'none'} and this learnest needs {head}: "
                           "start `learnest serve` once (it migrates) or run `alembic upgrade head`")

    @contextmanager
    def _migration_lock(self):
        path = self.sqlite_path
        if path is None:
            yield
            return
        with open(path.with_name(path.name + ".migrate.lock"), "a") as handle:
            fcntl.flock(handle, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(handle, fcntl.LOCK_UN)

    def dispose(self) -> None:
        """Close the engine's pooled connections."""
        self.engine.dispose()


def _driver_connection(connection: Connection) -> Any:
    """The DBAPI driver's own connection under ``connection`` (sqlite3's, for the pragmas)."""
    driver = connection.connection.driver_connection
    if driver is None:  # only None once the pooled connection was invalidated
        raise RuntimeError("the database connection was closed during the migration")
    return driver


def _sqlite_pragmas(engine) -> None:
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection, _record):
        dbapi_connection.isolation_level = None  # let SQLAlchemy's BEGIN below be the only one
        cursor = dbapi_connection.cursor()
        cursor.execute("PRAGMA journal_mode=WAL")      # readers never block the writer
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute("PRAGMA synchronous=FULL")      # a committed row survives a power cut
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(connection):
        # IMMEDIATE: take the write lock now (waiting up to the busy timeout) instead of failing with
        # "database is locked" when a read transaction later tries to write
        connection.exec_driver_sql("BEGIN IMMEDIATE")


# -- typed helpers ----------------------------------------------------------------------------------------
RowT = TypeVar("RowT", bound="Base")


def get_row(session: Session, table: type[RowT], key: Any, what: str, *, for_update: bool = False) -> RowT:
    """The row of ``table`` with primary key ``key``; `NotFound` (naming it ``what``) if there is none."""
    row = session.get(table, key, with_for_update=for_update)
    if row is None:
        raise NotFound(f"{what} {key} not found")
    return row


def dml_rowcount(result: QueryResult[Any]) -> int:
    """The number of rows an UPDATE / DELETE matched.  ``Session.execute`` is typed as returning a plain
    ``Result``, but for a DML statement SQLAlchemy returns a `CursorResult`, which has ``rowcount``."""
    return cast("CursorResult[Any]", result).rowcount


# -- leases -------------------------------------------------------------------------------------------
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
