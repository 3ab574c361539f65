"""The registry seen across rows, as MLflow shows it: the evaluations list, a version's lineage, and versions
side by side.  Data functions shared by the JSON routes, the web pages and the CLI (like service.operations.catalog).

- `list_evaluations`: one page of evaluations, newest first, each with its median MSE per method and the
  KNODE improvements (`evaluation_summary`).
- `version_lineage`: the links of one version: training flight(s) and validation flights, whether the residual
  learned anything held-out data confirm, parent, children, the diagnosis that
  produced it and the effects it added, its job, evaluations and aliases; a link to a deleted object is
  marked ``exists: False`` (the row keeps the name as lineage text).
- `compare_versions`: hyperparameters, metrics, loss curves (training and validation) and evaluation
  results on the flights every compared version was evaluated on (MSE per method, side by side).
"""
from __future__ import annotations

from typing import Any

from sqlalchemy import func, select

from learnest.errors import InvalidInput

from ..storage import registry
from ..storage.database import Database, flights_by_id
from ..storage.references import parse_ref
from ..storage.tables import Diagnosis, Evaluation, FlightRecord, Job, ModelAlias, ModelVersion

MAX_COMPARED = 10


# -- evaluations -----------------------------------------------------------------------------------------
def split_ref(model_ref: str) -> tuple[str, int | None]:
    """("name", version) of a stored "name:version" reference."""
    name, _, version = model_ref.partition(":")
    return name, int(version) if version.isdigit() else None


def evaluation_summary(evaluation: Evaluation, job: Job | None) -> dict:
    """One row of the evaluations list: state, model version, flights, median MSE per method, improvements
    (percent, KNODE vs its prior: positive is better), links."""
    report = evaluation.report or {}
    name, version = split_ref(evaluation.model_ref)
    return {"id": evaluation.id, "job_id": evaluation.job_id, "state": job.state if job else "unknown",
            "model_ref": evaluation.model_ref, "model": name, "version": version,
            "flight_ids": list(evaluation.flight_ids), "flights_scored": report.get("flights_scored"),
            "methods": list(evaluation.settings.get("methods", [])),
            "median_mse": report.get("median") or {}, "improvement_pct": report.get("improvement_pct") or {},
            "created_at": evaluation.created_at, "created_by": evaluation.created_by,
            "links": {"report": f"/evaluations/{evaluation.id}/report.html", "json": f"/evaluations/{evaluation.id}",
                      "model_version": f"/models/{name}/versions/{version}", "job": f"/jobs/{evaluation.job_id}"}}


def list_evaluations(db: Database, q: str | None = None, model: str | None = None, limit: int = 50,
                     offset: int = 0) -> tuple[int, list[dict]]:
    """(how many match, one page of `evaluation_summary` rows), newest first; ``q`` matches the model
    reference (case-insensitive substring), ``model`` a model name exactly."""
    conditions = []
    if q:
        conditions.append(Evaluation.model_ref.icontains(q, autoescape=True))
    if model:
        conditions.append(Evaluation.model_ref.startswith(f"{model}:", autoescape=True))
    with db.transaction() as session:
        total = session.scalar(select(func.count(Evaluation.id)).where(*conditions)) or 0
        rows = list(session.scalars(select(Evaluation).where(*conditions).order_by(Evaluation.id.desc())
                                    .limit(limit).offset(offset)))
        jobs = {j.id: j for j in session.scalars(select(Job).where(Job.id.in_([r.job_id for r in rows])))}
    return total, [evaluation_summary(r, jobs.get(r.job_id)) for r in rows]


