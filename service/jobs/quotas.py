"""Quotas: how much work one request may ask for.  Without them ``{"epochs": 100000,
"hidden": 4096}`` was accepted and would occupy a worker for days.  Checked where jobs are created
(`training.start_training`, `diagnosis.start_diagnosis`), so the API, the web forms and the CLI share them;
each limit is a setting, and the message names the setting that raises it."""
from __future__ import annotations

from learnest.errors import InvalidInput

from ..config import Settings


class QuotaExceeded(InvalidInput):
    """A request for more work than the server's limits allow: HTTP 422 naming the limit and its setting."""


def check_training(settings: Settings, *, epochs: int, hidden: int, samples: int, what: str = "training") -> None:
    """Raise `QuotaExceeded` when a training of ``epochs`` epochs of a ``hidden``-unit network on a flight of
    ``samples`` samples exceeds LEARNEST_MAX_EPOCHS, LEARNEST_MAX_HIDDEN or LEARNEST_MAX_TRAINING_WORK
    (epochs x samples x hidden; 0 = none)."""
    if epochs > settings.max_epochs:
        raise QuotaExceeded(f"epochs: {epochs} is above this server's limit of {settings.max_epochs} "
                            "(LEARNEST_MAX_EPOCHS raises it)")
    if hidden > settings.max_hidden:
        raise QuotaExceeded(f"hidden: {hidden} is above this server's limit of {settings.max_hidden} "
                            "(LEARNEST_MAX_HIDDEN raises it)")
    work = float(epochs) * samples * hidden
    if settings.max_training_work and work > settings.max_training_work:
        raise QuotaExceeded(f"{what} too large: epochs x samples x hidden = {epochs} x {samples} x {hidden} = "
                            f"{work:,.0f}, above this server's limit of {settings.max_training_work:,.0f} "
                            "(LEARNEST_MAX_TRAINING_WORK raises it; fewer epochs or hidden units lower it)")
