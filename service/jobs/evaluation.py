"""Evaluation jobs: score a model version on stored flights, one executor task per flight without a cached
result (`result_cache`), then the report (the shape of workflows.flights.evaluate_flights)."""
from __future__ import annotations

import json
import logging
import time
from collections.abc import Callable, Iterable, Sequence

from sqlalchemy import select
from sqlalchemy.orm import Session

from learnest.errors import InvalidInput
from learnest.estimators.evaluation_settings import EvaluationSettings
from learnest.workflows.reports import EvaluationReport, FlightScore

from ..storage import registry
from ..storage.database import discard_blobs, flights_by_id, flights_not_found, get_row
from ..storage.tables import Evaluation, FlightRecord, ModelVersion, utcnow
from .result_cache import cached_entries, settings_key, store_result
from .runner import JobContext, error_message
from .services import Services
from .tasks import evaluate_task

log = logging.getLogger("learnest.jobs")


def start_evaluation(services: Services, model_ref: str, flights: Iterable[int] | str, settings: EvaluationSettings,
                     wait: bool = False, on_progress: Callable[[], object] | None = None,
                     created_by: str | None = None) -> tuple[int, int, str]:
    """Create the evaluation and its job; answer from the cache at once when every flight has a result,
    otherwise run it (in the background, or here when wait=True).  -> (job id, evaluation id, state)
    ``created_by``: the name of the token that asks for it (None without a token).

    ``flights`` is a list of flight ids or ``"all-other"`` (every stored flight but the training one).
    ``settings`` are stored as their JSON (the job's arguments, the evaluation's row), which the job reads back
    into the type before anything runs.
    """
    with services.db.transaction() as session:
        version = registry.resolve(session, model_ref)
        flight_ids = _flight_ids(session, flights, version)
        stored = settings.to_json()
        job = services.runner.create(session, "evaluation", {"model": model_ref, "flights": flight_ids,
                                                             "settings": stored})
        evaluation = Evaluation(job_id=job.id, model_ref=f"{version.name}:{version.version}",
                                model_version_id=version.id, flight_ids=flight_ids,
                                settings=stored, created_at=utcnow(), created_by=created_by)
        session.add(evaluation)
        session.flush()
        by_id = flights_by_id(session, flight_ids)
        _check_gaps(settings, [by_id[i] for i in flight_ids])   # before a job exists: the transaction rolls back
        shas = [by_id[i].sha256 for i in flight_ids]
        entries = cached_entries(session, version.id, settings_key(settings), shas)
        if len(entries) == len(flight_ids):  # everything cached: no job to run
            evaluation.report = assemble_report(evaluation.model_ref, [entries[sha] for sha in shas], flight_ids,
                                                shas, model_meta=_model_meta(services.blobs.read_bytes(
                                                    registry.weights_of(version)))).to_dict()
            job.state, job.progress, job.started_at, job.finished_at = "succeeded", 1.0, utcnow(), utcnow()
            job.result = {"evaluation_id": evaluation.id, "flights": len(flight_ids), "computed": 0}
            return job.id, evaluation.id, job.state
        job_id, evaluation_id = job.id, evaluation.id

    def work(ctx: JobContext) -> None:
        run_evaluation(services, ctx, evaluation_id)

    if wait:
        services.runner.run(job_id, work, on_progress=on_progress)
    else:
        services.runner.launch(job_id, work)
    return job_id, evaluation_id, "queued"


def _check_gaps(settings: EvaluationSettings, flights: Sequence[FlightRecord]) -> None:
    """InvalidInput naming the field and the flight when the settings' gap plan does not fit a flight's grid: a
    gap or the mocap between gaps shorter than one sample, or more than MAX_GAPS gaps (`GapPlan.problem_on`)."""
    for flight in flights:
        dt = 1.0 / flight.rate_hz if flight.rate_hz and flight.rate_hz > 0 else None
        problem = settings.gaps.problem_on(dt, flight.samples)
        if problem is not None:
            raise InvalidInput(f"{problem} (flight {flight.id}, {flight.name}, at {flight.rate_hz:.4g} Hz)")


