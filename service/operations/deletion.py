"""Deleting flights, model versions and evaluations, and what depends on each (shown before a delete).

The rule, the same for the API, the web pages and Python:

- What is **deleted with** an object is listed first (``GET .../dependents``, the confirmation page).  When
  that includes things a user made or points at (a version's evaluations or aliases), the delete is refused
  with 409 unless it is forced (``?force=true``; the confirmation page's button forces, after showing them).
  Caches go without asking: a flight's or a version's cached per-flight results (with their stored
  estimates), an evaluation's report figures, the kept estimate exports of the evaluations they show.
- What **keeps a record** of it stays, with the deleted object's id, name or "name:version" as lineage text
  (shown as deleted): versions trained on a deleted flight, evaluations and diagnoses that used it, versions
  whose parent it was, diagnoses that analysed or registered a deleted version, the job of a deleted
  evaluation.
- An object still being computed is **blocked** (409 whatever ``force`` says): a version still training, an
  evaluation whose job is queued or running, a version with such an evaluation.  Cancel the job first.
- Nothing is half-deleted: the rows go in one transaction, and the blobs only they named (normalized flight,
  raw files, weights, stored estimates) are removed after it commits (a blob another row still names stays).
  Ids and version numbers are never handed out again (``registered_models.last_version``).
"""
from __future__ import annotations

from typing import Any

from sqlalchemy import delete, func, select
from sqlalchemy.orm import Session

from learnest.errors import Conflict, NotFound

from ..jobs.runner import ACTIVE
from ..storage import audit, registry
from ..storage.blobs import BlobStore
from ..storage.database import Database, blob_is_referenced
from ..storage.export_cache import forget_exports
from ..storage.tables import (
    Diagnosis,
    Evaluation,
    FlightRecord,
    Job,
    ModelAlias,
    ModelVersion,
    ReportFigure,
    Result,
)


def _item(kind: str, label: str, href: str | None = None, **extra: Any) -> dict:
    return {"kind": kind, "label": label, "href": href, **extra}


def _answer(target: dict, deleted_with_it: list[dict], keeps_a_record: list[dict], *, needs_force: bool,
            blocked: str | None) -> dict:
    return {"target": target, "deleted_with_it": deleted_with_it, "keeps_a_record": keeps_a_record,
            "requires_force": needs_force, "blocked": blocked}


def _evaluation_item(evaluation: Evaluation, job: Job | None) -> dict:
    state = job.state if job else "?"
    return _item("evaluation", f"evaluation {evaluation.id} of {evaluation.model_ref} on "
                               f"{len(evaluation.flight_ids)} flight(s) ({state})",
                 f"/evaluations/{evaluation.id}/report.html", id=evaluation.id)


def _jobs_of(session: Session, evaluations) -> dict[int, Job]:
    ids = [ev.job_id for ev in evaluations]
    return {j.id: j for j in session.scalars(select(Job).where(Job.id.in_(ids)))} if ids else {}


# -- flights ---------------------------------------------------------------------------------------------
def _flight_dependents(session: Session, flight: FlightRecord) -> dict:
    results = session.scalar(select(func.count(Result.id)).where(Result.flight_sha256 == flight.sha256)) or 0
    kept: list[dict] = []
    for v in session.scalars(select(ModelVersion).where(ModelVersion.training_flight_id == flight.id)
                             .order_by(ModelVersion.name, ModelVersion.version)):
        kept.append(_item("model version", f"{v.name}:{v.version} was trained on it (keeps its id, name and "
                                           "sha256)", f"/ui/models/{v.name}/versions/{v.version}",
                          ref=f"{v.name}:{v.version}"))
    # JSON lists cannot be searched portably in SQL: the registry is small, scan them here
    evaluations = [ev for ev in session.scalars(select(Evaluation).order_by(Evaluation.id))
                   if flight.id in (ev.flight_ids or [])]
    jobs = _jobs_of(session, evaluations)
    kept += [{**_evaluation_item(ev, jobs.get(ev.job_id)),
              "label": _evaluation_item(ev, jobs.get(ev.job_id))["label"] + " includes it (keeps its report)"}
             for ev in evaluations]
    kept += [_item("diagnosis", f"diagnosis {d.id} used it (keeps its report)", f"/diagnoses/{d.id}/report.html",
                   id=d.id)
             for d in session.scalars(select(Diagnosis).order_by(Diagnosis.id)) if flight.id in (d.flight_ids or [])]
    gone = [_item("results", f"{results} cached per-flight result(s) with their stored estimates (evaluations "
                             "that include this flight can no longer export its estimates)", count=results)] \
        if results else []
    target = {"kind": "flight", "id": flight.id, "label": f"flight {flight.id}: {flight.name}",
              "href": f"/ui/flights/{flight.id}"}
    return _answer(target, gone, kept, needs_force=False, blocked=None)


