"""The model registry and flight store used in process, without HTTP: what the CLI's commands do.

It uses the same database and blob folder as `learnest serve` (LEARNEST_HOME, or LEARNEST_DATABASE_URL), so a
model trained by `learnest train` is `name:version` for the API and the web pages too, and the reverse.  This
replaces the plain file store of the ingest issue (home/models/NAME.json files are no longer read).

- `add_flight`: store a flight's log file(s) as POST /flights does (service.operations.uploads.add_flight: raw files +
  normalized flight as blobs, one row, deduplicated by sha256).
- `train`: register the next version of a model trained on those flights (one, or several of one vehicle), as
  POST /models does (a training job on a one-process local pool, with the same provenance), and wait for it.
  Interrupted (Ctrl-C), the job is
  cancelled, its worker stopped and its reserved version removed: nothing half-registered is left.
- `register_repaired`: register a diagnosis' repaired model as the next version of a name (its fitting flight
  stored as by an upload), as POST /diagnoses with "register" does.
- `evaluate`: store the flights (as `add_flight`) and evaluate a registered version on them as POST /evaluations
  does, here and now (`InlineExecutor`); the evaluation is then in the registry, its page and its exports.
- `export`: write a stored evaluation's state estimates (service.operations.exports).
- `load_model`: "NAME" (its latest ready version), "NAME:VERSION" or "NAME@ALIAS" -> HybridModel, through
  service.storage.registry.load_model_ref; a reference that names nothing usable is a NotFound or Conflict listing the
  known models.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

from sqlalchemy import select

from learnest.errors import Conflict, InvalidInput, LearnestError, NotFound
from learnest.ingest.flight import existing_file
from learnest.ingest.sidecar import info_sidecar
from learnest.models.knode import HybridModel

from ..config import Settings
from ..jobs.evaluation import start_evaluation
from ..jobs.executors import Executor, InlineExecutor
from ..jobs.result_cache import EstimatorSettings
from ..jobs.runner import ACTIVE, seconds_left
from ..jobs.services import Services, open_services
from ..jobs.tasks import diagnosis_metrics
from ..jobs.training import start_training, training_config
from ..operations import catalog
from ..operations.uploads import LocalFile
from ..operations.uploads import add_flight as add_uploaded_flight
from ..storage import registry
from ..storage.blobs import BlobStore
from ..storage.database import Database
from ..storage.tables import Evaluation, FlightRecord, Job, ModelVersion, RegisteredModel


class TrainingFailed(LearnestError):
    """The training job failed (the job's error says why)."""

    status = 422


def cli_settings() -> Settings:
    """The LEARNEST_* settings, except that the CLI trains in one local worker process (never on Dask)."""
    return Settings().model_copy(update={"dask_address": None, "pool_workers": 1, "schedule_seconds": 0.0})


@contextmanager
def local_services(settings: Settings | None = None, executor: Executor | None = None) -> Iterator[Services]:
    """The service's Services opened in this process (default: `cli_settings`; a local pool unless an
    ``executor`` is given), closed on exit."""
    services = open_services(settings or cli_settings(), executor=executor)
    try:
        yield services
    finally:
        services.close()


# -- flights -----------------------------------------------------------------------------------------------
def flight_files(paths) -> list[Path]:
    """The given files plus the sidecars their readers would use: for a NanoBench CSV the *_metadata.yaml
    next to it, for a uSD log logNNN crazyswarm2's infoNNN.yaml."""
    files: dict[Path, Path] = {}
    for path in map(Path, paths):
        existing_file(path, "flight log")
        files.setdefault(path.resolve(), path)
        sidecar = path.with_name(f"{path.stem}_metadata.yaml")
        if path.suffix.lower() == ".csv" and sidecar.is_file():
            files.setdefault(sidecar.resolve(), sidecar)
        info = info_sidecar(path)
        if info is not None:
            files.setdefault(info.resolve(), info)
    return list(files.values())


def add_flight(services: Services, paths, *, pose_topic: str | None = None,
               imu_topic: str | None = None, cut: str | None = None) -> tuple[FlightRecord, bool]:
    """Store the log file(s) of one flight exactly as an upload would (with the topics chosen, for MCAP
    recordings and ROS bags, and the cut, `learnest.ingest.align.parse_cut`).  -> (row, created); created is
    False when the same content was stored before (its existing row)."""
    with ExitStack() as stack:
        uploads = [LocalFile(path.name, stack.enter_context(open(path, "rb"))) for path in flight_files(paths)]
        return add_uploaded_flight(services.db, services.blobs, uploads, pose_topic=pose_topic, imu_topic=imu_topic,
                                   cut=cut)


# -- training ----------------------------------------------------------------------------------------------
class UnreadableFile(InvalidInput):
    """``train(..., strict=True)``: a given file could not be read, so nothing was trained (the message names
    the file and why; `learnest train --strict` exits with status 1 on it)."""


def train(paths, name: str, *, epochs: int | None = None, include_bad: bool = False,
          progress: Callable[[float], None] | None = None, settings: Settings | None = None,
          system: str = "quadrotor", pose_topic: str | None = None, imu_topic: str | None = None,
          cut: str | None = None, on_stage: Callable[[str, float | None], None] | None = None,
          validate=None, strict: bool = False) -> dict:
    """Store the flights, train the next version of `name` on them and wait; `progress(fraction)` while it
    trains, `on_stage(stage, seconds_left)` as the job's stage changes ("ingest", "observer ...", "epoch 12/150").

    ``paths`` are the log files of one flight or of several, or folders of them (`learnest.ingest.collect_logs`,
    grouped into flights by `learnest.ingest.group_files`); several flights train one model of one vehicle
    (`service.jobs.training.start_training`), ``validate`` names log files of flights held out whole (default:
    one flight in five).  A file that cannot be read (unknown format, a missing channel, cut short) is listed
    in ``errors`` and the model is trained on the others; with ``strict`` it is an `UnreadableFile` instead,
    raised before any training.  Of several flights, those failing the quality checks are left out and listed
    (``skipped_flights``) unless ``include_bad``; one such flight alone is refused.
    ``cut``: the stretch of the log to keep (`learnest.ingest.align.parse_cut`).
    Returns what `learnest train --json` prints: ``seconds`` is the epochs' time, ``total_seconds`` the
    job's (observer, epochs, storing), ``training_flights`` and ``validation_flights`` the names, ``learned``
    False when no epoch beat the prior on the held-out data (``learned_note`` says so in words), ``errors``
    ``[{"file", "message"}]`` the files left out because they could not be read."""
    registry.check_name(name)  # before any work
    settings = settings or cli_settings()
    if on_stage:
        on_stage("ingest", None)
    groups, errors = _log_groups(paths, strict)
    held_groups, held_errors = _log_groups(validate, strict) if validate else ([], [])
    errors += held_errors
    if not groups and not held_groups:
        raise InvalidInput(_nothing_read("no flight log among the given files", errors))
    read = {"pose_topic": pose_topic, "imu_topic": imu_topic, "cut": cut}
    with local_services(settings) as services:
        stored = _store_groups(services, groups, errors, strict, read)
        held = [row for row, _ in _store_groups(services, held_groups, errors, strict, read)]
        if not stored and not held:
            raise InvalidInput(_nothing_read("no flight could be read", errors))
        rows, held, skipped = _quality_filter(list({row.id: row for row, _ in stored}.values()), held, include_bad)
        for row in rows + held:   # before a worker starts: a missing channel is said at once
            _check_inputs(services, row, system)
        job, version = _run_training(services, name, rows, held, {"epochs": epochs, "system": system},
                                     include_bad, progress, on_stage)
    return {**_trained_json(version, job, settings), "skipped_flights": skipped, "errors": errors,
            "flight_stored": "new" if any(created for _, created in stored) else "existing"}


def _log_groups(paths, strict: bool) -> tuple[list, list[dict]]:
    """The flights among ``paths`` (files or folders) as `learnest.ingest.group_files` groups them, and the
    files that cannot be one (``[{"file", "message"}]``); with ``strict`` the first of those is raised."""
    from learnest.ingest import IngestError, collect_logs

    logs, errors = [], []
    for path in paths:
        try:
            logs += collect_logs([path])[0]
        except IngestError as err:
            errors.append({"file": err.path, "message": err.problem})
    groups, unreadable = _readable_groups(logs)
    errors += unreadable
    if strict and errors:
        raise UnreadableFile(f"{errors[0]['file']}: not read: {errors[0]['message']}")
    return groups, errors


def _store_groups(services: Services, groups: list, errors: list[dict], strict: bool,
                  read: dict) -> list[tuple[FlightRecord, bool]]:
    """Store each group as `add_flight` does -> [(row, created)]; a group that cannot be read is appended to
    ``errors`` (raised as `UnreadableFile` with ``strict``) and the others are stored."""
    stored = []
    for _, files in groups:
        try:
            stored.append(add_flight(services, files, **read))
        except InvalidInput as err:
            message = str(err).removeprefix(f"{Path(files[0]).name}: ")   # the upload's message names the file
            if strict:
                raise UnreadableFile(f"{files[0]}: not read: {message}") from None
            errors.append({"file": str(files[0]), "message": message})
    return stored


def _nothing_read(what: str, errors: list[dict]) -> str:
    return what + "".join(f"; {e['file']}: {e['message']}" for e in errors)


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
            "total_seconds": (job.result or {}).get("total_seconds"), "home": str(settings.home)}


