"""Scheduled evaluation: every LEARNEST_SCHEDULE_SECONDS, evaluate each flight that has no result yet for
the model version holding an alias (default "production").  `learnest evaluate --new` runs one round.

Exactly one process does it, even with several uvicorn workers (each starts a Scheduler) or a cron job
next to the server: a round runs only while its process holds the database lease "scheduler" (a row with an
owner and an expiry, taken with one conditional UPDATE).  The lease is renewed on every tick and after
every evaluated flight; if its holder dies, it expires and another process takes over.  A lease row was
chosen over a PostgreSQL advisory lock / an fcntl lock file because it behaves the same on SQLite and
PostgreSQL, across machines, and does not pin a database connection for the life of the process.
"""
from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from sqlalchemy import select

from learnest.estimators.evaluation_settings import EvaluationSettings
from learnest.models.presets import PRODUCTION_ALIAS, parse_methods

from ..config import Settings
from ..storage import registry
from ..storage.database import get_row
from ..storage.leases import acquire_lease, release_lease
from ..storage.tables import Job, ModelAlias
from .evaluation import start_evaluation
from .result_cache import flights_without_results, settings_key
from .services import Services, open_services

log = logging.getLogger("learnest.scheduler")

LEASE_NAME = "scheduler"


def schedule_settings(services: Services) -> EvaluationSettings:
    """The estimator settings of scheduled rounds: LEARNEST_SCHEDULE_METHODS, default horizon, good flights."""
    return EvaluationSettings(tuple(parse_methods(services.settings.schedule_methods)))


def evaluate_new(services: Services, alias: str = PRODUCTION_ALIAS, settings: EvaluationSettings | None = None,
                 on_progress: Callable[[], object] | None = None) -> list[dict]:
    """One round, in this thread: for every model with `alias`, evaluate the flights without a result.
    Returns [{"model", "evaluation_id", "job_id", "flights", "state", "failed", "error"}] (empty when
    nothing was new); ``on_progress`` is called as each flight finishes."""
    settings = settings or schedule_settings(services)
    with services.db.transaction() as session:
        holders = [(row.name, row.version) for row in
                   session.scalars(select(ModelAlias).where(ModelAlias.alias == alias).order_by(ModelAlias.name))]
        todo = []
        for name, version in holders:
            row = registry.get_version(session, name, version)
            flight_ids = flights_without_results(session, row.id, settings_key(settings))
            if flight_ids:
                todo.append((f"{name}:{version}", flight_ids))
    rounds = []
    for ref, flight_ids in todo:
        job_id, evaluation_id, _ = start_evaluation(services, ref, flight_ids, settings, wait=True,
                                                    on_progress=on_progress)
        with services.db.transaction() as session:
            job = get_row(session, Job, job_id, "job")
        rounds.append({"model": ref, "evaluation_id": evaluation_id, "job_id": job_id, "flights": flight_ids,
                       "state": job.state, "failed": (job.result or {}).get("failed", 0), "error": job.error})
        log.info("scheduled evaluation %s of %s on %d new flight(s)", evaluation_id, ref, len(flight_ids))
    return rounds


def run_once(services: Services, alias: str = PRODUCTION_ALIAS, settings: EvaluationSettings | None = None,
             lease_s: float = 600.0) -> list[dict] | None:
    """evaluate_new under the scheduler lease; None when another process holds it."""
    owner = services.runner.owner
    if not acquire_lease(services.db, LEASE_NAME, owner, lease_s):
        return None
    renew = lambda: acquire_lease(services.db, LEASE_NAME, owner, lease_s)  # noqa: E731
    try:
        return evaluate_new(services, alias, settings, on_progress=renew)
    finally:
        release_lease(services.db, LEASE_NAME, owner)


def evaluate_new_once(alias: str = PRODUCTION_ALIAS, settings: EvaluationSettings | None = None,
                      app_settings: Settings | None = None) -> list[dict] | None:
    """`learnest evaluate --new`: one round with the service's storage (LEARNEST_* environment)."""
    services = open_services(app_settings or Settings())
    try:
        return run_once(services, alias, settings)
    finally:
        services.close()


class Scheduler:
    """A daemon thread per server process; only the lease holder's ticks do anything."""

    def __init__(self, services: Services, interval_s: float, alias: str = PRODUCTION_ALIAS,
                 settings: EvaluationSettings | None = None) -> None:
        self.services, self.interval_s, self.alias = services, interval_s, alias
        self.settings = settings or schedule_settings(services)
        self.lease_s = max(60.0, 3 * interval_s)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        """Start the daemon thread: a `tick` every ``interval_s`` seconds until `stop`."""
        self._thread = threading.Thread(target=self._loop, name="learnest-scheduler", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                self.tick()
            except Exception:  # one bad round must not end scheduling
                log.exception("scheduled evaluation failed")

    def tick(self) -> list[dict] | None:
        """One round if this process holds (or can take) the lease; None otherwise."""
        owner = self.services.runner.owner
        if not acquire_lease(self.services.db, LEASE_NAME, owner, self.lease_s):
            return None
        renew = lambda: acquire_lease(self.services.db, LEASE_NAME, owner, self.lease_s)  # noqa: E731
        return evaluate_new(self.services, self.alias, self.settings, on_progress=renew)

    def stop(self) -> None:
        """Stop the thread (waiting up to 5 s) and release the lease if this process holds it."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        release_lease(self.services.db, LEASE_NAME, self.services.runner.owner)  # only if it is still ours
