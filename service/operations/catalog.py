"""Reading what is stored: the data functions the JSON routes and the web pages share.

A route and a page that show the same thing call the same function here (full-stack-fastapi-template's
`crud.py` habit), so they cannot disagree about what "latest version" or "not found" means; each then
shapes the answer its own way (JSON in service.api.routes, HTML in service.web).  Every function opens and
closes its own transaction; the rows it returns stay readable afterwards (the sessions do not expire them
on commit, and a flight's files are loaded with it).  A missing thing is NotFound (404) with the message
both surfaces show.
"""
from __future__ import annotations

from typing import NamedTuple

from sqlalchemy import ColumnElement, func, select

from learnest.errors import Conflict, NotFound

from ..storage import audit, registry
from ..storage.database import Database, flights_by_id
from ..storage.tables import Diagnosis, Evaluation, FlightRecord, Job, ModelVersion, RegisteredModel


# -- flights ---------------------------------------------------------------------------------------------
def _get(db: Database, table, row_id: int, what: str):
    with db.transaction() as session:
        row = session.get(table, row_id)
    if row is None:
        raise NotFound(f"{what} {row_id} not found")
    return row


def get_flight(db: Database, flight_id: int) -> FlightRecord:
    """The flight row with its files; NotFound when there is none."""
    return _get(db, FlightRecord, flight_id, "flight")


def flight_names(db: Database, flight_ids: list[int]) -> list[tuple[int, str | None]]:
    """(id, name) of each flight in order; the name is None for a flight deleted since."""
    with db.transaction() as session:
        found = flights_by_id(session, flight_ids)
    return [(i, found[i].name if i in found else None) for i in flight_ids]


def list_flights(db: Database, *conditions: ColumnElement[bool], limit: int, offset: int = 0,
                 newest_first: bool = False) -> tuple[int, list[FlightRecord]]:
    """(how many flights match `conditions`, one page of them), by id."""
    order = FlightRecord.id.desc() if newest_first else FlightRecord.id
    with db.transaction() as session:
        total = session.scalar(select(func.count(FlightRecord.id)).where(*conditions)) or 0
        query = select(FlightRecord).where(*conditions).order_by(order).limit(limit).offset(offset)
        rows = session.scalars(query).all()
    return total, list(rows)


def name_contains(q: str | None) -> list[ColumnElement[bool]]:
    """The condition "flight name contains ``q``" (case-insensitive; % and _ match themselves), or none."""
    return [FlightRecord.name.icontains(q, autoescape=True)] if q else []


def versions_trained_on(db: Database, flight_id: int) -> list[ModelVersion]:
    """Every model version trained on the flight (any status), by name and version."""
    with db.transaction() as session:
        return list(session.scalars(select(ModelVersion).where(ModelVersion.training_flight_id == flight_id)
                                    .order_by(ModelVersion.name, ModelVersion.version)))


# -- models ----------------------------------------------------------------------------------------------
class ModelSummary(NamedTuple):
    """One registered model as the model lists show it."""

    model: RegisteredModel
    aliases: dict[str, int]        # alias -> version
    latest_version: int | None     # the highest ready version
    version_count: int             # versions of any status


class ModelDetail(NamedTuple):
    """One registered model with all its versions (oldest first)."""

    model: RegisteredModel
    aliases: dict[str, int]
    latest_version: int | None
    versions: list[ModelVersion]


def list_models(db: Database, q: str | None = None) -> list[ModelSummary]:
    """Every registered model, by name; with ``q``, those whose name contains it (case-insensitive)."""
    query = select(RegisteredModel).order_by(RegisteredModel.name)
    if q:
        query = query.where(RegisteredModel.name.icontains(q, autoescape=True))
    with db.transaction() as session:
        models = session.scalars(query).all()
        return [ModelSummary(m, registry.aliases_of(session, m.name), _latest_ready(session, m.name),
                             session.scalar(select(func.count(ModelVersion.id)).where(ModelVersion.name == m.name))
                             or 0)
                for m in models]


