"""The functions that run in executor processes (pool workers, Dask workers): training, one flight's
evaluation, a diagnosis.  Each takes and returns bytes, JSON-able values and frozen types of plain values (an
evaluation's settings); flight and model bytes travel with the task, so a remote worker needs no access to the
blob folder; training writes its own progress (`report_progress`) when the worker can reach the database, and
stops (`TaskCancelled`) as soon as it finds its job no longer running (cancelled): the worker is then free for
the next task.
"""
from __future__ import annotations

import logging
import os
import time
from typing import Any

from sqlalchemy import update

from learnest.errors import InvalidInput
from learnest.estimators.evaluation_settings import EvaluationSettings
from learnest.ingest.flight import Flight, json_compatible
from learnest.models.knode import HybridModel

from ..storage import registry
from ..storage.database import Database, dml_rowcount
from ..storage.tables import Job
from .executors import init_worker
from .runner import progress_values

log = logging.getLogger("learnest.jobs")

_worker_databases: dict[str, Database] = {}
PROGRESS_EVERY_S = 1.0


class TaskCancelled(RuntimeError):
    """The task's job is no longer running (cancelled, or failed by a sweep): its work is dropped."""


def report_progress(target: tuple[str, int] | None, fraction: float | None, stage: str | None = None,
                    eta_s: float | None = None) -> bool:
    """Write a job's progress (None: leave it), stage and ETA from a worker; best effort (a remote Dask
    worker may not reach the DB).  Returns False only when the database says the job is no longer running."""
    if target is None:
        return True
    url, job_id = target
    try:
        database = _worker_databases.get(url) or _worker_databases.setdefault(url, Database(url))
        with database.transaction() as session:
            return bool(dml_rowcount(session.execute(update(Job).where(Job.id == job_id, Job.state == "running")
                                                     .values(progress_values(fraction, stage, eta_s)))))
    except Exception:
        log.debug("progress of job %s not written", job_id, exc_info=True)
        return True


