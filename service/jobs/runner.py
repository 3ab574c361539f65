"""The job runner: job rows' states, this server process's ownership of them, and the sweep of jobs a crashed
server left behind.

A job row (queued -> running -> succeeded | failed | cancelled, progress 0..1) is created in the request's
transaction;
a thread of this server process (the JobRunner) then orchestrates it, sending the heavy parts (training,
each flight of an evaluation) to the Executor.  Progress is written to the database, by the orchestrating
thread or, for training, by the worker itself (`tasks.report_progress`).

Ownership: every job row names the server process that runs it, and each process holds a lease
"runner:<owner>" renewed every HEARTBEAT_S.  A job whose owner has no live lease (or, on this host, a dead
pid) was left behind by a crashed server: `sweep` marks it failed with "server restarted" (at start-up
and on every heartbeat, so several uvicorn workers never fail each other's live jobs).

A job always reaches a final state.  When recording its failure itself fails (a full database), the runner
retries a few times, then keeps the failure in memory and records it on every heartbeat until the database
takes it.  And the heartbeat's sweep fails this process's own running jobs that no thread runs any more (its
worker stopped without recording a result), and those that wrote no progress for ``stall_s`` (its worker is
wedged; LEARNEST_JOB_STALL_S, hours by default): the lease alone no longer keeps such a job "running".  A
stalled job's thread is told to stop, which kills its executor tasks.

Cancelling (`JobRunner.cancel`, any server process): the row becomes "cancelled" at once, in one transaction
with the `on_stale` hooks (a reserved model version is failed), so nothing the job computes afterwards can be
stored: `mark_succeeded` only completes a running job.  The orchestrating thread notices within
CANCEL_CHECK_S (`JobContext.wait`, `JobContext.finished`) and stops its executor tasks: pending ones never
start, running ones get ``cancel_grace_s`` to stop themselves (training checks its job's state between
epochs, `tasks.report_progress`) and are then killed (`Executor.stop`).
"""
from __future__ import annotations

import logging
import os
import re
import socket
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from typing import TYPE_CHECKING

from sqlalchemy import select, update
from sqlalchemy.orm import Session

from learnest.errors import Conflict, LearnestError, NotFound

from ..storage.database import Database, dml_rowcount
from ..storage.leases import acquire_lease, release_lease
from ..storage.tables import Job, Lease, utcnow
from .quotas import check_queue

if TYPE_CHECKING:
    from .executors import Executor

log = logging.getLogger("learnest.jobs")

ACTIVE = ("queued", "running")
STATES = ("queued", "running", "succeeded", "failed", "cancelled")
HEARTBEAT_S = 10.0
LEASE_S = 30.0
ERROR_CHARS = 1000
CANCEL_CHECK_S = 1.0     # how often a waiting job reads its state (a cancel by another server process)
WAIT_POLL_S = 0.05       # how often it looks at its executor tasks
CANCEL_GRACE_S = 10.0    # a cancelled task's time to stop itself before it is killed
RECORD_RETRIES_S = (0.5, 1.0, 2.0)   # waits between attempts to record a failure before the heartbeat takes over
ORPHAN_REASON = "the job's worker stopped without recording a result"
STALL_S = 6 * 3600.0     # a running job with no progress for this long is failed (its worker is wedged)


class JobAborted(RuntimeError):
    """The job is no longer running (cancelled, or a sweep or shutdown failed it): drop its result."""


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

    def progress(self, fraction: float, stage: str | None = None, eta_s: float | None = None) -> None:
        """Record progress (clipped to 0..1) of a running job, with its stage and the seconds left when
        given, and call ``on_progress``."""
        self.runner.set_progress(self.job_id, fraction, stage, eta_s)
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

    def wait(self, executor: Executor, future):
        """The result of one executor task; `JobAborted` (the task stopped, `Executor.stop`) as soon as the
        job is no longer running (cancelled, or failed by a sweep)."""
        for done in self.finished(executor, [future]):
            return done.result()
        raise AssertionError("unreachable: finished yields every future or raises")

    def finished(self, executor: Executor, futures: Iterable) -> Iterator:
        """Yield ``futures`` as they finish, like as_completed; when the job stops running, stop the
        unfinished ones (`Executor.stop`) and raise `JobAborted`."""
        pending = list(futures)
        stopped = self.runner.stop_event(self.job_id)
        next_check = time.monotonic() + CANCEL_CHECK_S
        while pending:
            # one at a time, asking no further than the first finished one (an InlineExecutor's future
            # runs its task when asked)
            finished = next((f for f in pending if f.done()), None)
            if finished is not None:
                pending.remove(finished)
                yield finished
                continue
            if time.monotonic() >= next_check:  # a cancel may come through another server process
                next_check = time.monotonic() + CANCEL_CHECK_S
                if not self.runner.is_running(self.job_id):
                    stopped.set()
            if stopped.wait(WAIT_POLL_S):
                executor.stop(pending, self.runner.cancel_grace_s)
                raise JobAborted(self.job_id)


