"""Training jobs: reserve a model version, train on the executor (Algorithm 1 on one stored flight), store
the weights and mark the version ready; a failed job fails its version."""
from __future__ import annotations

from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from learnest.errors import InvalidInput
from learnest.models.presets import CRAZYFLIE_TRAINING

from .. import registry
from ..storage.database import discard_blobs, get_row
from ..storage.tables import FlightRecord, Job, ModelVersion, utcnow
from . import quotas
from .runner import JobContext
from .services import Services
from .tasks import train_task


def training_config(overrides: dict) -> dict:
    """The Crazyflie training settings as a dict, with the non-None ``overrides`` applied; "system" is the
    prior the KNODE is built on (service.experiments.flights.FLIGHT_SYSTEMS), kept with the training
    hyperparameters so the registry shows it and a retraining reuses it."""
    return {**CRAZYFLIE_TRAINING.as_dict(), "system": "quadrotor",
            **{k: v for k, v in overrides.items() if v is not None}}


def start_training(services: Services, name: str, flight_id: int, overrides: dict, parent: str | None = None,
                   include_bad: bool = False) -> tuple[Job, ModelVersion]:
    """Reserve name's next version, create the job and launch it.  -> (job, version)

    Raises
    ------
    InvalidInput
        For a bad name, or a flight that failed the quality checks without ``include_bad``;
        `quotas.QuotaExceeded` for more epochs, hidden units or work than the settings allow.
    NotFound
        If the flight or the parent does not exist.
    Conflict
        If the parent version is not ready.
    """
    registry.check_name(name)
    with services.db.transaction() as session:
        flight = get_row(session, FlightRecord, flight_id, "flight")
        if not flight.quality_ok and not include_bad:
            raise InvalidInput(f"flight {flight_id} ({flight.name}) failed the quality checks "
                          f"({'; '.join(flight.quality.get('issues', []))}); pass include_bad to train on it anyway")
        if parent is not None:
            resolved = registry.resolve(session, parent)
            parent = f"{resolved.name}:{resolved.version}"
        samples = flight.samples
    config = training_config(overrides)
    quotas.check_training(services.settings, epochs=config["epochs"], hidden=config["hidden"], samples=samples)
    for attempt in range(20):  # another request may take the same version number first
        try:
            with services.db.transaction() as session:
                flight = get_row(session, FlightRecord, flight_id, "flight")
                job = services.runner.create(session, "training", {"name": name, "flight_id": flight_id,
                                                                   "config": config, "parent": parent})
                version = registry.reserve_version(session, name, job_id=job.id, flight=flight,
                                                   hyperparameters=config, parent=parent)
            break
        except IntegrityError:
            if attempt == 19:
                raise
    version_id = version.id
    services.runner.launch(job.id, lambda ctx: run_training(services, ctx, version_id),
                           on_failure=lambda session, message: _fail_version(session, version_id, message))
    return job, version


def run_training(services: Services, ctx: JobContext, version_id: int) -> None:
    """The training job's work: train on the executor, store the weights, mark the version ready.  The job's
    result has ``seconds`` (the epochs alone) and ``total_seconds`` (the job from start to stored weights)."""
    started_at = utcnow()
    with services.db.transaction() as session:
        version = get_row(session, ModelVersion, version_id, "model version")
        flight = session.get(FlightRecord, version.training_flight_id)
        if flight is None:
            raise InvalidInput(f"training flight {version.training_flight_id} was deleted")
        meta = {"name": version.name, "version": version.version, "training_flight_id": flight.id}
        config, blob = dict(version.hyperparameters), flight.flight_blob
    out = ctx.wait(services.executor, services.executor.submit(train_task, services.blobs.read_bytes(blob), config,
                                                               ctx.progress_target, meta))
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
                                       "total_seconds": (utcnow() - started_at).total_seconds()})
    except BaseException:  # cancelled at the last moment, or the row failed: no weights without their version
        if weights is not None:
            discard_blobs(services.db, services.blobs, [weights])
        raise


def _fail_version(session: Session, version_id: int, message: str) -> None:
    version = session.get(ModelVersion, version_id)
    if version is not None and version.status == "training":
        version.status, version.error = "failed", message
