"""Training jobs: reserve a model version, train on the executor (Algorithm 1 on one stored flight, or on
several flights of one vehicle), store the weights and mark the version ready; a failed job fails its version."""
from __future__ import annotations

from collections.abc import Sequence

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from learnest.errors import InvalidInput
from learnest.models.presets import CRAZYFLIE_TRAINING

from ..storage import registry
from ..storage.database import discard_blobs, get_row
from ..storage.tables import FlightRecord, Job, ModelVersion, utcnow
from . import quotas
from .runner import JobContext
from .services import Services
from .tasks import train_task


def training_config(overrides: dict) -> dict:
    """The Crazyflie training settings as a dict, with the non-None ``overrides`` applied; "system" is the
    prior the KNODE is built on (estimators.prepared.FLIGHT_SYSTEMS) and "group_by" the groups of the
    training flights held out to choose the residual's scale (`learnest.estimators.group_training`: "family",
    "none", "name:REGEX"), kept with the training hyperparameters so the registry shows them and a retraining
    reuses them; "noise" is "identified" (the default: the model's and its prior's noise identified on the
    training flights, `learnest.estimators.noise_identification`) or "paper" (the system's fixed noise)."""
    return {**CRAZYFLIE_TRAINING.as_dict(), "system": "quadrotor", "group_by": "family", "noise": "identified",
            **{k: v for k, v in overrides.items() if v is not None}}


def start_training(services: Services, name: str, flight_id: int | Sequence[int], overrides: dict,
                   parent: str | None = None, include_bad: bool = False, validation_ids: Sequence[int] | None = None,
                   created_by: str | None = None) -> tuple[Job, ModelVersion]:
    """Reserve name's next version (its ``created_by``: the asking token's name), create the job, launch it.

    ``flight_id`` is one stored flight (the paper's protocol: time blocks of it validate) or several, trained
    on as one vehicle (`workflows.flights.train_on_flights`); ``validation_ids`` are held out whole
    (also when not among ``flight_id``), by default one flight in five of several (`default_validation`).
    The version's lineage records every training and validation flight.

    Raises
    ------
    InvalidInput
        For a bad name, a flight given twice, every flight held out, flights whose rows declare different
        vehicles, or a flight that failed the quality checks without ``include_bad``; `quotas.QuotaExceeded`
        for more epochs, hidden units or work than the settings allow.
    NotFound
        If a flight or the parent does not exist.
    Conflict
        If the parent version is not ready.
    """
    from learnest.estimators.flight_training import default_validation

    registry.check_name(name)
    ids = [flight_id] if isinstance(flight_id, int) else [int(i) for i in flight_id]
    twice = sorted({i for i in ids if ids.count(i) > 1})
    if not ids or twice:
        raise InvalidInput(f"flight(s) given more than once: {', '.join(map(str, twice))}" if twice
                           else "training needs at least one flight")
    if validation_ids is None:
        held = [ids[i] for i in default_validation(len(ids))]
    else:
        held = list(dict.fromkeys(int(i) for i in validation_ids))
        ids += [i for i in held if i not in ids]
    trained = [i for i in ids if i not in held]
    if not trained:
        raise InvalidInput(f"every flight is held out for validation ({', '.join(map(str, ids))}): keep one to "
                           "train on")
    with services.db.transaction() as session:
        rows = {i: get_row(session, FlightRecord, i, "flight") for i in ids}
        for i, flight in rows.items():
            if not flight.quality_ok and not include_bad:
                raise InvalidInput(f"flight {i} ({flight.name}) failed the quality checks "
                                   f"({'; '.join(flight.quality.get('issues', []))}); pass include_bad to train on "
                                   "it anyway")
        declared: dict[str, list[str]] = {}
        for flight in rows.values():
            if flight.vehicle:
                declared.setdefault(flight.vehicle, []).append(flight.name)
        if len(declared) > 1:   # what the uploads declared; the job checks the logs and the thrust maps too
            listed = "; ".join(f"{vehicle}: {', '.join(names)}" for vehicle, names in declared.items())
            raise InvalidInput(f"the training flights come from different vehicles ({listed}): one model is trained "
                               "on one vehicle; train a model per vehicle")
        if parent is not None:
            resolved = registry.resolve(session, parent)
            parent = f"{resolved.name}:{resolved.version}"
        charged = [rows[i] for i in ids]
    config = training_config(overrides)
    _charge(services, charged, config)
    for attempt in range(20):  # another request may take the same version number first
        try:
            with services.db.transaction() as session:
                flights = {i: get_row(session, FlightRecord, i, "flight") for i in ids}
                job = services.runner.create(session, "training", {"name": name, "flight_id": trained[0],
                                                                   "flight_ids": ids, "validation_ids": held,
                                                                   "config": config, "parent": parent})
                version = registry.reserve_version(session, name, job_id=job.id, flight=flights[trained[0]],
                                                   hyperparameters=config, parent=parent,
                                                   training_flights=[flights[i] for i in trained],
                                                   validation_flights=[flights[i] for i in held])
                version.created_by = created_by
            break
        except IntegrityError:
            if attempt == 19:
                raise
    version_id = version.id
    services.runner.launch(job.id, lambda ctx: run_training(services, ctx, version_id),
                           on_failure=lambda session, message: _fail_version(session, version_id, message))
    return job, version


