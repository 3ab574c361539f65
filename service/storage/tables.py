"""The service's tables (SQLAlchemy ORM): flights and their raw files, the model registry (names, versions,
aliases), jobs, evaluations, diagnoses, the per-flight result cache, leases, and who may do what (API tokens,
web sessions, the audit log).

Alembic migrations (`storage/migrations`) create them; every timestamp is naive UTC (`utcnow`).
"""
from __future__ import annotations

from datetime import UTC, datetime

from sqlalchemy import (
    JSON,
    BigInteger,
    Boolean,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    text,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship


def utcnow() -> datetime:
    """Naive UTC: SQLite drops time zones, so every timestamp is stored as UTC without one."""
    return datetime.now(UTC).replace(tzinfo=None)


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
    created_by: Mapped[str | None] = mapped_column(String(100))   # the token's name (None: no token, the CLI)
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
    # the highest version number ever handed out: a deleted version's number is never reused (see 0006)
    last_version: Mapped[int] = mapped_column(Integer, default=0, server_default="0")


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
    # every flight trained on / held out whole for validation: [{"id", "name", "sha256"}] (see 0007); the
    # training_flight_* columns above are the first training flight's
    training_flights: Mapped[list | None] = mapped_column(JSON)
    validation_flights: Mapped[list | None] = mapped_column(JSON)
    parent: Mapped[str | None] = mapped_column(String(120))
    hyperparameters: Mapped[dict] = mapped_column(JSON)
    prior: Mapped[dict | None] = mapped_column(JSON)
    losses: Mapped[list | None] = mapped_column(JSON)
    validation_losses: Mapped[list | None] = mapped_column(JSON)   # per epoch (None before 0006 / no split)
    training_seconds: Mapped[float | None] = mapped_column(Float)
    metrics: Mapped[dict | None] = mapped_column(JSON)
    code_version: Mapped[dict | None] = mapped_column(JSON)
    library_versions: Mapped[dict | None] = mapped_column(JSON)
    weights_blob: Mapped[str | None] = mapped_column(String(64))
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    created_by: Mapped[str | None] = mapped_column(String(100))   # the token's name (None: no token, the CLI)
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
    failed | cancelled, ``progress`` 0..1, ``stage`` what it does now with ``eta_s`` (the seconds left as
    estimated at ``progress_at``), ``owner`` the server process running it."""

    __tablename__ = "jobs"
    __table_args__ = {"sqlite_autoincrement": True}  # an id is never handed out twice (see 0003)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    kind: Mapped[str] = mapped_column(String(20))
    state: Mapped[str] = mapped_column(String(20), index=True, default="queued")
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    stage: Mapped[str | None] = mapped_column(String(200))       # "observer", "epoch 12/150", ...
    eta_s: Mapped[float | None] = mapped_column(Float)           # seconds left, as estimated at progress_at
    progress_at: Mapped[datetime | None] = mapped_column(DateTime)
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
    created_by: Mapped[str | None] = mapped_column(String(100))   # the token's name (None: no token, the CLI)


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
    created_by: Mapped[str | None] = mapped_column(String(100))   # the token's name (None: no token, the CLI)


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
    # FlightEstimates.to_bytes of a scored flight (None: excluded, failed, or stored before 0005)
    estimates_blob: Mapped[str | None] = mapped_column(String(64))
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class ReportFigure(Base):
    """The velocity figure of one flight of an evaluation's report page, computed once (it runs the UKFs) by
    an executor task and kept: a page view never runs an estimator for a figure stored here."""

    __tablename__ = "report_figures"
    __table_args__ = (UniqueConstraint("evaluation_id", "flight_id", name="uq_report_figures_evaluation_flight"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    evaluation_id: Mapped[int] = mapped_column(ForeignKey("evaluations.id", ondelete="CASCADE"))
    flight_id: Mapped[int] = mapped_column(Integer)
    png: Mapped[str | None] = mapped_column(Text)                # data URI; None when it failed
    error: Mapped[str | None] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)


class Lease(Base):
    """A named lock with an expiry: whoever holds an unexpired lease owns the thing it names."""

    __tablename__ = "leases"

    name: Mapped[str] = mapped_column(String(200), primary_key=True)
    owner: Mapped[str] = mapped_column(String(200))
    expires_at: Mapped[float] = mapped_column(Float)              # unix time


ACTIVE_TOKEN = text("revoked_at IS NULL")


class ApiToken(Base):
    """A person's API token: only its SHA-256 is kept (the token itself is shown once, when it is made).
    ``scope`` is read, write or admin; a revoked token keeps its row (the audit log names it), and its name
    may be given to a new token.  Rows are never deleted, so "tokens exist" never turns false again."""

    __tablename__ = "api_tokens"
    __table_args__ = (Index("uq_api_tokens_active_name", "name", unique=True, sqlite_where=ACTIVE_TOKEN,
                            postgresql_where=ACTIVE_TOKEN), {"sqlite_autoincrement": True})

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    name: Mapped[str] = mapped_column(String(64))
    scope: Mapped[str] = mapped_column(String(10))
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)   # sha256 hex of the token
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    created_by: Mapped[str | None] = mapped_column(String(100))
    revoked_at: Mapped[datetime | None] = mapped_column(DateTime)
    revoked_by: Mapped[str | None] = mapped_column(String(100))


class WebSession(Base):
    """A web sign-in: the browser holds a random session id in an HttpOnly cookie, this row its SHA-256 and
    the hash of the token it signed in with, which is looked up again on every request (a revoked token ends
    its sessions at once)."""

    __tablename__ = "web_sessions"

    id_hash: Mapped[str] = mapped_column(String(64), primary_key=True)
    token_hash: Mapped[str] = mapped_column(String(64), index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime, default=utcnow)
    expires_at: Mapped[datetime] = mapped_column(DateTime, index=True)


class AuditEntry(Base):
    """One deletion or access change: who (``actor``, a token's name), what (``action``), on what
    (``target``), when.  No foreign key: an entry outlives whatever it names."""

    __tablename__ = "audit_log"
    __table_args__ = {"sqlite_autoincrement": True}

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    at: Mapped[datetime] = mapped_column(DateTime, index=True, default=utcnow)
    actor: Mapped[str] = mapped_column(String(100))
    action: Mapped[str] = mapped_column(String(40))
    target: Mapped[str] = mapped_column(String(300))
    detail: Mapped[dict | None] = mapped_column(JSON)
