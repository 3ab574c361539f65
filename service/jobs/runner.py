"""Jobs: long work behind `202 Accepted`.

A job row (queued -> running -> succeeded | failed, progress 0..1) is created in the request's transaction;
a thread of this server process (the JobRunner) then orchestrates it, sending the heavy parts (training,
each flight of an evaluation) to the Executor.  Progress is written to the database, by the orchestrating
thread or, for training, by the worker itself (`report_progress`).

Ownership: every job row names the server process that runs it, and each process holds a lease
"runner:<owner>" renewed every HEARTBEAT_S.  A job whose owner has no live lease (or, on this host, a dead
pid) was left behind by a crashed server: `sweep` marks it failed with "server restarted" (at start-up
and on every heartbeat, so several uvicorn workers never fail each other's live jobs).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

from sqlalchemy import select, update
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from learnest.errors import InvalidInput, NotFound
from learnest.ingest.flight import json_compatible
from learnest.models.knode import HybridModel
from learnest.models.presets import CRAZYFLIE_TRAINING, METHODS, MHE_HORIZON

from . import registry
from .blobs import BlobStore
from .config import Settings
from .db import (
    Database,
    Diagnosis,
    Evaluation,
    FlightRecord,
    Job,
    Lease,
    ModelVersion,
    Result,
    acquire_lease,
    blob_is_referenced,
    dml_rowcount,
    get_row,
    referenced_blobs,
    release_lease,
    utcnow,
)
from .executors import Executor, init_worker, make_executor

log = logging.getLogger("learnest.jobs")

ACTIVE = ("queued", "running")
HEARTBEAT_S = 10.0
LEASE_S = 30.0
ERROR_CHARS = 1000


class JobAborted(RuntimeError):
    """The job is no longer running (a sweep or shutdown failed it): drop its result."""


# -- the runner ---------------------------------------------------------------------------------------
def make_owner_id() -> str:
    """"host:pid:random8": names this server process as the owner of the jobs it runs."""
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


@dataclass
class JobContext:
    """What a job's work function gets: progress reporting and the transactional completion."""

    job_id: int
    runner: JobRunner
    on_progress: Callable[[], object] | None = None   # e.g. the scheduler renewing its lease
    completed: bool = False

    def progress(self, fraction: float) -> None:
        """Record progress (clipped to 0..1) of a running job and call ``on_progress``."""
        self.runner.set_progress(self.job_id, fraction)
        if self.on_progress:
            self.on_progress()

    @property
    def progress_target(self) -> tuple[str, int]:
        """(database URL, job id): lets a worker process write its own progress."""
        return self.runner.db.url, self.job_id

    def complete(self, session: Session, result: dict) -> None:
        """Mark the job succeeded inside the caller's transaction (with the rows its result created)."""
        self.runner.mark_succeeded(session, self.job_id, result)
        self.completed = True