# -- lineage ---------------------------------------------------------------------------------------------
def version_lineage(db: Database, name: str, version: int) -> dict:
    """The links of ``name:version`` (module docstring); NotFound when there is no such version."""
    with db.transaction() as session:
        row = registry.get_version(session, name, version)
        ref = f"{name}:{version}"
        flight = session.get(FlightRecord, row.training_flight_id) if row.training_flight_id else None
        trained, held = registry.training_flights_of(row), list(row.validation_flights or [])
        ids = [f["id"] for f in trained + held if f.get("id") is not None]
        stored = set(session.scalars(select(FlightRecord.id).where(FlightRecord.id.in_(ids)))) if ids else set()
        parent = _parent(session, row.parent)
        children = [f"{c.name}:{c.version}" for c in session.scalars(
            select(ModelVersion).where(ModelVersion.parent == ref).order_by(ModelVersion.name, ModelVersion.version))]
        produced_by = next((d for d in session.scalars(select(Diagnosis).where(Diagnosis.register_as == name))
                            if (d.registered or {}).get("version") == version), None)
        analysed_by = [d.id for d in session.scalars(select(Diagnosis).where(Diagnosis.model_ref == ref)
                                                     .order_by(Diagnosis.id))]
        evaluations = list(session.scalars(select(Evaluation).where(Evaluation.model_version_id == row.id)
                                           .order_by(Evaluation.id.desc())))
        jobs = {j.id: j for j in session.scalars(select(Job).where(Job.id.in_([e.job_id for e in evaluations])))}
        aliases = sorted(session.scalars(select(ModelAlias.alias).where(ModelAlias.name == name,
                                                                       ModelAlias.version == version)))
    diagnosis_metrics = (row.metrics or {}).get("diagnosis") or {}
    effects = list(diagnosis_metrics.get("effects") or (row.prior or {}).get("effects") or [])
    return {
        "ref": ref,
        "training_flight": {"id": row.training_flight_id, "name": row.training_flight_name,
                            "sha256": row.training_flight_sha256, "exists": flight is not None,
                            "href": f"/flights/{row.training_flight_id}" if flight else None},
        # every flight it was trained on, and those held out whole to choose its epoch (lineage by sha256)
        "training_flights": [_flight_link(f, stored) for f in trained],
        "validation_flights": [_flight_link(f, stored) for f in held],
        "learned": (row.metrics or {}).get("learned"),
        "learned_note": (row.metrics or {}).get("learned_note"),
        "parent": parent,
        "children": [{"ref": c, "href": "/models/{}/versions/{}".format(*c.split(":"))} for c in children],
        "diagnosis": {"id": produced_by.id if produced_by else None,
                      "href": f"/diagnoses/{produced_by.id}" if produced_by else None,
                      "effects_added": effects, "before": diagnosis_metrics.get("before"),
                      "after": diagnosis_metrics.get("after")} if (produced_by or diagnosis_metrics) else None,
        "analysed_by_diagnoses": [{"id": i, "href": f"/diagnoses/{i}"} for i in analysed_by],
        "job": {"id": row.job_id, "href": f"/jobs/{row.job_id}"} if row.job_id else None,
        "aliases": aliases,
        "evaluations": [{**evaluation_summary(e, jobs.get(e.job_id))} for e in evaluations],
    }


def _flight_link(entry: dict, stored: set) -> dict:
    exists = entry.get("id") in stored
    return {"id": entry.get("id"), "name": entry.get("name"), "sha256": entry.get("sha256"), "exists": exists,
            "href": f"/flights/{entry['id']}" if exists else None}


def _parent(session, parent: str | None) -> dict | None:
    if not parent:
        return None
    name, version = split_ref(parent)
    exists = version is not None and session.scalar(
        select(ModelVersion.id).where(ModelVersion.name == name, ModelVersion.version == version)) is not None
    return {"ref": parent, "exists": exists, "href": f"/models/{name}/versions/{version}" if exists else None}


# -- comparing versions ------------------------------------------------------------------------------------
def _compared_version(session, text: str) -> ModelVersion:
    """A "name:version" of any status, or what "name" / "name@alias" resolves to."""
    ref = parse_ref(text)
    if ref.version is not None:
        return registry.get_version(session, ref.name, ref.version)
    return registry.resolve(session, ref)