def _check_inputs(services: Services, row, system: str) -> None:
    """MissingInputs (naming the flight and the channels) when the stored flight lacks the prior's inputs."""
    from learnest.ingest.flight import Flight
    from learnest.models.inputs import MissingInputs, missing_inputs

    if system == "quadrotor":
        return
    lacking = missing_inputs(Flight.from_bytes(services.blobs.read_bytes(row.flight_blob)), system)
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


def wait_for_job(services: Services, job_id: int, progress: Callable[[float], None] | None = None,
                 poll_s: float = 0.25, on_stage: Callable[[str, float | None], None] | None = None) -> Job:
    """Poll the job row (the worker writes its progress, stage and ETA there) until it is finished."""
    while True:
        job = catalog.get_job(services.db, job_id)
        if progress:
            progress(job.progress)
        if on_stage and job.state in ACTIVE:
            on_stage(job.stage or "starting a worker", seconds_left(job))
        if job.state not in ACTIVE:
            return job
        time.sleep(poll_s)


@contextmanager
def watching_stages(services: Services, on_stage: Callable[[str, float | None], None] | None,
                    poll_s: float = 0.25, progress: Callable[[float], None] | None = None) -> Iterator[None]:
    """While the block runs, call ``on_stage(stage, seconds_left)`` whenever the stage of this process's
    running job changes (a job run here and now, whose worker writes its stage to the database), and
    ``progress(fraction)`` whenever its progress does."""
    if on_stage is None and progress is None:
        yield
        return
    stop = threading.Event()

    def watch() -> None:
        seen, fraction = None, None
        while not stop.wait(poll_s):
            with services.db.transaction() as session:
                job = session.scalar(select(Job).where(Job.owner == services.runner.owner, Job.state == "running")
                                     .order_by(Job.id.desc()).limit(1))
            if job is None:
                continue
            if progress is not None and job.progress != fraction:
                fraction = job.progress
                progress(job.progress)
                seen = None   # the stage is said again with the new fraction: both from this one read
            if on_stage is not None and job.stage and (job.stage, job.eta_s) != seen:
                seen = (job.stage, job.eta_s)
                on_stage(job.stage, seconds_left(job))

    thread = threading.Thread(target=watch, name="learnest-stages", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join()


# -- evaluation ----------------------------------------------------------------------------------------------
def evaluate(paths, model_ref: str, estimator_settings: EstimatorSettings, *, pose_topic: str | None = None,
             imu_topic: str | None = None, progress: Callable[[float], None] | None = None,
             settings: Settings | None = None, on_stage: Callable[[str, float | None], None] | None = None,
             cut: str | None = None) -> dict:
    """Store the flights of ``paths`` (grouped as `learnest.ingest.group_files` does; stored ones are found
    by content) and evaluate ``model_ref`` on them as an evaluation job run in this process.  A file that
    cannot be read is listed in ``errors`` and the others are stored and evaluated.

    Returns
    -------
    dict
        The stored evaluation's report (``flight_id`` and ``sha256`` per flight, ``units``) plus
        ``evaluation_id``, ``job_id``, ``stored`` (per flight: ``file``, ``flight_id``, ``name``, ``stored``
        "new" or "existing") and ``errors`` (``[{"file", "message"}]``: what could not be read).

    Raises
    ------
    LearnestError
        No file can be read, the reference names nothing usable, or the job failed.
    """
    settings = settings or cli_settings()
    groups, errors = _readable_groups(paths)   # sniffs the formats only: bad files are named before anything is stored
    with local_services(settings, executor=InlineExecutor()) as services:
        ids, stored = [], []
        for k, (_, files) in enumerate(groups, start=1):
            if on_stage:
                on_stage(f"ingest {k}/{len(groups)}", None)
            try:
                row, created = add_flight(services, files, pose_topic=pose_topic, imu_topic=imu_topic, cut=cut)
            except InvalidInput as err:
                errors.append({"file": str(files[0]), "message": str(err)})
                continue
            ids.append(row.id)
            stored.append({"file": str(files[0]), "flight_id": row.id, "name": row.name,
                           "stored": "new" if created else "existing"})
        if not ids:
            raise InvalidInput("no flight could be read: " + "; ".join(f"{e['file']}: {e['message']}" for e in errors))
        # interrupted (Ctrl-C), the job is failed by the runner's shutdown when the services close; the
        # progress shown is the job row's own (flights done of all, cached ones included), never a count
        # of progress calls
        with watching_stages(services, on_stage, progress=progress):
            job_id, evaluation_id, _ = start_evaluation(services, model_ref, ids, estimator_settings, wait=True)
        job = catalog.get_job(services.db, job_id)
        if job.state != "succeeded":
            raise Conflict(f"evaluation {evaluation_id} {job.state}: {job.error}")
        evaluation, _ = catalog.row_and_job(services.db, Evaluation, evaluation_id, "evaluation")
    return {**(evaluation.report or {}), "evaluation_id": evaluation_id, "job_id": job_id, "stored": stored,
            "errors": errors}


def _readable_groups(paths) -> tuple[list, list[dict]]:
    """The flights among ``paths`` as `learnest.ingest.group_files` groups them, leaving out (and listing) the
    files no adapter recognises or that lack their pair: ``(groups, [{"file", "message"}])``."""
    from learnest.ingest import IngestError, detect, group_files

    errors, readable = [], []
    for path in map(Path, paths):
        try:
            detect(path)
            readable.append(path)
        except IngestError as err:
            errors.append({"file": err.path, "message": err.problem})
    while readable:
        try:
            return group_files(readable), errors
        except IngestError as err:
            remaining = [path for path in readable if str(path) != err.path]
            errors.append({"file": err.path, "message": err.problem})
            readable = remaining if len(remaining) < len(readable) else []
    return [], errors


def export(evaluation_id: int, path: str | Path, fmt: str, flight_id: int | None = None,
           settings: Settings | None = None) -> list:
    """Write evaluation ``evaluation_id``'s state estimates to ``path`` as ``fmt`` (service.operations.exports);
    returns the `FlightEstimates` written.  NotFound when there is no registry yet or no such evaluation."""
    from ..operations.exports import export_evaluation

    settings = settings or cli_settings()
    if settings.database_url is None and not (settings.home / "learnest.db").is_file():
        raise NotFound(f"evaluation {evaluation_id} not found: nothing is stored under {settings.home} "
                       "(LEARNEST_HOME)")
    database = Database(settings.url)
    try:
        database.require_current_schema()
        return export_evaluation(database, BlobStore(settings.home / "blobs"), evaluation_id, path, fmt, flight_id)
    finally:
        database.dispose()


# -- diagnosis -----------------------------------------------------------------------------------------------
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


# -- loading -----------------------------------------------------------------------------------------------
def load_model(ref: str, settings: Settings | None = None) -> HybridModel:
    """The model a reference names.

    Raises
    ------
    InvalidInput
        `ref` does not parse.
    NotFound, Conflict
        It names nothing usable (no such model/version/alias, not ready, no database yet, an older
        schema); the message lists the registered models (except when there is no database).
    """
    parsed = registry.parse_ref(ref)  # InvalidInput (a ValueError) says which forms are accepted
    settings = settings or Settings()
    # no database yet: say so instead of creating an empty one (Settings.url puts SQLite at home/learnest.db)
    if settings.database_url is None and not (settings.home / "learnest.db").is_file():
        raise NotFound(f"no model {ref!r}: nothing is registered under {settings.home} (LEARNEST_HOME); "
                         "`learnest train FILE... --name NAME` registers one")
    try:
        return registry.load_model_ref(str(parsed), settings)
    except (NotFound, Conflict) as err:
        raise type(err)(f"{err} (registered models: {', '.join(known_models(settings)) or 'none'})") from None


def known_models(settings: Settings) -> list[str]:
    """Names of every registered model in the database `settings` points to, sorted."""
    database = Database(settings.url)
    try:
        with database.transaction() as session:
            return list(session.scalars(select(RegisteredModel.name).order_by(RegisteredModel.name)))
    finally:
        database.dispose()


# -- browsing the registry (learnest flights list, models list|show, alias set) ----------------------------------
@contextmanager
def registry_database(settings: Settings | None = None) -> Iterator[Database]:
    """The registry's database for reading (or a small write such as an alias), never migrated; NotFound when
    nothing is stored under LEARNEST_HOME yet, Conflict when its schema is older than this learnest."""
    settings = settings or cli_settings()
    if settings.database_url is None and not (settings.home / "learnest.db").is_file():
        raise NotFound(f"nothing is stored under {settings.home} (LEARNEST_HOME) yet: `learnest train`, "
                       "`learnest evaluate` or `learnest serve` store flights and models there")
    database = Database(settings.url)
    try:
        database.require_current_schema()
        yield database
    finally:
        database.dispose()


def list_flights(q: str | None = None, limit: int = 1000, settings: Settings | None = None) -> dict:
    """{"items": [...], "total"}: the stored flights by id (those whose name contains ``q``)."""
    with registry_database(settings) as db:
        total, rows = catalog.list_flights(db, *catalog.name_contains(q), limit=limit)
    return {"total": total, "items": [{
        "id": r.id, "name": r.name, "adapter": r.adapter, "vehicle": r.vehicle, "duration_s": r.duration_s,
        "rate_hz": r.rate_hz, "samples": r.samples, "quality": r.quality, "sha256": r.sha256,
        "created_at": r.created_at.isoformat()} for r in rows]}


def list_models(q: str | None = None, settings: Settings | None = None) -> dict:
    """{"items": [...], "total"}: the registered models by name (those whose name contains ``q``)."""
    with registry_database(settings) as db:
        models = catalog.list_models(db, q=q)
    return {"total": len(models), "items": [{
        "name": m.model.name, "versions": m.version_count, "latest_version": m.latest_version,
        "aliases": m.aliases, "created_at": m.model.created_at.isoformat()} for m in models]}


def show_model(ref: str, settings: Settings | None = None) -> dict:
    """"NAME": the model with its versions and aliases; "NAME:N" or "NAME@ALIAS": that version with its
    hyperparameters, metrics, timing, lineage and evaluations (service.operations.comparison.version_lineage)."""
    from ..operations.comparison import version_lineage
    from ..storage.references import parse_ref

    parsed = parse_ref(ref)
    with registry_database(settings) as db:
        if parsed.version is None and parsed.alias is None:
            detail = catalog.get_model(db, parsed.name)
            return {"name": parsed.name, "aliases": detail.aliases, "latest_version": detail.latest_version,
                    "versions": [_version_json(v, detail.aliases) for v in detail.versions]}
        with db.transaction() as session:
            row = registry.get_version(session, parsed.name, parsed.version) if parsed.version is not None \
                else registry.resolve(session, parsed)
            aliases = registry.aliases_of(session, parsed.name)
        lineage = version_lineage(db, row.name, row.version)
    lineage["evaluations"] = [{**e, "created_at": e["created_at"].isoformat()} for e in lineage["evaluations"]]
    return {**_version_json(row, aliases), "prior": row.prior, "code_version": row.code_version,
            "lineage": lineage}


def _version_json(row, aliases: dict[str, int]) -> dict:
    return {"ref": f"{row.name}:{row.version}", "name": row.name, "version": row.version, "status": row.status,
            "error": row.error, "aliases": sorted(a for a, v in aliases.items() if v == row.version),
            "training_flight": {"id": row.training_flight_id, "name": row.training_flight_name},
            "training_flights": registry.training_flights_of(row),
            "validation_flights": list(row.validation_flights or []),
            "learned": (row.metrics or {}).get("learned"), "learned_note": (row.metrics or {}).get("learned_note"),
            "parent": row.parent, "hyperparameters": row.hyperparameters, "metrics": row.metrics,
            "training_seconds": row.training_seconds, "created_at": row.created_at.isoformat()}


def set_alias(name: str, version: int, alias: str, settings: Settings | None = None) -> dict:
    """Point NAME@ALIAS at VERSION (as PUT /models/{name}/aliases/{alias}); returns what it did, with the
    version the alias pointed at before (None if it is new)."""
    with registry_database(settings) as db:
        with db.transaction() as session:
            before = registry.aliases_of(session, name).get(alias)
            registry.set_alias(session, name, alias, version)
    return {"name": name, "alias": alias, "version": version, "previous_version": before}
