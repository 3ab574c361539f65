"""The service opened in this process: its settings for the CLI, its Services, the registry's database for
reading, and watching a job run (its progress, stage and time left) until it is finished."""
from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from sqlalchemy import select

from learnest.errors import NotFound

from ..config import Settings
from ..jobs.executors import Executor
from ..jobs.runner import ACTIVE, seconds_left
from ..jobs.services import Services, open_services
from ..operations import catalog
from ..storage.database import Database
from ..storage.tables import Job


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


@contextmanager
def registry_database(settings: Settings | None = None, missing: str | None = None) -> Iterator[Database]:
    """The registry's database for reading (or a small write such as an alias), never migrated; NotFound when
    nothing is stored under LEARNEST_HOME yet (``missing``: its message), Conflict when its schema is older than
    this learnest."""
    settings = settings or cli_settings()
    if settings.database_url is None and not (settings.home / "learnest.db").is_file():
        raise NotFound(missing or f"nothing is stored under {settings.home} (LEARNEST_HOME) yet: `learnest train`, "
                                  "`learnest evaluate` or `learnest serve` store flights and models there")
    database = Database(settings.url)
    try:
        database.require_current_schema()
        yield database
    finally:
        database.dispose()


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

