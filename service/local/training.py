"""Training in this process: the next version of a model trained on local log files (a training job on a
one-process pool, waited for, cleaned up when interrupted), and a diagnosis's repaired model registered."""
from __future__ import annotations

from collections.abc import Callable

from learnest.errors import Conflict, InvalidInput, LearnestError
from learnest.models.knode import HybridModel

from ..config import Settings
from ..jobs.services import Services
from ..jobs.tasks import diagnosis_metrics
from ..jobs.training import start_training, training_config
from ..storage import registry
from ..storage.tables import Job, ModelVersion
from .flights import add_flight, log_groups, nothing_read, store_groups
from .services import cli_settings, local_services, wait_for_job


class TrainingFailed(LearnestError):
    """The training job failed (the job's error says why)."""

    status = 422


def train(paths, name: str, *, epochs: int | None = None, include_bad: bool = False,
          progress: Callable[[float], None] | None = None, settings: Settings | None = None,
          system: str = "quadrotor", pose_topic: str | None = None, imu_topic: str | None = None,
          cut: str | None = None, on_stage: Callable[[str, float | None], None] | None = None,
          validate=None, strict: bool = False, group_by: str | None = None, noise: str = "identified",
          ensemble: int = 1) -> dict:
    """Store the flights, train the next version of `name` on them and wait; `progress(fraction)` while it
    trains, `on_stage(stage, seconds_left)` as the job's stage changes ("ingest", "observer ...", "epoch 12/150").

    ``paths`` are the log files of one flight or of several, or folders of them (`learnest.ingest.collect_logs`,
    grouped into flights by `learnest.ingest.group_files`); several flights train one model of one vehicle
    (`service.jobs.training.start_training`), ``validate`` names log files of flights held out whole (default:
    one flight in five).  A file that cannot be read (unknown format, a missing channel, cut short) is listed
    in ``errors`` and the model is trained on the others; with ``strict`` it is an `UnreadableFile` instead,
    raised before any training.  Of several flights, those failing the quality checks are left out and listed
    (``skipped_flights``) unless ``include_bad``; one such flight alone is refused.
    ``cut``: the stretch of the log to keep (`learnest.ingest.align.parse_cut`).  ``group_by``: the groups of
    several flights held out in turn to choose the residual's scale (`learnest.estimators.group_training`;
    default "family", "none" keeps the whole residual).  ``noise``: "identified" (the default) identifies the model's
    and its prior's noise on the training flights and stores it with the version; "paper" keeps the system's
    fixed noise.
    ``ensemble``: residuals trained from seeds on several flights (`learnest.models.ensemble`; 1 trains one).
    Returns what `learnest train --json` prints: ``seconds`` is the epochs' time, ``total_seconds`` the
    job's (observer, epochs, storing), ``training_flights`` and ``validation_flights`` the names, ``learned``
    False when no epoch beat the prior on the held-out data (``learned_note`` says so in words), ``errors``
    ``[{"file", "message"}]`` the files left out because they could not be read, ``residual_scale`` the
    scale of the residual kept, ``residual_scale_groups`` the groups held out to choose it and
    ``residual_scale_note`` how it was chosen or why none was."""
    registry.check_name(name)  # before any work
    settings = settings or cli_settings()
    if on_stage:
        on_stage("ingest", None)
    groups, errors = log_groups(paths, strict)
    held_groups, held_errors = log_groups(validate, strict) if validate else ([], [])
    errors += held_errors
    if not groups and not held_groups:
        raise InvalidInput(nothing_read("no flight log among the given files", errors))
    read = {"pose_topic": pose_topic, "imu_topic": imu_topic, "cut": cut}
    with local_services(settings) as services:
        stored = store_groups(services, groups, errors, strict, read)
        held = [row for row, _ in store_groups(services, held_groups, errors, strict, read)]
        if not stored and not held:
            raise InvalidInput(nothing_read("no flight could be read", errors))
        rows, held, skipped = _quality_filter(list({row.id: row for row, _ in stored}.values()), held, include_bad)
        for row in rows + held:   # before a worker starts: a missing channel is said at once
            _check_inputs(services, row, system)
        job, version = _run_training(services, name, rows, held,
                                     {"epochs": epochs, "system": system, "group_by": group_by, "noise": noise,
                                      "ensemble": ensemble},
                                     include_bad, progress,
                                     on_stage)
    return {**_trained_json(version, job, settings), "skipped_flights": skipped, "errors": errors,
            "flight_stored": "new" if any(created for _, created in stored) else "existing"}


def _quality_filter(rows: list, held: list, include_bad: bool) -> tuple[list, list, list[str]]:
    """(training rows, held-out rows, skipped): the flights failing the quality checks left out and listed,
    unless ``include_bad``; InvalidInput when no good training flight would remain."""
    bad = [row for row in {row.id: row for row in rows + held}.values() if not row.quality_ok]
    if not bad or include_bad:
        return rows, held, []
    held_ids = {row.id for row in held}
    if not [row for row in rows if row.quality_ok and row.id not in held_ids]:
        row = bad[0]   # checked here too, to name the CLI's flag
        raise InvalidInput(f"{row.name} failed the quality checks ({'; '.join(row.quality.get('issues', []))}"
                           "); pass --include-bad to train on it anyway")
    skipped = [f"{row.name} ({'; '.join(row.quality.get('issues', []))})" for row in bad]
    return [row for row in rows if row.quality_ok], [row for row in held if row.quality_ok], skipped