def flight_dependents(db: Database, flight_id: int) -> dict:
    """What depends on flight ``flight_id`` (the module docstring says what each list means); NotFound."""
    with db.transaction() as session:
        return _flight_dependents(session, _flight(session, flight_id))


def _flight(session: Session, flight_id: int, for_update: bool = False) -> FlightRecord:
    row = session.get(FlightRecord, flight_id, with_for_update=for_update)
    if row is None:
        raise NotFound(f"flight {flight_id} not found")
    return row


def delete_flight(db: Database, blobs: BlobStore, flight_id: int, actor: str | None = None) -> dict:
    """Delete the flight and its cached results; versions, evaluations and diagnoses keep its id and name.
    Returns what was listed as its dependents.  NotFound when there is none.  The audit log records it as
    ``actor``'s (a token's name; None: the command line's)."""
    with db.transaction() as session:
        # locked first: an evaluation storing this flight's result waits, or has stored it (deleted below)
        row = _flight(session, flight_id, for_update=True)
        dependents = _flight_dependents(session, row)
        candidates = [row.flight_blob] + [f.sha256 for f in row.files]
        candidates += [sha for sha in session.scalars(select(Result.estimates_blob)
                                                      .where(Result.flight_sha256 == row.sha256)) if sha]
        session.execute(delete(Result).where(Result.flight_sha256 == row.sha256))
        session.delete(row)
        audit.record(session, actor, "flight.delete", f"flight {flight_id} ({row.name})",
                     {"sha256": row.sha256, "created_by": row.created_by})
    blobs.collect(candidates, lambda sha: blob_is_referenced(db, sha))  # after the commit: never half-deleted
    # the exports of the evaluations that scored it showed it (an evaluation's whole export too)
    forget_exports(blobs, [d["id"] for d in dependents["keeps_a_record"] if d["kind"] == "evaluation"])
    return dependents


# -- model versions --------------------------------------------------------------------------------------
def _version_dependents(session: Session, row: ModelVersion) -> dict:
    ref = f"{row.name}:{row.version}"
    evaluations = list(session.scalars(select(Evaluation).where(Evaluation.model_version_id == row.id)
                                       .order_by(Evaluation.id)))
    jobs = _jobs_of(session, evaluations)
    aliases = list(session.scalars(select(ModelAlias.alias).where(ModelAlias.name == row.name,
                                                                 ModelAlias.version == row.version)))
    results = session.scalar(select(func.count(Result.id)).where(Result.model_version_id == row.id)) or 0
    gone = [_evaluation_item(ev, jobs.get(ev.job_id)) for ev in evaluations]
    gone += [_item("alias", f"alias {row.name}@{a}", f"/ui/models/{row.name}", alias=a) for a in aliases]
    if results:
        gone.append(_item("results", f"{results} cached per-flight result(s) with their stored estimates",
                          count=results))
    kept = [_item("model version", f"{c.name}:{c.version} names it as its parent", f"/ui/models/{c.name}/versions/"
                                                                                   f"{c.version}",
                  ref=f"{c.name}:{c.version}")
            for c in session.scalars(select(ModelVersion).where(ModelVersion.parent == ref)
                                     .order_by(ModelVersion.name, ModelVersion.version))]
    for d in session.scalars(select(Diagnosis).order_by(Diagnosis.id)):
        registered = d.registered or {}
        if d.model_ref == ref or (registered.get("name"), registered.get("version")) == (row.name, row.version):
            what = "analysed it" if d.model_ref == ref else "registered it"
            kept.append(_item("diagnosis", f"diagnosis {d.id} {what} (keeps its report)",
                              f"/diagnoses/{d.id}/report.html", id=d.id))
    running = [ev.id for ev in evaluations if (jobs.get(ev.job_id) and jobs[ev.job_id].state in ACTIVE)]
    blocked = None
    if row.status == "training":
        blocked = f"{ref} is still training: cancel job {row.job_id} first"
    elif running:
        blocked = f"evaluation(s) {', '.join(map(str, running))} of {ref} still run: cancel their jobs first"
    target = {"kind": "model version", "name": row.name, "version": row.version, "label": ref,
              "href": f"/ui/models/{row.name}/versions/{row.version}"}
    return _answer(target, gone, kept, needs_force=bool(evaluations or aliases), blocked=blocked)


def version_dependents(db: Database, name: str, version: int) -> dict:
    """What depends on ``name:version``; NotFound when there is no such version."""
    with db.transaction() as session:
        return _version_dependents(session, registry.get_version(session, name, version))