def get_model(db: Database, name: str) -> ModelDetail:
    """The model, its aliases and versions; NotFound when no model has that name."""
    with db.transaction() as session:
        model = registry.get_model(session, name)
        versions = session.scalars(select(ModelVersion).where(ModelVersion.name == name)
                                   .order_by(ModelVersion.version)).all()
        return ModelDetail(model, registry.aliases_of(session, name), _latest_ready(session, name), list(versions))


def _latest_ready(session, name: str) -> int | None:
    return session.scalar(select(func.max(ModelVersion.version))
                          .where(ModelVersion.name == name, ModelVersion.status == "ready"))


def get_version_by_id(db: Database, version_id: int) -> ModelVersion:
    """A model version by its row id (what evaluations keep); NotFound when there is none."""
    return _get(db, ModelVersion, version_id, "model version")


def set_alias(db: Database, name: str, alias: str, version: int, actor: str | None = None) -> None:
    """Point `name@alias` at `version` (registry.set_alias in a transaction of its own), in the audit log as
    ``actor``'s (None: the command line's, `audit.local_actor`)."""
    with db.transaction() as session:
        registry.set_alias(session, name, alias, version)
        audit.record(session, actor, "alias.set", f"alias {name}@{alias}", {"version": version})


def delete_alias(db: Database, name: str, alias: str, actor: str | None = None) -> None:
    """Remove `name@alias`, in the audit log as ``actor``'s; NotFound when there is no such alias."""
    with db.transaction() as session:
        version = registry.aliases_of(session, name).get(alias)
        registry.delete_alias(session, name, alias)
        audit.record(session, actor, "alias.delete", f"alias {name}@{alias}", {"version": version})


# -- jobs and the results they make ------------------------------------------------------------------------
def get_job(db: Database, job_id: int) -> Job:
    """The job row; NotFound when there is none."""
    return _get(db, Job, job_id, "job")


def list_jobs(db: Database, *conditions: ColumnElement[bool], limit: int, offset: int = 0) -> tuple[int, list[Job]]:
    """(how many jobs match `conditions`, one page of them), newest first."""
    with db.transaction() as session:
        total = session.scalar(select(func.count(Job.id)).where(*conditions)) or 0
        jobs = session.scalars(select(Job).where(*conditions).order_by(Job.id.desc()).limit(limit).offset(offset))
        return total, list(jobs)


def row_and_job(db: Database, table, row_id: int, what: str):
    """(row, its job) of a job-backed resource (evaluations, diagnoses).

    Raises
    ------
    NotFound
        There is no such row.
    Conflict
        Its job failed or was cancelled (the message carries the job's error).
    """
    with db.transaction() as session:
        row = session.get(table, row_id)
        if row is None:
            raise NotFound(f"{what} {row_id} not found")
        job = session.get(Job, row.job_id)
    if job is None:  # the foreign key forbids it; said rather than an AttributeError if a database lies
        raise NotFound(f"{what} {row_id} has no job")
    if job.state in ("failed", "cancelled"):
        raise Conflict(f"{what} {row_id} {job.state}: {job.error}")
    return row, job


def evaluation_of_job(db: Database, job_id: int) -> Evaluation | None:
    """The evaluation a job computes, if it is an evaluation job."""
    with db.transaction() as session:
        return session.scalar(select(Evaluation).where(Evaluation.job_id == job_id))


def diagnosis_of_job(db: Database, job_id: int) -> Diagnosis | None:
    """The diagnosis a job computes, if it is a diagnosis job."""
    with db.transaction() as session:
        return session.scalar(select(Diagnosis).where(Diagnosis.job_id == job_id))


def evaluations_of(db: Database, versions: list[ModelVersion], limit: int) -> list[tuple[Evaluation, Job | None]]:
    """The newest evaluations of these model versions, each with its job."""
    with db.transaction() as session:
        evaluations = session.scalars(select(Evaluation)
                                      .where(Evaluation.model_version_id.in_([v.id for v in versions]))
                                      .order_by(Evaluation.id.desc()).limit(limit)).all()
        jobs = {j.id: j for j in session.scalars(select(Job).where(Job.id.in_([ev.job_id for ev in evaluations])))}
    return [(ev, jobs.get(ev.job_id)) for ev in evaluations]
