"""The per-flight result cache of evaluations: one stored entry per (flight content, model version, estimator
settings), so an evaluation computes only the flights no earlier one has scored with the same settings."""
from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Iterable
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from learnest.estimators.evaluation_settings import EvaluationSettings
from learnest.models.presets import GAP_EVERY_S, GAP_S, SG_WINDOW

from ..storage.database import Database
from ..storage.tables import FlightRecord, Result, utcnow

log = logging.getLogger("learnest.jobs")


# What a cached flight entry holds and how it was computed.  2: each entry has a `prediction_check`,
# and a Crazyflie model's attitude input has no heading; an entry of format 1 would show "nothing flagged"
# where nothing was checked, and mix inputs with newly computed flights of the same model.  3: a
# Crazyflie prior scales its thrust by the flight's thrust gain (entries carry `thrust_gain`).  4: and
# by the motors' heating before it (`heating_thrust_loss_pct`).  5: entries carry the KNODE's
# `gain_interval_pct`.  6: entries carry the `yardsticks` (mocap gaps, fast reference, the paper's SG score).
# 7: entries carry the `noise` each method ran with.  8: entries carry their `verdict` (mocap gaps), and the
# one-step `one_step_innovation_ratio` in place of the `prediction_check`.
ENTRY_FORMAT = 8


def settings_key(settings: EvaluationSettings) -> str:
    """Cache key part: what changes a flight's entry besides the flight and the model.  The default SG window
    and gaps are left out, so results cached before they could be chosen keep their key; the entry format
    (`ENTRY_FORMAT`) is in it, so an entry of another format is computed again."""
    fields: dict = {"methods": sorted(settings.methods), "horizon": settings.horizon,
                    "include_bad": settings.include_bad, "entry_format": ENTRY_FORMAT}
    if settings.sg_window != SG_WINDOW:
        fields["sg_window"] = settings.sg_window
    if (settings.gap_s, settings.gap_every_s) != (GAP_S, GAP_EVERY_S):
        fields["gaps"] = [float(settings.gap_s), float(settings.gap_every_s)]
    if settings.noise != "identified":
        fields["noise"] = settings.noise
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True)
class EstimatorSettings(EvaluationSettings):
    """An evaluation's settings (`learnest.estimators.evaluation_settings.EvaluationSettings`, the fields and
    checks all its own) under the name the service's callers know, with its result cache ``key``."""

    @property
    def key(self) -> str:
        """`settings_key` of these settings."""
        return settings_key(self)


def cached_entries(session: Session, version_id: int, key: str, shas: Iterable[str],
                   include_failed: bool = False) -> dict:
    """{flight sha256: stored entry} of this model version and settings key (succeeded results only,
    unless ``include_failed``).  A scored flight whose result has no stored estimates (cached before they
    were kept) is left out: computing it again stores them."""
    query = select(Result).where(Result.model_version_id == version_id, Result.settings_key == key,
                                 Result.flight_sha256.in_(list(shas)))
    if not include_failed:  # an explicit request retries flights that failed before
        query = query.where(Result.state == "succeeded")
    return {row.flight_sha256: row.entry for row in session.scalars(query)
            if row.estimates_blob is not None or row.state == "failed" or row.entry.get("excluded")}


def store_result(db: Database, sha: str, version_id: int, key: str, flight_id: int, entry: dict,
                 error: str | None, estimates_blob: str | None = None) -> str | None:
    """Insert or update the result of one flight (failed when ``error`` is given), with the blob of its
    per-step estimates (`FlightEstimates.to_bytes`, written before this call); retried on a concurrent
    insert; after three conflicts the result is not cached (logged: the evaluation's report still has it).
    A failure never replaces a stored success of the same flight, model version and settings.  A flight
    deleted while it was being evaluated is not cached (its results went with it): the flight row is locked
    first, so a concurrent delete either sees this result or this sees the flight gone.

    Returns the estimates blob the update replaced, or ``estimates_blob`` when nothing names it (for the
    caller to collect), else None."""
    state = "failed" if error else "succeeded"
    for _ in range(3):  # two evaluations may store the same flight at once: the second updates
        try:
            with db.transaction() as session:
                if session.scalar(select(FlightRecord.id).where(FlightRecord.sha256 == sha).with_for_update()) is None:
                    log.info("flight %s was deleted while it was evaluated: its result is not cached", flight_id)
                    return estimates_blob
                row = session.scalar(select(Result).where(Result.flight_sha256 == sha, Result.settings_key == key,
                                                          Result.model_version_id == version_id))
                if row is None:
                    session.add(Result(flight_sha256=sha, model_version_id=version_id, settings_key=key,
                                       flight_id=flight_id, state=state, entry=entry, error=error,
                                       estimates_blob=estimates_blob, created_at=utcnow()))
                    return None
                if error and row.state == "succeeded":
                    # the same code on the same flight, model and settings succeeded before: this failure is
                    # the machine's (a server shutting down, a lost worker), so the stored result is kept
                    log.warning("flight %s (version %s) failed (%s); its earlier result is kept", flight_id,
                                version_id, error)
                    return None
                previous = row.estimates_blob
                row.state, row.entry, row.error, row.created_at = state, entry, error, utcnow()
                row.estimates_blob = estimates_blob
            return previous if previous != estimates_blob else None
        except IntegrityError:
            continue
    log.warning("result of flight %s (version %s) not cached: three concurrent inserts conflicted", flight_id,
                version_id)
    return estimates_blob  # named by no row: the caller collects it


def flights_without_results(session: Session, version_id: int, key: str) -> list[int]:
    """Every stored flight with no result (succeeded or failed) for this model version and settings."""
    done = select(Result.flight_sha256).where(Result.model_version_id == version_id, Result.settings_key == key)
    query = select(FlightRecord.id).where(FlightRecord.sha256.not_in(done)).order_by(FlightRecord.id)
    return list(session.scalars(query))
