"""The functions that run in executor processes (pool workers, Dask workers): training, one flight's
evaluation, a diagnosis.  Each takes and returns bytes and JSON-able values (flight and model bytes travel
with the task), so a remote worker needs no access to the blob folder; training writes its own progress
(`report_progress`) when the worker can reach the database, and stops (`TaskCancelled`) as soon as it finds
its job no longer running (cancelled): the worker is then free for the next task.
"""
from __future__ import annotations

import logging
import os
import time

from sqlalchemy import update

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight, json_compatible
from learnest.models.knode import HybridModel

from .. import registry
from ..storage.database import Database, dml_rowcount
from ..storage.tables import Job
from .executors import init_worker

log = logging.getLogger("learnest.jobs")

_worker_databases: dict[str, Database] = {}
PROGRESS_EVERY_S = 1.0


class TaskCancelled(RuntimeError):
    """The task's job is no longer running (cancelled, or failed by a sweep): its work is dropped."""


def report_progress(target: tuple[str, int] | None, fraction: float) -> bool:
    """Write a job's progress from a worker; best effort (a remote Dask worker may not reach the DB).
    Returns False only when the database says the job is no longer running."""
    if target is None:
        return True
    url, job_id = target
    try:
        database = _worker_databases.get(url) or _worker_databases.setdefault(url, Database(url))
        with database.transaction() as session:
            return bool(dml_rowcount(session.execute(update(Job).where(Job.id == job_id, Job.state == "running")
                                                     .values(progress=max(0.0, min(1.0, fraction))))))
    except Exception:
        log.debug("progress of job %s not written", job_id, exc_info=True)
        return True


def train_task(flight_bytes: bytes, config: dict, progress_target: tuple[str, int] | None = None,
               meta: dict | None = None) -> dict:
    """Algorithm 1 on one flight (service.experiments.flights.train_on_flight); the model comes back as JSON.

    ``config`` holds `TrainingConfig`'s fields; ``meta`` is added to the model's meta.  Returns
    ``model_json``, ``losses``, ``seconds``, ``library_versions``, ``code_version`` and ``metrics``.
    The worker exits if its parent process dies; `TaskCancelled` when the job stops running (checked with
    each progress report, about every PROGRESS_EVERY_S).
    """
    from learnest.models.training import TrainingConfig

    from ..experiments.flights import train_on_flight

    init_worker()
    last, parent = [0.0], os.getppid()

    def on_epoch(epoch: int, _loss: float) -> None:
        if os.getppid() != parent:  # the server died: an orphaned worker must not train on for hours
            os._exit(1)             # (and nobody is left to read an exception)
        if time.monotonic() - last[0] >= PROGRESS_EVERY_S:
            last[0] = time.monotonic()
            if not report_progress(progress_target, 0.99 * (epoch + 1) / config["epochs"]):
                raise TaskCancelled(f"job {progress_target and progress_target[1]} is no longer running")

    hyper = dict(config)
    system = hyper.pop("system", "quadrotor")
    result = train_on_flight(flight_from_bytes(flight_bytes), TrainingConfig(**hyper), progress=on_epoch,
                             system=system)
    model = result.model
    model.meta.update(meta or {})
    return {"model_json": registry.model_to_json(model), "losses": [float(x) for x in result.losses],
            "seconds": float(result.seconds), "library_versions": registry.library_versions(),
            "code_version": registry.code_version(),
            "metrics": training_metrics(model)}


def flight_from_bytes(data: bytes) -> Flight:
    """A stored normalized flight (`Flight.to_bytes`); InvalidInput when it cannot be read."""
    try:
        return Flight.from_bytes(data)
    except (OSError, ValueError, KeyError) as err:
        raise InvalidInput(f"the stored normalized flight is unreadable ({type(err).__name__})") from None


def evaluate_task(model_json: bytes, flight_bytes: bytes, settings: dict) -> dict:
    """One flight's entry of service.experiments.flights.evaluate_flights' report and its estimates.

    ``settings`` is `EstimatorSettings.as_dict()`.  Returns ``entry`` and ``estimates``: the per-step
    estimates as `FlightEstimates.to_bytes` (None when the flight was not scored).
    """
    from ..experiments.flights import evaluate_flights

    init_worker()
    model = registry.model_from_json(model_json)
    flight = flight_from_bytes(flight_bytes)
    kept: list[bytes] = []
    report = evaluate_flights(model, [flight], list(settings["methods"]), include_bad=settings["include_bad"],
                              horizon=settings["horizon"], on_estimates=lambda _i, e: kept.append(e.to_bytes()))
    return {"entry": report["flights"][0], "estimates": kept[0] if kept else None}


def diagnose_task(flights_bytes: list[bytes], model_json: bytes | None, methods: list[str], epochs: int,
                  system: str = "quadrotor") -> dict:
    """service.experiments.diagnosis.diagnose_flights on stored flights; the report as plain JSON, the
    repaired model as HybridModel JSON, and the name of the flight it was fitted on."""
    from ..experiments.diagnosis import diagnose_flights

    init_worker()
    knode = registry.model_from_json(model_json) if model_json is not None else None
    report, repaired = diagnose_flights([flight_from_bytes(b) for b in flights_bytes], knode=knode,
                                        methods=tuple(methods), epochs=epochs, return_model=True, system=system)
    return {"report": json_compatible(report), "model_json": registry.model_to_json(repaired),
            "fitting_flight": repaired.meta.get("training_flight")}


def training_metrics(model: HybridModel) -> dict:
    """What the registry keeps of a training run besides its weights and losses."""
    return {key: model.meta.get(key) for key in ("final_loss", "best_epoch", "best_validation_loss", "envelope",
                                                 "training_profile")}


def diagnosis_metrics(model: HybridModel, report: dict) -> dict:
    """What a version made by a diagnosis records besides its weights: training metrics and before/after."""
    return {**training_metrics(model),
            "diagnosis": {"effects": [e["id"] for e in report["effects"]], "before": report["before"],
                          "after": report["after"]}}