class JobRunner:
    """Runs this server process's jobs in a thread pool and keeps its lease (module docstring).

    Parameters
    ----------
    db : Database
    threads : int
        Jobs orchestrated at once; the heavy parts go to the Executor.
    cancel_grace_s : float
        Seconds a cancelled executor task gets to stop itself before it is killed.
    stall_s : float
        Seconds without progress after which a running job of this process is failed (0: never).
    max_queued : int
        Jobs that may wait to start, on every server of the database (0: no limit; `quotas.check_queue`).

    Attributes
    ----------
    owner : str
        This process's owner id (`make_owner_id`).
    on_stale : list of callable
        Hooks ``hook(session, job_ids, reason)`` called in the transaction that fails jobs (sweep, shutdown).
    """

    def __init__(self, db: Database, threads: int = 4, cancel_grace_s: float = CANCEL_GRACE_S,
                 stall_s: float = STALL_S, max_queued: int = 0) -> None:
        self.db, self.max_queued = db, max_queued   # max_queued 0: no limit
        self.cancel_grace_s = cancel_grace_s
        self.stall_s = stall_s   # 0: never fail a job for making no progress
        self._stop_events: dict[int, threading.Event] = {}  # jobs this process runs, set when they must stop
        self._events_lock = threading.Lock()
        self.owner = make_owner_id()
        self._threads = ThreadPoolExecutor(threads, thread_name_prefix="learnest-job")
        self._stop = threading.Event()
        self._heartbeat: threading.Thread | None = None
        # called in the sweep's transaction with the ids of the jobs it failed and the reason
        self.on_stale: list[Callable[[Session, list[int], str], None]] = []
        self._running: set[int] = set()   # jobs a thread of this process is running (in `run`)
        # failures not yet recorded (the database refused the write): job id -> (message, on_failure)
        self._unrecorded: dict[int, tuple[str, Callable[[Session, str], None] | None]] = {}

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
            self.beat()

    def beat(self) -> None:
        """One heartbeat: record the failures the database refused before, renew the lease, sweep.  Each step
        on its own: a database hiccup in one must not skip the others, nor kill the heartbeat."""
        for step in (self.record_unrecorded, lambda: acquire_lease(self.db, self.lease_name, self.owner, LEASE_S),
                     self.sweep):
            try:
                step()
            except Exception:
                log.exception("job heartbeat step failed")

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
        check_queue(session, self.max_queued)   # quotas.QueueFull when max_queued jobs wait already
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
        with self._events_lock:
            self._running.add(job_id)   # before the row says running: the sweep never sees it unowned
        try:
            if not self._mark_running(job_id):
                return
            context = JobContext(job_id, self, on_progress)
            try:
                result = work(context)
                if not context.completed:
                    with self.db.transaction() as session:
                        context.complete(session, result or {})
            except JobAborted:
                log.info("job %s was stopped while running; its result is dropped", job_id)
            except Exception as err:  # recorded on the job: no traceback reaches a user, the log keeps it
                if self._still_running(job_id):
                    if isinstance(err, LearnestError):   # bad input, said in the job's error: no traceback needed
                        log.info("job %s failed: %s", job_id, err)
                    else:
                        log.exception("job %s failed", job_id)
                    self.record_failure(job_id, error_message(err), on_failure)
                else:  # a cancelled task's own exception (tasks.TaskCancelled, a killed worker): expected
                    log.info("job %s was stopped while running (%s)", job_id, type(err).__name__)
        finally:
            with self._events_lock:
                self._stop_events.pop(job_id, None)
                self._running.discard(job_id)

    def _still_running(self, job_id: int) -> bool:
        try:
            return self.is_running(job_id)
        except Exception:   # the database cannot even be read: record the failure (a no-op if it ended)
            log.exception("job %s: its state could not be read", job_id)
            return True

    def record_failure(self, job_id: int, message: str,
                       on_failure: Callable[[Session, str], None] | None = None) -> bool:
        """`mark_failed`, retried (RECORD_RETRIES_S); when the database still refuses, the failure is kept and
        recorded by the heartbeat (`record_unrecorded`).  Returns whether it is recorded."""
        for wait in (*RECORD_RETRIES_S, None):
            try:
                self.mark_failed(job_id, message, on_failure)
                return True
            except Exception:
                log.exception("job %s: recording its failure failed%s", job_id,
                              "; retrying" if wait is not None else "; the heartbeat retries")
            if wait is None or self._stop.wait(wait):
                break
        with self._events_lock:
            self._unrecorded[job_id] = (message, on_failure)
        return False

    def record_unrecorded(self) -> list[int]:
        """Record the failures the database refused before (each in its own transaction); -> the job ids
        recorded now.  Raises the first error after trying them all."""
        with self._events_lock:
            pending = dict(self._unrecorded)
        done, problem = [], None
        for job_id, (message, on_failure) in pending.items():
            try:
                self.mark_failed(job_id, message, on_failure)
            except Exception as err:
                problem = problem or err
                continue
            done.append(job_id)
            with self._events_lock:
                self._unrecorded.pop(job_id, None)
        if done:
            log.warning("recorded the failure of job(s) %s that the database had refused", done)
        if problem is not None:
            raise problem
        return done

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

    def cancel(self, job_id: int, reason: str = "cancelled by request") -> Job:
        """Cancel a queued or running job: state "cancelled" with ``reason`` and the `on_stale` hooks in one
        transaction; the thread running it (in this process, or found by `JobContext.finished` in another)
        then stops its executor tasks.  Cancelling a cancelled job changes nothing.

        Raises
        ------
        NotFound
            No such job.
        Conflict
            The job already succeeded or failed.
        """
        with self.db.transaction() as session:
            job = session.get(Job, job_id, with_for_update=True)
            if job is None:
                raise NotFound(f"job {job_id} not found")
            if job.state in ACTIVE:
                job.state, job.error, job.finished_at = "cancelled", reason, utcnow()
                for hook in self.on_stale:
                    hook(session, [job_id], reason)
            elif job.state != "cancelled":
                raise Conflict(f"job {job_id} already {job.state}; only queued or running jobs can be cancelled")
        with self._events_lock:
            event = self._stop_events.get(job_id)
        if event is not None:
            event.set()
        return job

    def stop_event(self, job_id: int) -> threading.Event:
        """Set when job ``job_id``, run by this process, must stop (`cancel`)."""
        with self._events_lock:
            return self._stop_events.setdefault(job_id, threading.Event())

    def is_running(self, job_id: int) -> bool:
        """Whether the job's row still says "running"."""
        with self.db.transaction() as session:
            return session.scalar(select(Job.state).where(Job.id == job_id)) == "running"

    def set_progress(self, job_id: int, fraction: float, stage: str | None = None,
                     eta_s: float | None = None) -> None:
        """Write a running job's progress (clipped to 0..1), and its stage and ETA when given."""
        with self.db.transaction() as session:
            session.execute(update(Job).where(Job.id == job_id, Job.state == "running")
                            .values(progress_values(fraction, stage, eta_s)))

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
            with self._events_lock:
                running_here, unrecorded = set(self._running), dict(self._unrecorded)
            # this process's own: running, yet no thread here runs it (nor holds a failure to record for it)
            orphans = [job for job in jobs if job.owner == self.owner and job.state == "running"
                       and job.id not in running_here and job.id not in unrecorded]
            # this process's own, run by a thread here, with no progress for stall_s: its worker is wedged
            stalled = [job for job in jobs if self.stall_s and job.owner == self.owner and job.state == "running"
                       and job.id in running_here and _seconds_since(job.progress_at or job.started_at) > self.stall_s]
            stall_reason = (f"no progress for {self.stall_s:g} s: its worker is stuck (LEARNEST_JOB_STALL_S); "
                            "the job was stopped")
            for job in stale:
                job.state, job.error, job.finished_at = "failed", reason, utcnow()
            for job in orphans:
                job.state, job.error, job.finished_at = "failed", ORPHAN_REASON, utcnow()
            for job in stalled:
                job.state, job.error, job.finished_at = "failed", stall_reason, utcnow()
            ids = [job.id for job in stale]
            for hook in self.on_stale:
                hook(session, ids, reason)
                if orphans:
                    hook(session, [job.id for job in orphans], ORPHAN_REASON)
                if stalled:
                    hook(session, [job.id for job in stalled], stall_reason)
        for job in stalled:   # its thread stops its executor tasks (a wedged worker is killed)
            self.stop_event(job.id).set()
        orphans = orphans + stalled
        if ids:
            log.warning("marked %d job(s) left by a stopped server as failed: %s", len(ids), ids)
        if orphans:
            log.warning("marked %d job(s) whose worker stopped or stalled as failed: %s", len(orphans),
                        [j.id for j in orphans])
        return ids + [job.id for job in orphans]

    @staticmethod
    def _fail(session: Session, query, reason: str) -> list[int]:
        jobs = session.scalars(query).all()
        for job in jobs:
            job.state, job.error, job.finished_at = "failed", reason, utcnow()
        return [job.id for job in jobs]