def run_evaluation(services: Services, ctx: JobContext, evaluation_id: int) -> None:
    """The evaluation job's work: one executor task per flight without a cached result, each stored as
    it finishes (a failed flight is recorded and does not stop the others), then the report."""
    with services.db.transaction() as session:
        evaluation = get_row(session, Evaluation, evaluation_id, "evaluation")
        version = get_row(session, ModelVersion, evaluation.model_version_id, "model version")
        settings = EvaluationSettings.from_json(evaluation.settings)   # stored JSON, read back at once
        key = settings_key(settings)
        flights = flights_by_id(session, evaluation.flight_ids)
        entries = cached_entries(session, version.id, key, [f.sha256 for f in flights.values()])
        model_json = services.blobs.read_bytes(registry.weights_of(version))
        todo = {f.id: (f.name, f.sha256, f.flight_blob) for f in flights.values() if f.sha256 not in entries}
        order = [flights[i].sha256 if i in flights else None for i in evaluation.flight_ids]
        model_ref, version_id, flight_ids = evaluation.model_ref, version.id, list(evaluation.flight_ids)

    total, done, failed = len(flight_ids), len(flight_ids) - len(todo), 0
    ctx.progress(done / total, f"{len(todo)} of {total} flight(s) to compute ({done} from the results cache)")
    futures = {}
    for k, (flight_id, (name, sha, blob)) in enumerate(todo.items(), start=1):
        try:
            flight_bytes = services.blobs.read_bytes(blob)
        except FileNotFoundError:  # deleted while this job was starting
            entries[sha], done = _missing_entry(flight_id), done + 1
            continue
        futures[services.executor.submit(evaluate_task, model_json, flight_bytes, settings,
                                         ctx.progress_target, f"{name} ({k}/{len(todo)})")] = (flight_id, name, sha)
    started, computed = time.monotonic(), 0
    for future in ctx.finished(services.executor, futures):  # JobAborted when cancelled: no report stored
        flight_id, name, sha = futures[future]
        entry, estimates, error = _outcome(future, name)
        failed += error is not None
        with services.blobs.writing():  # the estimates blob, then the row naming it
            kept = services.blobs.put_bytes(estimates) if estimates is not None else None
            replaced = store_result(services.db, sha, version_id, key, flight_id, entry, error, kept)
        discard_blobs(services.db, services.blobs, [replaced] if replaced else [])
        entries[sha] = entry
        done, computed = done + 1, computed + 1
        # the pace of the flights computed so far, for the ones left
        ctx.progress(done / total, f"{done}/{total} flight(s) done",
                     (time.monotonic() - started) / computed * (len(futures) - computed))

    report = assemble_report(model_ref, [entries[sha] if sha else _missing_entry(i)
                                         for i, sha in zip(flight_ids, order)], flight_ids, order,
                             model_meta=_model_meta(model_json))
    with services.db.transaction() as session:
        get_row(session, Evaluation, evaluation_id, "evaluation").report = report.to_dict()
        ctx.complete(session, {"evaluation_id": evaluation_id, "flights": total, "computed": len(todo),
                               "failed": failed})


def _outcome(future, flight_name: str) -> tuple[dict, bytes | None, str | None]:
    """(entry, estimates bytes, error): a flight that fails is recorded with its reason and does not stop
    the others."""
    try:
        result = future.result()
        return result["entry"], result["estimates"], None
    except Exception as err:
        message = error_message(err)
        log.warning("evaluation of %s failed: %s", flight_name, message)
        return {"flight": flight_name, "excluded": True, "reason": f"failed: {message}", "mse": {}, "groups": {},
                "failed": True}, None, message


def _missing_entry(flight_id: int) -> dict:
    return {"flight": f"#{flight_id}", "excluded": True, "reason": "flight was deleted", "mse": {}, "groups": {}}


def assemble_report(model_ref: str, entries: list[dict], flight_ids: Sequence[int],
                    shas: Sequence[str | None], model_meta: dict | None = None) -> EvaluationReport:
    """The evaluation's report from its flights' stored entries (the JSON of `FlightScore`s, each read back into
    the type here), as workflows.flights.score_flights builds it; each flight's entry also names the stored
    flight (``flight_id``, ``sha256``: its content key); ``learned`` and ``learned_note`` come from the model's
    ``model_meta``.  Stored as its JSON (`EvaluationReport.to_dict`)."""
    from learnest.estimators.evaluate import summarize

    scores = [FlightScore.from_dict(entry).updated(flight_id=flight_id, sha256=sha)
              for entry, flight_id, sha in zip(entries, flight_ids, shas)]
    return summarize(scores, model=model_ref, model_meta=model_meta or {})


def _model_meta(model_json: bytes) -> dict:
    """The meta of a stored model (`registry.model_to_json`), {} when it has none."""
    try:
        return dict(json.loads(model_json).get("meta") or {})
    except (ValueError, AttributeError):
        return {}


def _flight_ids(session: Session, flights, version: ModelVersion) -> list[int]:
    if flights == "all-other":
        query = select(FlightRecord.id).order_by(FlightRecord.id)
        if version.training_flight_id is not None:
            query = query.where(FlightRecord.id != version.training_flight_id)
        ids = list(session.scalars(query))
        if not ids:
            raise InvalidInput("no flights other than the model's training flight are stored")
        return ids
    ids = list(dict.fromkeys(int(i) for i in flights))
    if not ids:
        raise InvalidInput("flights: give at least one flight id, or \"all-other\"")
    found = set(session.scalars(select(FlightRecord.id).where(FlightRecord.id.in_(ids))))
    missing = [i for i in ids if i not in found]
    if missing:
        raise flights_not_found(missing)
    return ids
