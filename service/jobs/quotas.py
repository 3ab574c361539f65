"""Quotas: how much work one request may ask for.  Without them ``{"epochs": 100000,
"hidden": 4096}`` was accepted and would occupy a worker for days.  Checked where jobs are created
(`training.start_training`, `diagnosis.start_diagnosis`), so the API, the web forms and the CLI share them;
each limit is a setting, and the message names the setting that raises it."""
from __future__ import annotations

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from learnest.errors import InvalidInput, LearnestError

from ..config import Settings
from ..storage.tables import Job


class QuotaExceeded(InvalidInput):
    """A request for more work than the server's limits allow: HTTP 422 naming the limit and its setting."""


class QueueFull(LearnestError):
    """Too many jobs wait to start (LEARNEST_MAX_QUEUED_JOBS): HTTP 503, retry later."""

    status = 503
    headers = {"Retry-After": "30"}


def check_queue(session: Session, max_queued: int) -> None:
    """Raise `QueueFull` when ``max_queued`` jobs (0: no limit) wait to start already: each one accepted would
    otherwise wait its turn, however many came (300 trainings were accepted in 42 s)."""
    if not max_queued:
        return
    waiting = session.scalar(select(func.count()).select_from(Job).where(Job.state == "queued")) or 0
    if waiting >= max_queued:
        raise QueueFull(f"{waiting} jobs are waiting to start, the limit is {max_queued} (LEARNEST_MAX_QUEUED_JOBS): "
                        "retry when some have run, or cancel some")


def check_training(settings: Settings, *, epochs: int, hidden: int, samples: int, what: str = "training",
                   trainings: int = 1) -> None:
    """Raise `QuotaExceeded` when ``trainings`` trainings of ``epochs`` epochs of a ``hidden``-unit network on
    flights of ``samples`` samples in all (training and validation flights: the epochs run over both) exceed
    LEARNEST_MAX_EPOCHS, LEARNEST_MAX_HIDDEN or LEARNEST_MAX_TRAINING_WORK (trainings x epochs x samples x
    hidden; 0 = none).  A grouped training is one training per held-out group plus the final one
    (`estimators.group_training`)."""
    if epochs > settings.max_epochs:
        raise QuotaExceeded(f"epochs: {epochs} is above this server's limit of {settings.max_epochs} "
                            "(LEARNEST_MAX_EPOCHS raises it)")
    if hidden > settings.max_hidden:
        raise QuotaExceeded(f"hidden: {hidden} is above this server's limit of {settings.max_hidden} "
                            "(LEARNEST_MAX_HIDDEN raises it)")
    work = float(trainings) * epochs * samples * hidden
    if settings.max_training_work and work > settings.max_training_work:
        runs = f"{trainings} trainings x " if trainings > 1 else ""
        product = f"{trainings} x " if trainings > 1 else ""
        raise QuotaExceeded(f"{what} too large: {runs}epochs x samples x hidden = {product}{epochs} x {samples} x "
                            f"{hidden} = {work:,.0f}, above this server's limit of {settings.max_training_work:,.0f} "
                            "(LEARNEST_MAX_TRAINING_WORK raises it; fewer epochs, hidden units or groups lower it)")