def progress_values(fraction: float | None, stage: str | None = None, eta_s: float | None = None) -> dict:
    """The job columns a progress report sets: with a ``fraction``, the progress (clipped to 0..1) and a new
    ETA (``eta_s``, None: unknown) stamped now (``progress_at``); the stage when given.  A stage alone
    (a worker naming the method it runs) leaves the progress and the job's ETA as they are."""
    values: dict = {}
    if fraction is not None:
        values.update(progress=max(0.0, min(1.0, float(fraction))), progress_at=utcnow(),
                      eta_s=None if eta_s is None else max(0.0, float(eta_s)))
    if stage is not None:
        values["stage"] = stage[:200]
    return values


def seconds_left(job: Job, now=None) -> float | None:
    """A job's ETA as of ``now`` (default: now): the estimate written at ``progress_at`` minus the time
    since; None when the job is not running or no estimate was written."""
    if job.state != "running" or job.eta_s is None or job.progress_at is None:
        return None
    elapsed = ((now or utcnow()) - job.progress_at).total_seconds()
    return max(0.0, job.eta_s - elapsed)


def _seconds_since(moment) -> float:
    """Seconds from ``moment`` (a stored time, naive UTC or aware; None: no time) to now."""
    if moment is None:
        return 0.0
    now = utcnow()
    if (moment.tzinfo is None) != (now.tzinfo is None):
        moment = moment.replace(tzinfo=now.tzinfo)
    return (now - moment).total_seconds()


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


