"""The state estimates of a stored evaluation, as data: what GET /evaluations/{id}/estimates and
`learnest export` write.

An evaluation's per-step estimates are stored once per flight result (the result cache's
``estimates_blob``: `FlightEstimates.to_bytes`), so an evaluation answered from the cache has them too and a
download reads them instead of running the estimators again.  A download's file is made once and kept
(`cached_export`, within the export budget); `learnest export` writes where it is told.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import IO, BinaryIO

from sqlalchemy import select

from learnest import __version__
from learnest.errors import Conflict, NotFound
from learnest.estimators.estimates import FlightEstimates
from learnest.estimators.evaluation_settings import EvaluationSettings
from learnest.estimators.export import FORMATS, check_format, write_estimates

from ..jobs.result_cache import settings_key
from ..storage.blobs import BlobStore
from ..storage.database import Database, flights_by_id
from ..storage.export_cache import ExportCache
from ..storage.tables import Evaluation, Result
from .catalog import row_and_job

__all__ = ["FORMATS", "cached_export", "estimates_sources", "evaluation_estimates", "export_evaluation",
           "export_filename"]


def evaluation_estimates(db: Database, blobs: BlobStore, evaluation_id: int,
                         flight_id: int | None = None) -> list[FlightEstimates]:
    """The stored estimates of every scored flight of a finished evaluation (or of one of its flights).

    Flights deleted since are left out (their results went with them).

    Raises
    ------
    NotFound
        No such evaluation, or ``flight_id`` is not one of its flights.
    Conflict
        The evaluation has not finished (or failed); the chosen flight was not scored; no flight has
        estimates; or a scored flight's estimates were never stored (evaluated before they were kept:
        evaluate it again).
    """
    return [_read(blobs, source) for source in estimates_sources(db, evaluation_id, flight_id)]


def estimates_sources(db: Database, evaluation_id: int,
                      flight_id: int | None = None) -> list[tuple[int, str, str, str]]:
    """What `evaluation_estimates` reads, from the database alone: per scored flight still stored, (flight id,
    name, content sha256, estimates blob).  Raises as `evaluation_estimates` does."""
    evaluation, job = row_and_job(db, Evaluation, evaluation_id, "evaluation")
    if job.state != "succeeded":
        raise Conflict(f"evaluation {evaluation_id} is {job.state}: its estimates exist once it has succeeded")
    pairs = list(zip(evaluation.flight_ids, (evaluation.report or {}).get("flights", [])))
    if flight_id is not None:
        pairs = [(i, entry) for i, entry in pairs if i == flight_id]
        if not pairs:
            raise NotFound(f"flight {flight_id} is not one of evaluation {evaluation_id}'s flights "
                           f"({', '.join(map(str, evaluation.flight_ids))})")
        if pairs[0][1].get("excluded"):
            raise Conflict(f"flight {flight_id} was not scored in evaluation {evaluation_id}: {pairs[0][1]['reason']}")
    scored = [(i, entry) for i, entry in pairs if not entry.get("excluded")]
    key = settings_key(EvaluationSettings.from_json(evaluation.settings))
    with db.transaction() as session:
        rows = flights_by_id(session, [i for i, _ in scored])
        shas = {i: row.sha256 for i, row in rows.items()}
        query = select(Result.flight_sha256, Result.estimates_blob).where(
            Result.model_version_id == evaluation.model_version_id, Result.settings_key == key,
            Result.flight_sha256.in_(list(shas.values())))
        blob_of: dict[str, str] = {sha: blob for sha, blob in session.execute(query) if blob}
        names = {i: row.name for i, row in rows.items()}
    missing = [i for i in shas if shas[i] not in blob_of]
    if missing:
        raise Conflict(f"evaluation {evaluation_id} has no stored estimates for flight(s) "
                       f"{', '.join(map(str, missing))} (scored before estimates were kept): evaluate them again")
    sources = [(i, names[i], shas[i], blob_of[shas[i]]) for i, _entry in scored if i in shas]  # else deleted since
    if not sources:
        raise Conflict(f"evaluation {evaluation_id} has no scored flight with estimates to export")
    return sources


def _read(blobs: BlobStore, source: tuple[int, str, str, str]) -> FlightEstimates:
    flight_id, name, sha, blob = source
    estimates = FlightEstimates.from_bytes(blobs.read_bytes(blob))
    estimates.flight, estimates.flight_id, estimates.sha256 = name, flight_id, sha
    return estimates


def cached_export(db: Database, blobs: BlobStore, budget_bytes: int, evaluation_id: int, fmt: str,
                  flight_id: int | None = None) -> BinaryIO:
    """An evaluation's estimates as ``fmt``, opened for reading: made once per (evaluation, flight or all,
    format, stored estimates) and kept within ``budget_bytes`` of disk (`service.storage.export_cache`).

    Raises
    ------
    NotFound, Conflict
        As `evaluation_estimates`.
    ExportBudgetExceeded
        The export does not fit in the budget (HTTP 507).
    """
    check_format(fmt)
    sources = estimates_sources(db, evaluation_id, flight_id)
    # what the file is made of: another version's writer or other stored estimates make another file
    digest = hashlib.sha256(json.dumps([__version__, fmt, sources]).encode()).hexdigest()

    def still_wanted() -> bool:
        with db.transaction() as session:
            return session.get(Evaluation, evaluation_id) is not None

    return ExportCache(blobs, budget_bytes).open(
        evaluation_id, flight_id, digest, FORMATS[fmt],
        lambda handle: write_estimates([_read(blobs, source) for source in sources], handle, fmt), still_wanted)


def export_filename(evaluation_id: int, fmt: str, flight_id: int | None = None) -> str:
    """``evaluation-<id>[-flight-<id>]-estimates.<ext>``."""
    part = f"-flight-{flight_id}" if flight_id is not None else ""
    return f"evaluation-{evaluation_id}{part}-estimates{FORMATS[check_format(fmt)]}"


def export_evaluation(db: Database, blobs: BlobStore, evaluation_id: int, target: str | Path | IO[bytes], fmt: str,
                      flight_id: int | None = None) -> list[FlightEstimates]:
    """Write an evaluation's estimates (`evaluation_estimates`) to ``target`` as ``fmt``; returns them."""
    check_format(fmt)  # before any work
    flights = evaluation_estimates(db, blobs, evaluation_id, flight_id)
    write_estimates(flights, target, fmt)
    return flights