def compare_versions(db: Database, refs: list[str]) -> dict:
    """Two or more versions side by side.

    Returns
    -------
    dict
        ``versions`` (ref, status, training flight, parent, training time, losses, validation losses),
        ``hyperparameters`` and ``metrics``: {key: [value per version]} with ``differs`` lists naming the
        keys whose values are not all equal; ``flights``: the flights every version was scored on (its
        newest succeeded evaluation that scored the flight), each with ``mse`` {method: [per version]} and
        the ``evaluations`` the numbers come from; ``median_mse`` {method: [per version]} over those
        flights; ``methods`` scored for every version.

    Raises
    ------
    InvalidInput
        Fewer than two or more than MAX_COMPARED references, a malformed one, or the same version twice.
    NotFound, Conflict
        A reference names no version (or, by alias or name, no ready one).
    """
    import numpy as np

    if not 2 <= len(refs) <= MAX_COMPARED:
        raise InvalidInput(f"compare needs 2 to {MAX_COMPARED} versions (name:version, name@alias or name), "
                           f"got {len(refs)}")
    with db.transaction() as session:
        rows = [_compared_version(session, r) for r in refs]
        names = [f"{r.name}:{r.version}" for r in rows]
        if len(set(names)) < len(names):
            raise InvalidInput(f"the same version is named twice: {', '.join(names)}")
        scored = [_scored_flights(session, r) for r in rows]
        common = sorted(set.intersection(*(set(s) for s in scored)))
        flights = flights_by_id(session, common)
    methods = [m for m in sorted({m for s in scored for entry in s.values() for m in entry["mse"]})
               if all(m in s[f]["mse"] for s in scored for f in common)]
    per_flight = [{"flight_id": f, "flight": flights[f].name if f in flights else scored[0][f]["flight"],
                   "evaluations": [s[f]["evaluation_id"] for s in scored],
                   "mse": {m: [s[f]["mse"][m] for s in scored] for m in methods}} for f in common]
    median = {m: [float(np.median([s[f]["mse"][m] for f in common])) for s in scored] for m in methods} \
        if common else {}
    hyper = _side_by_side([r.hyperparameters or {} for r in rows])
    metric_values = [{k: v for k, v in (r.metrics or {}).items() if not isinstance(v, (dict, list))}
                     | {"training_seconds": r.training_seconds} for r in rows]
    metrics = _side_by_side(metric_values)
    return {"refs": names,
            "versions": [{"ref": f"{r.name}:{r.version}", "name": r.name, "version": r.version, "status": r.status,
                          "training_flight": {"id": r.training_flight_id, "name": r.training_flight_name},
                          "parent": r.parent, "system": (r.hyperparameters or {}).get("system", "quadrotor"),
                          "training_seconds": r.training_seconds, "losses": r.losses,
                          "validation_losses": r.validation_losses} for r in rows],
            "hyperparameters": hyper, "metrics": metrics, "methods": methods, "flights": per_flight,
            "median_mse": median}


def _side_by_side(dicts: list[dict]) -> dict:
    keys = sorted({k for d in dicts for k in d})
    values = {k: [d.get(k) for d in dicts] for k in keys}
    return {"values": values, "differs": [k for k, v in values.items() if any(x != v[0] for x in v)]}


def _scored_flights(session, version: ModelVersion) -> dict[int, dict[str, Any]]:
    """{flight id: {"flight", "mse", "evaluation_id"}} of every flight this version's succeeded evaluations
    scored, from the newest evaluation that scored it."""
    evaluations = list(session.scalars(select(Evaluation).where(Evaluation.model_version_id == version.id)
                                       .order_by(Evaluation.id.desc())))
    succeeded = set(session.scalars(select(Job.id).where(Job.id.in_([e.job_id for e in evaluations]),
                                                         Job.state == "succeeded")))
    out: dict[int, dict[str, Any]] = {}
    for evaluation in evaluations:
        if evaluation.job_id not in succeeded:
            continue
        for flight_id, entry in zip(evaluation.flight_ids, (evaluation.report or {}).get("flights", []), strict=False):
            if not entry.get("excluded") and entry.get("mse") and flight_id not in out:
                out[flight_id] = {"flight": entry.get("flight"), "mse": entry["mse"], "evaluation_id": evaluation.id}
    return out
