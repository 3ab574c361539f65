"""The velocity figure of an evaluation report, computed once per (evaluation, flight) and kept.  It runs
the UKF and KNODE-UKF on the flight (seconds), and the report page is an unauthenticated GET: computed in
the request, even behind a small cache, it would let anyone keep the server busy by cycling through
evaluation ids.

So a page view reads the stored figure (table ``report_figures``); when there is none it starts one
executor task for it - at most `MAX_RUNNING` at a time in this server, never two for the same figure - and
the page says so and reloads itself.  The task's answer (or its error) is stored when it finishes, so each
figure is computed once however often and however many clients ask.
"""
from __future__ import annotations

import logging
import threading

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from ..jobs.runner import error_message
from ..jobs.services import Services
from ..local.figures import velocity_png
from ..operations import catalog
from ..storage import registry
from ..storage.tables import Evaluation, ReportFigure, utcnow

log = logging.getLogger("learnest.web")

MAX_RUNNING = 2   # figures computed at once by this server (each takes an executor worker for seconds)

_running: set[tuple[int, int]] = set()
_lock = threading.Lock()


def velocity_figure(services: Services, evaluation: Evaluation, flight_id: int) -> dict:
    """{"png": data URI} when stored, {"error": why} when it failed, else {"pending": True} (a task computes it
    now) or {"busy": True} (`MAX_RUNNING` others are being computed: asked again later)."""
    key = (evaluation.id, flight_id)
    with services.db.transaction() as session:
        stored = session.scalar(select(ReportFigure).where(ReportFigure.evaluation_id == key[0],
                                                           ReportFigure.flight_id == key[1]))
        if stored is not None:
            return {"png": stored.png} if stored.png else {"error": stored.error or "failed"}
    with _lock:
        if key in _running:
            return {"pending": True}
        if len(_running) >= MAX_RUNNING:
            return {"busy": True}
        _running.add(key)
    try:
        version = catalog.get_version_by_id(services.db, evaluation.model_version_id)
        row = catalog.get_flight(services.db, flight_id)
        model_json = services.blobs.read_bytes(registry.weights_of(version))
        flight_bytes = services.blobs.read_bytes(row.flight_blob)
        future = services.executor.submit(velocity_png, model_json, flight_bytes,
                                          f"{version.name}:{version.version} on {row.name}")
    except Exception as err:   # a deleted flight or version: said on the page, kept, not retried
        _store(services, key, None, error_message(err))
        return {"error": error_message(err)}
    future.add_done_callback(lambda done: _finished(services, key, done))
    return {"pending": True}


def _finished(services: Services, key: tuple[int, int], future) -> None:
    try:
        png, error = future.result(), None
    except Exception as err:
        log.warning("velocity figure of evaluation %s, flight %s failed: %s", *key, err)
        png, error = None, error_message(err)
    _store(services, key, png, error)


def _store(services: Services, key: tuple[int, int], png: str | None, error: str | None) -> None:
    try:
        with services.db.transaction() as session:
            session.add(ReportFigure(evaluation_id=key[0], flight_id=key[1], png=png, error=error,
                                     created_at=utcnow()))
    except IntegrityError:   # another server process stored it first
        pass
    except Exception:        # the server is closing (database disposed): the next view asks again
        log.warning("velocity figure of evaluation %s, flight %s not stored", *key, exc_info=True)
    finally:
        with _lock:
            _running.discard(key)