def train_task(flight_bytes: bytes | list[bytes], config: dict, progress_target: tuple[str, int] | None = None,
               meta: dict | None = None, validate: list[str] | None = None) -> dict:
    """Algorithm 1 on one flight, or on several of one vehicle with the flights ``validate`` names held out
    whole (workflows.flights.train_on_flights: the residual's scale chosen on held-out groups of the
    flights by ``config["group_by"]``; a version stored before it, without the key, keeps the whole residual);
    the model comes back as JSON.

    ``config`` holds `TrainingConfig`'s fields; ``meta`` is added to the model's meta.  Returns
    ``model_json``, ``losses``, ``validation_losses``, ``seconds`` (the epochs), ``total_seconds`` (the
    whole task: reading the flight, the pre-training observer and the epochs), ``library_versions``,
    ``code_version`` and ``metrics``.  Stages: "observer", then "epoch i/n" with an ETA from the epochs'
    pace; with the scale chosen on held-out groups, each training's stage first ("circle held out: epoch i/n",
    "final training: epoch i/n").  The worker exits if its parent process dies; `TaskCancelled` when the job
    stops running (checked with each progress report, about every PROGRESS_EVERY_S).
    """
    from learnest.models.training import TrainingConfig
    from learnest.workflows.flights import train_on_flights

    started = time.perf_counter()
    init_worker()
    last, parent, first_epoch_done = [0.0], os.getppid(), [0.0]
    epochs = config["epochs"]
    stage: list = ["", 0, 1]   # the training stage (`estimators.group_training`): its name, index and how many

    def on_stage(name: str, index: int, count: int) -> None:
        stage[:] = [f"{name}: " if count > 1 else "", index, count]
        if count > 1:
            report_progress(progress_target, 0.02 + 0.97 * index / count, name)

    def on_epoch(epoch: int, _loss: float) -> None:
        if os.getppid() != parent:  # the server died: an orphaned worker must not train on for hours
            os._exit(1)             # (and nobody is left to read an exception)
        now = time.monotonic()
        if epoch == 0:
            first_epoch_done[0] = now
        # the second epoch gives the first pace: reported at once, so an ETA shows however short the training
        if now - last[0] >= PROGRESS_EVERY_S or epoch == 1 or epoch + 1 == epochs:
            last[0] = now
            # the pace of the epochs after the first (which may carry one-time set-up)
            left = epochs - epoch - 1 + epochs * (stage[2] - stage[1] - 1)   # this stage's and the later ones'
            eta = (now - first_epoch_done[0]) / epoch * left if epoch else None
            if not report_progress(progress_target, 0.02 + 0.97 * (stage[1] + (epoch + 1) / epochs) / stage[2],
                                   f"{stage[0]}epoch {epoch + 1}/{epochs}", eta):
                raise TaskCancelled(f"job {progress_target and progress_target[1]} is no longer running")

    hyper = dict(config)
    system, group_by = hyper.pop("system", "quadrotor"), hyper.pop("group_by", "none")
    noise = hyper.pop("noise", "paper")
    stored = [flight_bytes] if isinstance(flight_bytes, bytes) else flight_bytes
    flights = [flight_from_bytes(data) for data in stored]
    report_progress(progress_target, 0.01, "observer (pre-training state estimates)"
                    + (f" of {len(flights)} flights" if len(flights) > 1 else ""))
    result = train_on_flights(flights, TrainingConfig(**hyper), progress=on_epoch, system=system, validate=validate,
                              group_by=group_by, on_stage=on_stage, noise=noise)
    model = result.model
    model.meta.update(meta or {})
    return {"model_json": registry.model_to_json(model), "losses": [float(x) for x in result.losses],
            "validation_losses": [float(x) for x in result.validation_losses],
            "seconds": float(result.seconds), "total_seconds": time.perf_counter() - started,
            "library_versions": registry.library_versions(),
            "code_version": registry.code_version(),
            "metrics": training_metrics(model)}


def flight_from_bytes(data: bytes) -> Flight:
    """A stored normalized flight (`Flight.to_bytes`); InvalidInput when it cannot be read."""
    try:
        return Flight.from_bytes(data)
    except (OSError, ValueError, KeyError) as err:
        raise InvalidInput(f"the stored normalized flight is unreadable ({type(err).__name__})") from None


def evaluate_task(model_json: bytes, flight_bytes: bytes, settings: EvaluationSettings,
                  progress_target: tuple[str, int] | None = None, label: str = "") -> dict:
    """One flight's entry of workflows.flights.score_flights' report and its estimates.

    ``settings`` travels as its type (pickled to a worker: a frozen dataclass of plain values), as the job read
    it from its stored JSON.  Returns ``entry`` (the flight's `FlightScore` as its JSON, what the result cache
    stores) and ``estimates``: the per-step estimates as `FlightEstimates.to_bytes` (None when the flight was
    not scored).  With ``progress_target`` the job's stage says which method runs on which flight ("knode-ukf
    on flight3 (2/4)", ``label`` being "flight3 (2/4)") and when an MHE is being built.
    """
    from learnest.workflows.flights import score_flights

    init_worker()
    model = registry.model_from_json(model_json)
    flight = flight_from_bytes(flight_bytes)
    kept: list[bytes] = []

    def on_stage(stage: str) -> None:
        report_progress(progress_target, None, f"{stage} on {label or flight.name}")

    report = score_flights(model, [flight], settings, on_estimates=lambda _i, e: kept.append(e.to_bytes()),
                           on_stage=on_stage if progress_target else None)
    return {"entry": report.flights[0].to_dict(), "estimates": kept[0] if kept else None}