# an absolute POSIX path not glued to a word ("m/s" is no path): its folders are the server's business
ABSOLUTE_PATH = re.compile(r"(?<![\w.~])/(?:[^\s'\"/:,;()]+/)+(?=[^\s'\"/:,;()]*)")


# what SQLAlchemy appends to a driver's message: the statement and its parameters, and a link
SQL_DETAIL = re.compile(r"\s*(\[SQL: .*|\[parameters: .*|\(Background on this error at: .*)", re.DOTALL)


def error_message(err: BaseException) -> str:
    """What a failed job records of ``err``: its message (prefixed by its kind when unexpected), at most
    ERROR_CHARS characters; never a traceback, no SQL, and no server folder (GET /jobs/{id} needs no key):
    an absolute path keeps only its file name ("/srv/learnest/blobs/ab/cd" -> ".../cd"); a full database is
    said as such (`storage.database.DatabaseFull`)."""
    from sqlalchemy.exc import SQLAlchemyError

    from ..storage.database import database_full, storage_is_full

    if isinstance(err, SQLAlchemyError) and storage_is_full(err):
        err = database_full(err)
    if isinstance(err, SQLAlchemyError):
        orig = getattr(err, "orig", None)
        text = f"database error: {SQL_DETAIL.sub('', str(orig if orig is not None else err)).strip()}"
    else:
        text = SQL_DETAIL.sub("", str(err)).strip() or type(err).__name__
        if not isinstance(err, (ValueError, LookupError)):  # unexpected: name the kind of failure
            text = f"{type(err).__name__}: {text}"
    return ABSOLUTE_PATH.sub(".../", text)[:ERROR_CHARS]