class JobRunner:
    """Runs this server process's jobs in a thread pool and keeps its lease (module docstring).

    Parameters
    ----------
    db : Database
    threads : int
        Jobs orchestrated at once; the heavy parts go to the Executor.

    Attributes
    ----------
    owner : str
        This process's owner id (`make_owner_id`).
    on_stale : list of callable
        Hooks ``hook(session, job_ids, reason)`` called in the transaction that fails jobs (sweep, shutdown).
    """

    def __init__(self, db: Database, threads: int = 4) -> None:
        self.db = db
        self.owner = make_owner_id()
        self._threads = ThreadPoolExecutor(threads, thread_name_prefix="learnest-job")
        self._stop = threading.Event()
        self._heartbeat: threading.Thread | None = None
        # called in the sweep's transaction with the ids of the jobs it failed and the reason
        self.on_stale: list[Callable[[Session, list[int], str], None]] = []

    @property
    def lease_name(self) -> str:
        """"runner:<owner>", the lease this process renews every HEARTBEAT_S."""
        return f"runner:{self.owner}"

    def start(self) -> list[int]:
        """Take the lease, fail the jobs of stopped servers (`sweep`) and start the heartbeat thread.
        Returns the ids of the jobs failed."""
        acquire_lease(self.db, self.lease_name, self.owner, LEASE_S)
        stale = self.sweep()
        self._heartbeat = threading.Thread(target=self._beat, name="learnest-heartbeat", daemon=True)
        self._heartbeat.start()
        return stale

    def _beat(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            try:
                acquire_lease(self.db, self.lease_name, self.owner, LEASE_S)
                self.sweep()
            except Exception:  # a database hiccup must not kill the heartbeat
                log.exception("job heartbeat failed")

    def shutdown(self) -> None:
        """Stop the heartbeat, cancel queued threads, fail this owner's active jobs and release the lease."""
        self._stop.set()
        self._threads.shutdown(wait=False, cancel_futures=True)
        reason = "server stopped before the job finished"
        with self.db.transaction() as session:
            ids = self._fail(session, select(Job).where(Job.owner == self.owner, Job.state.in_(ACTIVE)), reason)
            for hook in self.on_stale:
                hook(session, ids, reason)
        release_lease(self.db, self.lease_name, self.owner)

    # -- state changes ------------------------------------------------------------------------------------
    def create(self, session: Session, kind: str, payload: dict | None = None) -> Job:
        """Add a queued job row owned by this process (flushed, so it has an id) in the caller's transaction."""
        job = Job(kind=kind, state="queued", progress=0.0, payload=payload, owner=self.owner, created_at=utcnow())
        session.add(job)
        session.flush()
        return job

    def launch(self, job_id: int, work: Callable[[JobContext], dict | None],
               on_failure: Callable[[Session, str], None] | None = None) -> Future:
        """Run the job in a background thread of this process."""
        return self._threads.submit(self.run, job_id, work, on_failure)

    def run(self, job_id: int, work: Callable[[JobContext], dict | None],
            on_failure: Callable[[Session, str], None] | None = None,
            on_progress: Callable[[], object] | None = None) -> None:
        """Run the job here and now (the scheduler and the CLI call this directly).

        Does nothing unless the job is still queued.  ``work``'s result completes the job unless it did so
        itself (`JobContext.complete`); an exception fails it with its message and calls ``on_failure``.
        """
        if not self._mark_running(job_id):
            return
        context = JobContext(job_id, self, on_progress)
        try:
            result = work(context)
            if not context.completed:
                with self.db.transaction() as session:
                    context.complete(session, result or {})
        except JobAborted:
            log.info("job %s was failed while running; its result is dropped", job_id)
        except Exception as err:  # recorded on the job: no traceback reaches a user, the log keeps it
            log.exception("job %s failed", job_id)
            self.mark_failed(job_id, _message(err), on_failure)

    def _mark_running(self, job_id: int) -> bool:
        with self.db.transaction() as session:
            return bool(dml_rowcount(session.execute(update(Job).where(Job.id == job_id, Job.state == "queued")
                                                     .values(state="running", started_at=utcnow()))))

    def mark_succeeded(self, session: Session, job_id: int, result: dict) -> None:
        """Set a running job succeeded with ``result`` in the caller's transaction; `JobAborted` if it is
        no longer running."""
        job = session.get(Job, job_id, with_for_update=True)
        if job is None or job.state != "running":
            raise JobAborted(job_id)
        job.state, job.progress, job.result, job.finished_at = "succeeded", 1.0, result, utcnow()

    def mark_failed(self, job_id: int, message: str, on_failure: Callable[[Session, str], None] | None = None) -> None:
        """Fail an active job with ``message`` and call ``on_failure(session, message)``; no-op otherwise."""
        with self.db.transaction() as session:
            job = session.get(Job, job_id, with_for_update=True)
            if job is None or job.state not in ACTIVE:
                return
            job.state, job.error, job.finished_at = "failed", message, utcnow()
            if on_failure:
                on_failure(session, message)

    def set_progress(self, job_id: int, fraction: float) -> None:
        """Write a running job's progress, clipped to 0..1."""
        with self.db.transaction() as session:
            session.execute(update(Job).where(Job.id == job_id, Job.state == "running")
                            .values(progress=max(0.0, min(1.0, float(fraction)))))

    # -- crashed servers ----------------------------------------------------------------------------------
    def sweep(self, reason: str = "server restarted") -> list[int]:
        """Fail the queued/running jobs whose server process is gone."""
        now = time.time()
        with self.db.transaction() as session:
            live = {lease.name.split(":", 1)[1] for lease in
                    session.scalars(select(Lease).where(Lease.name.like("runner:%"), Lease.expires_at >= now))}
            jobs = session.scalars(select(Job).where(Job.state.in_(ACTIVE))).all()
            stale = [job for job in jobs if job.owner != self.owner
                     and (job.owner not in live or _dead_here(job.owner))]
            for job in stale:
                job.state, job.error, job.finished_at = "failed", reason, utcnow()
            ids = [job.id for job in stale]
            for hook in self.on_stale:
                hook(session, ids, reason)
        if ids:
            log.warning("marked %d job(s) left by a stopped server as failed: %s", len(ids), ids)
        return ids

    @staticmethod
    def _fail(session: Session, query, reason: str) -> list[int]:
        jobs = session.scalars(query).all()
        for job in jobs:
            job.state, job.error, job.finished_at = "failed", reason, utcnow()
        return [job.id for job in jobs]


def _dead_here(owner: str | None) -> bool:
    """An owner on this host whose process no longer exists (a restart within the lease time)."""
    try:
        host, pid, _ = (owner or "").rsplit(":", 2)
        if host != socket.gethostname():
            return False
        os.kill(int(pid), 0)
        return False
    except ProcessLookupError:
        return True
    except (ValueError, PermissionError):
        return False


def _message(err: BaseException) -> str:
    text = str(err) or type(err).__name__
    if not isinstance(err, (ValueError, LookupError)):  # unexpected: name the kind of failure
        text = f"{type(err).__name__}: {text}"
    return text[:ERROR_CHARS]


# -- the services a job needs --------------------------------------------------------------------------
@dataclass
class Services:
    """What a job needs, opened once per process (`open_services`)."""

    settings: Settings
    db: Database
    blobs: BlobStore
    executor: Executor
    runner: JobRunner
    owns_executor: bool = True

    def close(self) -> None:
        """Shut the runner down, the executor too if these services created it, and dispose the database."""
        self.runner.shutdown()
        if self.owns_executor:
            self.executor.shutdown()
        self.db.dispose()


def open_services(settings: Settings, executor: Executor | None = None) -> Services:
    """Migrate the database, open the blob folder and the executor, fail jobs of crashed servers."""
    settings.home.mkdir(parents=True, exist_ok=True)
    db = Database(settings.url)
    db.migrate()
    blobs = BlobStore(settings.home / "blobs")
    runner = JobRunner(db)
    runner.on_stale.append(registry.fail_versions_of_jobs)
    runner.start()
    owns = executor is None
    executor = executor or make_executor(settings.dask_address, settings.pool_workers)
    return Services(settings, db, blobs, executor, runner, owns_executor=owns)


def sweep_orphan_blobs(db: Database, blobs: BlobStore) -> list[str]:
    """Delete blobs no row names: a crash between a blob's write and its row's commit leaves one behind.
    Safe beside a running server: writers hold the store's shared lock until their row is committed,
    and `collect` checks each candidate again under the exclusive lock."""
    referenced = referenced_blobs(db)
    removed = blobs.collect([sha for sha in blobs.all_blobs() if sha not in referenced],
                            lambda sha: blob_is_referenced(db, sha))
    if removed:
        log.warning("removed %d orphaned blob(s) left by an interrupted write", len(removed))
    return removed


# -- worker-side tasks (run in executor processes / Dask workers) --------------------------------------
_worker_databases: dict[str, Database] = {}
PROGRESS_EVERY_S = 1.0


def report_progress(target: tuple[str, int] | None, fraction: float) -> None:
    """Write a job's progress from a worker; best effort (a remote Dask worker may not reach the DB)."""
    if target is None:
        return
    url, job_id = target
    try:
        database = _worker_databases.get(url) or _worker_databases.setdefault(url, Database(url))
        with database.transaction() as session:
            session.execute(update(Job).where(Job.id == job_id, Job.state == "running")
                            .values(progress=max(0.0, min(1.0, fraction))))
    except Exception:
        log.debug("progress of job %s not written", job_id, exc_info=True)


def train_task(flight_bytes: bytes, config: dict, progress_target: tuple[str, int] | None = None,
               meta: dict | None = None) -> dict:
    """Algorithm 1 on one flight (service.experiments.flights.train_on_flight); the model comes back as JSON.

    ``config`` holds `TrainingConfig`'s fields; ``meta`` is added to the model's meta.  Returns
    ``model_json``, ``losses``, ``seconds``, ``library_versions``, ``code_version`` and ``metrics``.
    The worker exits if its parent process dies.
    """
    from learnest.models.training import TrainingConfig

    from .experiments.flights import train_on_flight

    init_worker()
    last, parent = [0.0], os.getppid()

    def on_epoch(epoch: int, _loss: float) -> None:
        if os.getppid() != parent:  # the server died: an orphaned worker must not train on for hours
            os._exit(1)             # (and nobody is left to read an exception)
        if time.monotonic() - last[0] >= PROGRESS_EVERY_S:
            last[0] = time.monotonic()
            report_progress(progress_target, 0.99 * (epoch + 1) / config["epochs"])

    hyper = dict(config)
    system = hyper.pop("system", "quadrotor")
    result = train_on_flight(_flight_from_bytes(flight_bytes), TrainingConfig(**hyper), progress=on_epoch,
                             system=system)
    model = result.model
    model.meta.update(meta or {})
    return {"model_json": registry.model_to_json(model), "losses": [float(x) for x in result.losses],
            "seconds": float(result.seconds), "library_versions": registry.library_versions(),
            "code_version": registry.code_version(),
            "metrics": training_metrics(model)}


def _flight_from_bytes(data: bytes):
    from learnest.ingest.flight import Flight as CanonicalFlight

    try:
        return CanonicalFlight.from_bytes(data)
    except (OSError, ValueError, KeyError) as err:
        raise InvalidInput(f"the stored normalized flight is unreadable ({type(err).__name__})") from None


def evaluate_task(model_json: bytes, flight_bytes: bytes, settings: dict) -> dict:
    """One flight's entry of service.experiments.flights.evaluate_flights' report.

    ``settings`` is `EstimatorSettings.as_dict()`.
    """
    from .experiments.flights import evaluate_flights

    init_worker()
    model = registry.model_from_json(model_json)
    flight = _flight_from_bytes(flight_bytes)
    report = evaluate_flights(model, [flight], list(settings["methods"]), include_bad=settings["include_bad"],
                              horizon=settings["horizon"])
    return report["flights"][0]


# -- training jobs -------------------------------------------------------------------------------------
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
        For a bad name, or a flight that failed the quality checks without ``include_bad``.
    NotFound
        If the flight or the parent does not exist.
    Conflict
        If the parent version is not ready.
    """
    registry.check_name(name)
    with services.db.transaction() as session:
        flight = _flight(session, flight_id)
        if not flight.quality_ok and not include_bad:
            raise InvalidInput(f"flight {flight_id} ({flight.name}) failed the quality checks "
                          f"({'; '.join(flight.quality.get('issues', []))}); pass include_bad to train on it anyway")
        if parent is not None:
            resolved = registry.resolve(session, parent)
            parent = f"{resolved.name}:{resolved.version}"
    config = training_config(overrides)
    for attempt in range(20):  # another request may take the same version number first
        try:
            with services.db.transaction() as session:
                flight = _flight(session, flight_id)
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
    """The training job's work: train on the executor, store the weights, mark the version ready."""
    with services.db.transaction() as session:
        version = get_row(session, ModelVersion, version_id, "model version")
        flight = session.get(FlightRecord, version.training_flight_id)
        if flight is None:
            raise InvalidInput(f"training flight {version.training_flight_id} was deleted")
        meta = {"name": version.name, "version": version.version, "training_flight_id": flight.id}
        config, blob = dict(version.hyperparameters), flight.flight_blob
    out = services.executor.submit(train_task, services.blobs.read_bytes(blob), config, ctx.progress_target,
                                   meta).result()
    with services.blobs.writing():  # the weights blob exists before the row that names it commits
        weights = services.blobs.put_bytes(out["model_json"])
        with services.db.transaction() as session:
            version = get_row(session, ModelVersion, version_id, "model version", for_update=True)
            version.status, version.weights_blob, version.ready_at = "ready", weights, utcnow()
            version.prior = registry.prior_of(out["model_json"])
            version.losses, version.training_seconds = out["losses"], out["seconds"]
            version.metrics, version.code_version = out["metrics"], out["code_version"]
            version.library_versions = out["library_versions"]
            ctx.complete(session, {"name": version.name, "version": version.version,
                                   "final_loss": out["losses"][-1] if out["losses"] else None,
                                   "seconds": out["seconds"]})


def _fail_version(session: Session, version_id: int, message: str) -> None:
    version = session.get(ModelVersion, version_id)
    if version is not None and version.status == "training":
        version.status, version.error = "failed", message


def _flight(session: Session, flight_id: int) -> FlightRecord:
    flight = session.get(FlightRecord, flight_id)
    if flight is None:
        raise NotFound(f"flight {flight_id} not found")
    return flight


# -- evaluation jobs -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class EstimatorSettings:
    """Settings of an evaluation that change a flight's result (part of the result cache key).

    Attributes
    ----------
    methods : tuple of str
        Estimators to run.
    horizon : int
        MHE window N, samples.
    include_bad : bool
        Also score flights that failed the quality checks.
    """

    methods: tuple[str, ...] = METHODS
    horizon: int = MHE_HORIZON
    include_bad: bool = False

    def as_dict(self) -> dict:
        """The fields as JSON-able values."""
        return {"methods": list(self.methods), "horizon": self.horizon, "include_bad": self.include_bad}

    @property
    def key(self) -> str:
        """Cache key part: what changes a flight's entry besides the flight and the model."""
        canonical = json.dumps({"methods": sorted(self.methods), "horizon": self.horizon,
                                "include_bad": self.include_bad}, sort_keys=True)
        return hashlib.sha256(canonical.encode()).hexdigest()


def start_evaluation(services: Services, model_ref: str, flights: Iterable[int] | str, settings: EstimatorSettings,
                     wait: bool = False, on_progress: Callable[[], object] | None = None) -> tuple[int, int, str]:
    """Create the evaluation and its job; answer from the cache at once when every flight has a result,
    otherwise run it (in the background, or here when wait=True).  -> (job id, evaluation id, state)

    ``flights`` is a list of flight ids or ``"all-other"`` (every stored flight but the training one).
    """
    with services.db.transaction() as session:
        version = registry.resolve(session, model_ref)
        flight_ids = _flight_ids(session, flights, version)
        job = services.runner.create(session, "evaluation", {"model": model_ref, "flights": flight_ids,
                                                             "settings": settings.as_dict()})
        evaluation = Evaluation(job_id=job.id, model_ref=f"{version.name}:{version.version}",
                                model_version_id=version.id, flight_ids=flight_ids,
                                settings=settings.as_dict(), created_at=utcnow())
        session.add(evaluation)
        session.flush()
        by_id = _flights_by_id(session, flight_ids)
        shas = [by_id[i].sha256 for i in flight_ids]
        entries = cached_entries(session, version.id, settings.key, shas)
        if len(entries) == len(flight_ids):  # everything cached: no job to run
            evaluation.report = assemble_report(evaluation.model_ref, [entries[sha] for sha in shas])
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


def run_evaluation(services: Services, ctx: JobContext, evaluation_id: int) -> None:
    """The evaluation job's work: one executor task per flight without a cached result, each stored as
    it finishes (a failed flight is recorded and does not stop the others), then the report."""
    with services.db.transaction() as session:
        evaluation = get_row(session, Evaluation, evaluation_id, "evaluation")
        version = get_row(session, ModelVersion, evaluation.model_version_id, "model version")
        settings = EstimatorSettings(tuple(evaluation.settings["methods"]), evaluation.settings["horizon"],
                                     evaluation.settings["include_bad"])
        flights = _flights_by_id(session, evaluation.flight_ids)
        entries = cached_entries(session, version.id, settings.key, [f.sha256 for f in flights.values()])
        model_json = services.blobs.read_bytes(registry.weights_of(version))
        todo = {f.id: (f.name, f.sha256, f.flight_blob) for f in flights.values() if f.sha256 not in entries}
        order = [flights[i].sha256 if i in flights else None for i in evaluation.flight_ids]
        model_ref, version_id, flight_ids = evaluation.model_ref, version.id, list(evaluation.flight_ids)

    total, done, failed = len(flight_ids), len(flight_ids) - len(todo), 0
    futures = {}
    for flight_id, (name, sha, blob) in todo.items():
        try:
            flight_bytes = services.blobs.read_bytes(blob)
        except FileNotFoundError:  # deleted while this job was starting
            entries[sha], done = _missing_entry(flight_id), done + 1
            continue
        futures[services.executor.submit(evaluate_task, model_json, flight_bytes, settings.as_dict())] = \
            (flight_id, name, sha)
    for future in services.executor.as_completed(futures):
        flight_id, name, sha = futures[future]
        entry, error = _outcome(future, name)
        failed += error is not None
        store_result(services.db, sha, version_id, settings.key, flight_id, entry, error)
        entries[sha] = entry
        done += 1
        ctx.progress(done / total)

    report = assemble_report(model_ref, [entries[sha] if sha else _missing_entry(i)
                                         for i, sha in zip(flight_ids, order)])
    with services.db.transaction() as session:
        get_row(session, Evaluation, evaluation_id, "evaluation").report = report
        ctx.complete(session, {"evaluation_id": evaluation_id, "flights": total, "computed": len(todo),
                               "failed": failed})


def _outcome(future, flight_name: str) -> tuple[dict, str | None]:
    """A flight that fails is recorded with its reason and does not stop the others."""
    try:
        return future.result(), None
    except Exception as err:
        message = _message(err)
        log.warning("evaluation of %s failed: %s", flight_name, message)
        return {"flight": flight_name, "excluded": True, "reason": f"failed: {message}", "mse": {}, "groups": {},
                "failed": True}, message


def _missing_entry(flight_id: int) -> dict:
    return {"flight": f"#{flight_id}", "excluded": True, "reason": "flight was deleted", "mse": {}, "groups": {}}


def assemble_report(model_ref: str, entries: list[dict]) -> dict:
    """The same shape and numbers as service.experiments.flights.evaluate_flights."""
    from learnest.estimators.evaluate import summarize

    return {"model": model_ref, "flights": entries, **summarize(entries)}


def cached_entries(session: Session, version_id: int, key: str, shas: Iterable[str],
                   include_failed: bool = False) -> dict:
    """{flight sha256: stored entry} of this model version and settings key (succeeded results only,
    unless ``include_failed``)."""
    query = select(Result).where(Result.model_version_id == version_id, Result.settings_key == key,
                                 Result.flight_sha256.in_(list(shas)))
    if not include_failed:  # an explicit request retries flights that failed before
        query = query.where(Result.state == "succeeded")
    return {row.flight_sha256: row.entry for row in session.scalars(query)}


def store_result(db: Database, sha: str, version_id: int, key: str, flight_id: int, entry: dict,
                 error: str | None) -> None:
    """Insert or update the result of one flight (failed when ``error`` is given); retried on a concurrent
    insert; after three conflicts the result is not cached (logged: the evaluation's report still has it)."""
    state = "failed" if error else "succeeded"
    for _ in range(3):  # two evaluations may store the same flight at once: the second updates
        try:
            with db.transaction() as session:
                row = session.scalar(select(Result).where(Result.flight_sha256 == sha, Result.settings_key == key,
                                                          Result.model_version_id == version_id))
                if row is None:
                    session.add(Result(flight_sha256=sha, model_version_id=version_id, settings_key=key,
                                       flight_id=flight_id, state=state, entry=entry, error=error,
                                       created_at=utcnow()))
                else:
                    row.state, row.entry, row.error, row.created_at = state, entry, error, utcnow()
            return
        except IntegrityError:
            continue
    log.warning("result of flight %s (version %s) not cached: three concurrent inserts conflicted", flight_id,
                version_id)


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
        raise NotFound(f"flight(s) not found: {', '.join(map(str, missing))}")
    return ids


def _flights_by_id(session: Session, ids) -> dict[int, FlightRecord]:
    return {f.id: f for f in session.scalars(select(FlightRecord).where(FlightRecord.id.in_(list(ids))))}


def flights_without_results(session: Session, version_id: int, key: str) -> list[int]:
    """Every stored flight with no result (succeeded or failed) for this model version and settings."""
    done = select(Result.flight_sha256).where(Result.model_version_id == version_id, Result.settings_key == key)
    query = select(FlightRecord.id).where(FlightRecord.sha256.not_in(done)).order_by(FlightRecord.id)
    return list(session.scalars(query))


# -- diagnosis jobs ------------------------------------------------------------------------------------
def diagnose_task(flights_bytes: list[bytes], model_json: bytes | None, methods: list[str], epochs: int) -> dict:
    """service.experiments.diagnosis.diagnose_flights on stored flights; the report as plain JSON, the
    repaired model as HybridModel JSON, and the name of the flight it was fitted on."""
    from .experiments.diagnosis import diagnose_flights

    init_worker()
    knode = registry.model_from_json(model_json) if model_json is not None else None
    report, repaired = diagnose_flights([_flight_from_bytes(b) for b in flights_bytes], knode=knode,
                                        methods=tuple(methods), epochs=epochs, return_model=True)
    return {"report": json_compatible(report), "model_json": registry.model_to_json(repaired),
            "fitting_flight": repaired.meta.get("training_flight")}


def training_metrics(model: HybridModel) -> dict:
    """What the registry keeps of a training run besides its weights and losses."""
    return {key: model.meta.get(key) for key in ("final_loss", "best_epoch", "best_validation_loss")}


def diagnosis_metrics(model: HybridModel, report: dict) -> dict:
    """What a version made by a diagnosis records besides its weights: training metrics and before/after."""
    return {**training_metrics(model),
            "diagnosis": {"effects": [e["id"] for e in report["effects"]], "before": report["before"],
                          "after": report["after"]}}


def start_diagnosis(services: Services, flight_ids: list[int], model_ref: str | None, register: str | None,
                    methods: list[str], epochs: int) -> tuple[int, int]:
    """Create the diagnosis and its job and launch it.  -> (job id, diagnosis id)

    Raises
    ------
    InvalidInput
        For a bad ``register`` name or no flights.
    NotFound
        If a flight or the model does not exist.
    Conflict
        If the model version is not ready.
    """
    if register is not None:
        registry.check_name(register)
    ids = list(dict.fromkeys(int(i) for i in flight_ids))
    if not ids:
        raise InvalidInput("flights: give at least one flight id (the first is the fitting flight)")
    with services.db.transaction() as session:
        found = _flights_by_id(session, ids)
        missing = [i for i in ids if i not in found]
        if missing:
            raise NotFound(f"flight(s) not found: {', '.join(map(str, missing))}")
        if model_ref is not None:
            version = registry.resolve(session, model_ref)
            model_ref = f"{version.name}:{version.version}"
        settings = {"methods": list(methods), "epochs": epochs}
        job = services.runner.create(session, "diagnosis", {"flights": ids, "model": model_ref,
                                                            "register": register, **settings})
        diagnosis = Diagnosis(job_id=job.id, flight_ids=ids, model_ref=model_ref, register_as=register,
                              settings=settings, created_at=utcnow())
        session.add(diagnosis)
        session.flush()
        job_id, diagnosis_id = job.id, diagnosis.id
    services.runner.launch(job_id, lambda ctx: run_diagnosis(services, ctx, diagnosis_id))
    return job_id, diagnosis_id


def run_diagnosis(services: Services, ctx: JobContext, diagnosis_id: int) -> None:
    """The diagnosis job's work: diagnose on the executor, register the repaired model if asked, store the
    report.  The fitting flight is found by name among the diagnosis' flights (first flight if none matches)."""
    with services.db.transaction() as session:
        diagnosis = get_row(session, Diagnosis, diagnosis_id, "diagnosis")
        flights = _flights_by_id(session, diagnosis.flight_ids)
        if len(flights) != len(diagnosis.flight_ids):
            raise InvalidInput("a flight of this diagnosis was deleted before it started")
        blobs = [flights[i].flight_blob for i in diagnosis.flight_ids]
        weights = None
        if diagnosis.model_ref is not None:
            weights = registry.weights_of(registry.resolve(session, diagnosis.model_ref))
        settings, model_ref, register = dict(diagnosis.settings), diagnosis.model_ref, diagnosis.register_as
        first_flight_id = diagnosis.flight_ids[0]
    out = services.executor.submit(diagnose_task, [services.blobs.read_bytes(b) for b in blobs],
                                   services.blobs.read_bytes(weights) if weights else None,
                                   settings["methods"], settings["epochs"]).result()
    ctx.progress(0.95)
    registered = None
    if register is not None:
        model = registry.model_from_json(out["model_json"])
        # the fitting flight: diagnose_flights skips flights that fail the quality checks, so go by name
        fitting = next((f for f in flights.values() if f.name == out["fitting_flight"]),
                       flights[first_flight_id])
        row = registry.register_model(services.db, services.blobs, register, model, flight=fitting,
                                      hyperparameters=training_config({"epochs": settings["epochs"]}),
                                      parent=model_ref, job_id=ctx.job_id,
                                      metrics=diagnosis_metrics(model, out["report"]))
        registered = {"name": row.name, "version": row.version, "parent": row.parent}
    with services.db.transaction() as session:
        diagnosis = get_row(session, Diagnosis, diagnosis_id, "diagnosis")
        diagnosis.report, diagnosis.registered = out["report"], registered
        ctx.complete(session, {"diagnosis_id": diagnosis_id, "effects": [e["id"] for e in out["report"]["effects"]],
                               "registered": registered})