def diagnose_task(flights_bytes: list[bytes], model_json: bytes | None, methods: list[str], epochs: int,
                  system: str = "quadrotor", progress_target: tuple[str, int] | None = None) -> dict:
    """workflows.diagnosis.diagnosis_report on stored flights; the report as its JSON (serialised here, once: the
    job stores it as it comes), the repaired model as HybridModel JSON, and the name of the flight it was fitted
    on.  With ``progress_target`` the job's stage and progress follow the diagnosis' named stages (`diagnosis_stages`):
    the diagnosis' fraction f is written as DIAGNOSIS_SPAN[0] + f · (DIAGNOSIS_SPAN[1] - DIAGNOSIS_SPAN[0]);
    `TaskCancelled` when the job stops running."""
    from learnest.workflows.diagnosis import diagnosis_report

    init_worker()
    report_progress(progress_target, DIAGNOSIS_SPAN[0], f"reading {len(flights_bytes)} flight(s)")
    knode = registry.model_from_json(model_json) if model_json is not None else None
    report, repaired = diagnosis_report([flight_from_bytes(b) for b in flights_bytes], knode=knode,
                                        methods=tuple(methods), epochs=epochs, return_model=True, system=system,
                                        on_stage=_stage_writer(progress_target) if progress_target else None)
    assert repaired is not None   # return_model=True
    return {"report": json_compatible(report.to_dict()), "model_json": registry.model_to_json(repaired),
            "fitting_flight": repaired.meta.get("training_flight")}


# the share of a diagnosis job's progress the diagnosis itself covers (the rest: reading, storing the report)
DIAGNOSIS_SPAN = (0.02, 0.94)


def _stage_writer(target: tuple[str, int]):
    """``on_stage(name, fraction)`` writing a diagnosis' stages to its job: every new kind of stage at once,
    the ticks within one (epochs, effects tried) at most every PROGRESS_EVERY_S / 2."""
    from learnest.workflows.diagnosis_stages import stage_kind

    last: dict[str, Any] = {"kind": None, "at": 0.0}

    def on_stage(name: str, fraction: float | None) -> None:
        now, kind = time.monotonic(), stage_kind(name)
        if kind == last["kind"] and now - last["at"] < PROGRESS_EVERY_S / 2:
            return
        last.update(kind=kind, at=now)
        share = None if fraction is None else DIAGNOSIS_SPAN[0] + fraction * (DIAGNOSIS_SPAN[1] - DIAGNOSIS_SPAN[0])
        if not report_progress(target, share, name):
            raise TaskCancelled(f"job {target[1]} is no longer running")

    return on_stage


def noise_summary(model: HybridModel) -> dict:
    """The noise a version's filters run with, as the registry shows it: ``{"model": ..., "prior": ...}``, each
    None (the system's fixed noise) or its source, standard deviations per block in words and how it was
    identified (`learnest.models.noise.NoiseModel`)."""
    def one(noise):
        return None if noise is None else {**noise.describe(model.system), "detail": noise.detail}
    return {"model": one(model.noise), "prior": one(model.prior_noise)}


def training_metrics(model: HybridModel) -> dict:
    """What the registry keeps of a training run besides its weights and losses."""
    residual = None if model.residual is None else \
        {"frame": model.residual.frame, "members": len(model.residual.members or ()) or 1}
    return {"noise": noise_summary(model), "residual": residual,
            **{key: model.meta.get(key) for key in ("final_loss", "best_epoch", "best_validation_loss", "envelope",
                                                    "training_profile")},
            **{key: model.meta[key] for key in ("prior_validation_loss", "learned", "learned_note", "validation",
                                                "batch_pairs", "residual_scale", "residual_scale_groups",
                                                "residual_scale_note") if key in model.meta}}


def diagnosis_metrics(model: HybridModel, report: dict) -> dict:
    """What a version made by a diagnosis records besides its weights: training metrics and before/after."""
    return {**training_metrics(model),
            "diagnosis": {"effects": [e["id"] for e in report["effects"]], "before": report["before"],
                          "after": report["after"]}}