def _charge(services: Services, flights: Sequence[FlightRecord], config: dict) -> None:
    """Check the quota on all the work the training causes: every flight the epochs run over (the validation
    flights are predicted each epoch too) and, with two groups or more, one training per held-out group plus
    the final one.  A bad grouping (or a pattern that backtracks without end) is said here, before a job."""
    from learnest.estimators.group_training import group_names

    groups = len(set(group_names([(row.name, row.meta or {}) for row in flights], config["group_by"])))
    quotas.check_training(services.settings, epochs=config["epochs"], hidden=config["hidden"],
                          samples=sum(row.samples for row in flights),
                          trainings=(1 + groups if groups >= 2 else 1) * int(config.get("ensemble", 1)))


def run_training(services: Services, ctx: JobContext, version_id: int) -> None:
    """The training job's work: train on the executor, store the weights, mark the version ready.  The job's
    result has ``seconds`` (the epochs alone), ``total_seconds`` (the job from start to stored weights),
    ``training_flights`` and ``validation_flights`` (names) and ``learned``."""
    started_at = utcnow()
    with services.db.transaction() as session:
        version = get_row(session, ModelVersion, version_id, "model version")
        trained, held = registry.training_flights_of(version), list(version.validation_flights or [])
        rows = []
        for entry in trained + held:
            flight = session.get(FlightRecord, entry["id"]) if entry.get("id") is not None else None
            if flight is None:
                raise InvalidInput(f"training flight {entry.get('id')} ({entry.get('name')}) was deleted")
            rows.append(flight)
        meta = {"name": version.name, "version": version.version, "training_flight_id": rows[0].id}
        validate = [flight.name for flight in rows[len(trained):]]
        job = session.get(Job, ctx.job_id)
        rows = requested_order(rows, (job.payload or {}).get("flight_ids") if job is not None else None)
        config, blobs = dict(version.hyperparameters), [flight.flight_blob for flight in rows]
    flight_bytes = services.blobs.read_bytes(blobs[0]) if len(blobs) == 1 else \
        [services.blobs.read_bytes(blob) for blob in blobs]
    out = ctx.wait(services.executor, services.executor.submit(train_task, flight_bytes, config,
                                                               ctx.progress_target, meta, validate or None))
    ctx.progress(0.995, "storing the weights")
    weights = None
    try:
        with services.blobs.writing():  # the weights blob exists before the row that names it commits
            weights = services.blobs.put_bytes(out["model_json"])
            with services.db.transaction() as session:
                version = get_row(session, ModelVersion, version_id, "model version", for_update=True)
                version.status, version.weights_blob, version.ready_at = "ready", weights, utcnow()
                version.prior = registry.prior_of(out["model_json"])
                version.losses, version.training_seconds = out["losses"], out["seconds"]
                version.validation_losses = out.get("validation_losses") or None
                version.metrics, version.code_version = out["metrics"], out["code_version"]
                version.library_versions = out["library_versions"]
                ctx.complete(session, {"name": version.name, "version": version.version,
                                       "final_loss": out["losses"][-1] if out["losses"] else None,
                                       "seconds": out["seconds"],
                                       "total_seconds": (utcnow() - started_at).total_seconds(),
                                       "training_flights": [f["name"] for f in trained],
                                       "validation_flights": validate,
                                       "learned": out["metrics"].get("learned", True)})
    except BaseException:  # cancelled at the last moment, or the row failed: no weights without their version
        if weights is not None:
            discard_blobs(services.db, services.blobs, [weights])
        raise


def requested_order(rows: list[FlightRecord], flight_ids: Sequence[int] | None) -> list[FlightRecord]:
    """The training's flight rows in the order it was requested (``flight_ids`` of its job: the given flights,
    then the held-out ones not among them), or as given when the job does not list exactly these flights.

    Why: the order is part of the training's input, as in `workflows.flights.train_on_flights`: it
    orders the groups held out in turn and each group's scored flights (`estimators.group_training`), so the
    job trains on the flights in the order a notebook given the same list would.
    """
    by_id = {row.id: row for row in rows}
    if flight_ids is None or sorted(int(i) for i in flight_ids) != sorted(by_id):
        return rows
    return [by_id[int(i)] for i in flight_ids]


def _fail_version(session: Session, version_id: int, message: str) -> None:
    version = session.get(ModelVersion, version_id)
    if version is not None and version.status == "training":
        version.status, version.error = "failed", message
