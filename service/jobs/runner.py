"""The job runner: job rows' states, this server process's ownership of them, and the sweep of jobs a crashed
server left behind.

A job row (queued -> running -> succeeded | failed, progress 0..1) is created in the request's transaction;
a thread of this server process (the JobRunner) then orchestrates it, sending the heavy parts (training,
each flight of an evaluation) to the Executor.  Progress is written to the database, by the orchestrating
thread or, for training, by the worker itself (`tasks.report_progress`).

Ownership: every job row names the server process that runs it, and each process holds a lease
"runner:<owner>" renewed every HEARTBEAT_S.  A job whose owner has no live lease (or, on this host, a dead
pid) was left behind by a crashed server: `sweep` marks it failed with "server restarted" (at start-up
and on every heartbeat, so several uvicorn workers never fail each other's live jobs).
"""
from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from ..storage.database import Database, dml_rowcount
from ..storage.leases import acquire_lease, release_lease
from ..storage.tables import Job, Lease, utcnow

log = logging.getLogger("learnest.jobs")

ACTIVE = ("queued", "running")
HEARTBEAT_S = 10.0
LEASE_S = 30.0
ERROR_CHARS = 1000


class JobAborted(RuntimeError):
    """The job is no longer running (a sweep or shutdown failed it): drop its result."""


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
            self.mark_failed(job_id, error_message(err), on_failure)

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


def error_message(err: BaseException) -> str:
    """What a failed job records of ``err``: its message (prefixed by its kind when unexpected), at most
    ERROR_CHARS characters; never a traceback."""
    text = str(err) or type(err).__name__
    if not isinstance(err, (ValueError, LookupError)):  # unexpected: name the kind of failure
        text = f"{type(err).__name__}: {text}"
    return text[:ERROR_CHARS]