def _run_training(services: Services, name: str, rows: list, held: list, config: dict, include_bad: bool,
                  progress: Callable[[float], None] | None,
                  on_stage: Callable[[str, float | None], None] | None) -> tuple[Job, ModelVersion]:
    """Start the training job on ``rows`` (validated on ``held``), wait for it -> (job, registered version);
    TrainingFailed, with nothing registered, when the job did not succeed or was interrupted."""
    ids = [row.id for row in rows]
    job, version = start_training(services, name, ids[0] if len(ids) == 1 and not held else ids, config,
                                  include_bad=include_bad, validation_ids=[row.id for row in held] if held else None)
    try:
        job = wait_for_job(services, job.id, progress, on_stage=on_stage)
    except BaseException:  # Ctrl-C (KeyboardInterrupt) or a failure while waiting
        abandon_training(services, job.id)
        raise
    with services.db.transaction() as session:
        if job.state != "succeeded":   # no half-made model: the reserved version (and a name left empty) goes
            registry.drop_unfinished_versions(session, job.id)
        else:
            version = registry.get_version(session, name, version.version)
    if job.state != "succeeded":
        names = ", ".join(row.name for row in rows)
        raise TrainingFailed(f"training {name}:{version.version} on {names} failed: {job.error}; nothing was "
                             "registered")
    return job, version


def _trained_json(version: ModelVersion, job: Job, settings: Settings) -> dict:
    """What `learnest train --json` says of a registered version (its flights, whether it learned, timing)."""
    trained = registry.training_flights_of(version)
    validation = list(version.validation_flights or [])
    metrics = version.metrics or {}
    return {"name": version.name, "version": version.version, "ref": f"{version.name}:{version.version}",
            "training_flight": trained[0]["name"], "flight_id": trained[0]["id"],
            "training_flights": [f["name"] for f in trained], "validation_flights": [f["name"] for f in validation],
            "flight_ids": [f["id"] for f in trained], "validation_flight_ids": [f["id"] for f in validation],
            "learned": bool(metrics.get("learned", True)),
            **({"learned_note": metrics["learned_note"]} if metrics.get("learned_note") else {}),
            "system": version.hyperparameters.get("system", "quadrotor"),
            "epochs": version.hyperparameters["epochs"], "best_epoch": metrics.get("best_epoch"),
            "prior_validation_loss": metrics.get("prior_validation_loss"),
            "best_validation_loss": metrics.get("best_validation_loss"),
            "final_loss": version.losses[-1] if version.losses else None, "seconds": version.training_seconds,
            **residual_scale_of(metrics),
            "total_seconds": (job.result or {}).get("total_seconds"), "home": str(settings.home)}


def residual_scale_of(metrics: dict) -> dict:
    """``residual_scale`` (1.0 for a version stored before it was chosen: the whole residual),
    ``residual_scale_groups`` and ``residual_scale_note`` of a version's metrics."""
    return {"residual_scale": float(metrics.get("residual_scale", 1.0)),
            "residual_scale_groups": list(metrics.get("residual_scale_groups") or []),
            "residual_scale_note": metrics.get("residual_scale_note")}


def _check_inputs(services: Services, row, system: str) -> None:
    """MissingInputs (naming the flight and the channels) when the stored flight lacks the prior's inputs; the
    Crazyflie prior takes the thrust in any form the flight carries (`models.inputs.system_for_flight_thrust`)."""
    from learnest.ingest.flight import Flight
    from learnest.models.inputs import MissingInputs, flight_thrust_source, missing_inputs

    if system == "quadrotor":
        return
    flight = Flight.from_bytes(services.blobs.read_bytes(row.flight_blob))
    if system == "crazyflie" and flight_thrust_source(flight) is not None:
        return
    lacking = missing_inputs(flight, system)
    if lacking:
        raise MissingInputs(f"{row.name}: the {system!r} prior needs {', '.join(lacking)}, which this flight does "
                            "not carry; the kinematic prior (--system quadrotor) works without them")


def abandon_training(services: Services, job_id: int) -> None:
    """Cancel a training job this process started and remove the version it reserved, unless it finished
    first (a version that became ready is complete: its row and weights were committed together)."""
    try:
        services.runner.cancel(job_id, "interrupted")
    except Conflict:  # it succeeded or failed before the interrupt: nothing half-done to remove
        return
    with services.db.transaction() as session:
        registry.drop_unfinished_versions(session, job_id)


def register_repaired(name: str, model: HybridModel, flights, report: dict, *, epochs: int,
                      parent: str | None = None, settings: Settings | None = None, warning: str | None = None) -> dict:
    """Store the fitting flight (the one model.meta["training_flight"] names) and register `model` (from
    diagnose_flights(..., return_model=True)) as the next version of `name`, its prior's system in the
    hyperparameters and ``warning`` (a repair registered against the diagnosis's verdict) in its metrics.
    -> {"name", "version", "parent"}"""
    registry.check_name(name)
    fitting = next((f for f in flights if f.name == model.meta.get("training_flight")), flights[0])
    with local_services(settings or cli_settings()) as services:
        row, _ = add_flight(services, [source["path"] for source in fitting.meta["sources"]],
                            **fitting.meta.get("topic_choice", {}))
        version = registry.register_model(services.db, services.blobs, name, model, flight=row,
                                          hyperparameters=training_config({"epochs": epochs,
                                                                           "system": model.system.name}),
                                          parent=parent,
                                          metrics={**diagnosis_metrics(model, report),
                                                   **({"warning": warning} if warning else {})})
    return {"name": version.name, "version": version.version, "parent": version.parent}