def delete_version(db: Database, blobs: BlobStore, name: str, version: int, force: bool = False,
                   actor: str | None = None) -> dict:
    """Delete ``name:version`` with its evaluations (and their report figures), the aliases on it and its
    cached results; the weights and stored estimates blobs go after the commit.  The registered model stays
    (its version numbers are never reused), and so does lineage text naming the version.

    Raises
    ------
    NotFound
        No such version.
    Conflict
        The version is still training or one of its evaluations still runs (whatever ``force``), or it has
        evaluations or aliases and ``force`` is False (the message lists them).

    The audit log records it as ``actor``'s (a token's name; None: the command line's).
    """
    with db.transaction() as session:
        row = registry.get_version(session, name, version)
        dependents = _version_dependents(session, row)
        _refuse(dependents, force)
        evaluation_ids = [d["id"] for d in dependents["deleted_with_it"] if d["kind"] == "evaluation"]
        candidates = [row.weights_blob] if row.weights_blob else []
        candidates += [sha for sha in session.scalars(select(Result.estimates_blob)
                                                      .where(Result.model_version_id == row.id)) if sha]
        if evaluation_ids:
            session.execute(delete(ReportFigure).where(ReportFigure.evaluation_id.in_(evaluation_ids)))
            session.execute(delete(Evaluation).where(Evaluation.id.in_(evaluation_ids)))
        session.execute(delete(Result).where(Result.model_version_id == row.id))
        session.execute(delete(ModelAlias).where(ModelAlias.name == name, ModelAlias.version == version))
        session.delete(row)
        audit.record(session, actor, "version.delete", f"model version {name}:{version}",
                     {"evaluations": evaluation_ids, "created_by": row.created_by, "force": force})
    blobs.collect(candidates, lambda sha: blob_is_referenced(db, sha))
    forget_exports(blobs, evaluation_ids)
    return dependents


def _refuse(dependents: dict, force: bool) -> None:
    if dependents["blocked"]:
        raise Conflict(f"cannot delete {dependents['target']['label']}: {dependents['blocked']}")
    if dependents["requires_force"] and not force:
        listed = "; ".join(d["label"] for d in dependents["deleted_with_it"])
        raise Conflict(f"{dependents['target']['label']} would be deleted with: {listed}. Delete with force=true "
                       "to delete them too")


# -- evaluations -----------------------------------------------------------------------------------------
def _evaluation_dependents(session: Session, evaluation: Evaluation) -> dict:
    job = session.get(Job, evaluation.job_id)
    figures = session.scalar(select(func.count(ReportFigure.id))
                             .where(ReportFigure.evaluation_id == evaluation.id)) or 0
    gone = [_item("report figures", f"{figures} stored report figure(s)", count=figures)] if figures else []
    kept = [_item("job", f"job {job.id} ({job.kind}, {job.state}) stays in the job list", f"/ui/jobs/{job.id}",
                  id=job.id)] if job else []
    blocked = f"its job {job.id} is {job.state}: cancel it first" if job and job.state in ACTIVE else None
    target = {"kind": "evaluation", "id": evaluation.id, "label": f"evaluation {evaluation.id} of "
                                                                  f"{evaluation.model_ref}",
              "href": f"/evaluations/{evaluation.id}/report.html"}
    return _answer(target, gone, kept, needs_force=False, blocked=blocked)


def _evaluation(session: Session, evaluation_id: int) -> Evaluation:
    row = session.get(Evaluation, evaluation_id)
    if row is None:
        raise NotFound(f"evaluation {evaluation_id} not found")
    return row


def evaluation_dependents(db: Database, evaluation_id: int) -> dict:
    """What depends on evaluation ``evaluation_id``; NotFound when there is none."""
    with db.transaction() as session:
        return _evaluation_dependents(session, _evaluation(session, evaluation_id))


def delete_evaluation(db: Database, blobs: BlobStore, evaluation_id: int, actor: str | None = None) -> dict:
    """Delete the evaluation, its report figures and its kept estimate exports; its job stays in the job list,
    and the cached per-flight results stay too (shared by every evaluation of the same version and settings;
    they go with their version or flight).  Conflict while its job is queued or running."""
    with db.transaction() as session:
        row = _evaluation(session, evaluation_id)
        dependents = _evaluation_dependents(session, row)
        _refuse(dependents, force=False)
        session.execute(delete(ReportFigure).where(ReportFigure.evaluation_id == row.id))
        session.delete(row)
        audit.record(session, actor, "evaluation.delete", f"evaluation {evaluation_id} ({row.model_ref})",
                     {"created_by": row.created_by})
    forget_exports(blobs, [evaluation_id])   # after the commit, as the blobs
    return dependents

