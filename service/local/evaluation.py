"""Evaluating in this process: local log files stored and a registered version evaluated on them, here and
now, and a stored evaluation's state estimates written to a file."""
from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from learnest.errors import Conflict, InvalidInput
from learnest.estimators.evaluation_settings import EvaluationSettings

from ..config import Settings
from ..jobs.evaluation import start_evaluation
from ..jobs.executors import InlineExecutor
from ..operations import catalog
from ..storage.blobs import BlobStore
from ..storage.tables import Evaluation
from .flights import add_flight, readable_groups
from .services import cli_settings, local_services, registry_database, watching_stages


def evaluate(paths, model_ref: str, estimator_settings: EvaluationSettings, *, pose_topic: str | None = None,
             imu_topic: str | None = None, progress: Callable[[float], None] | None = None,
             settings: Settings | None = None, on_stage: Callable[[str, float | None], None] | None = None,
             cut: str | None = None) -> dict:
    """Store the flights of ``paths`` (grouped as `learnest.ingest.group_files` does; stored ones are found
    by content) and evaluate ``model_ref`` on them as an evaluation job run in this process.  A file that
    cannot be read is listed in ``errors`` and the others are stored and evaluated.

    Returns
    -------
    dict
        The stored evaluation's report (``flight_id`` and ``sha256`` per flight, ``units``) plus
        ``evaluation_id``, ``job_id``, ``stored`` (per flight: ``file``, ``flight_id``, ``name``, ``stored``
        "new" or "existing") and ``errors`` (``[{"file", "message"}]``: what could not be read).

    Raises
    ------
    LearnestError
        No file can be read, the reference names nothing usable, or the job failed.
    """
    settings = settings or cli_settings()
    groups, errors = readable_groups(paths)   # sniffs the formats only: bad files are named before anything is stored
    with local_services(settings, executor=InlineExecutor()) as services:
        ids, stored = [], []
        for k, (_, files) in enumerate(groups, start=1):
            if on_stage:
                on_stage(f"ingest {k}/{len(groups)}", None)
            try:
                row, created = add_flight(services, files, pose_topic=pose_topic, imu_topic=imu_topic, cut=cut)
            except InvalidInput as err:
                errors.append({"file": str(files[0]), "message": str(err)})
                continue
            ids.append(row.id)
            stored.append({"file": str(files[0]), "flight_id": row.id, "name": row.name,
                           "stored": "new" if created else "existing"})
        if not ids:
            raise InvalidInput("no flight could be read: " + "; ".join(f"{e['file']}: {e['message']}" for e in errors))
        # interrupted (Ctrl-C), the job is failed by the runner's shutdown when the services close; the
        # progress shown is the job row's own (flights done of all, cached ones included), never a count
        # of progress calls
        with watching_stages(services, on_stage, progress=progress):
            job_id, evaluation_id, _ = start_evaluation(services, model_ref, ids, estimator_settings, wait=True)
        job = catalog.get_job(services.db, job_id)
        if job.state != "succeeded":
            raise Conflict(f"evaluation {evaluation_id} {job.state}: {job.error}")
        evaluation, _ = catalog.row_and_job(services.db, Evaluation, evaluation_id, "evaluation")
    return {**(evaluation.report or {}), "evaluation_id": evaluation_id, "job_id": job_id, "stored": stored,
            "errors": errors}


def export(evaluation_id: int, path: str | Path, fmt: str, flight_id: int | None = None,
           settings: Settings | None = None) -> list:
    """Write evaluation ``evaluation_id``'s state estimates to ``path`` as ``fmt`` (service.operations.exports);
    returns the `FlightEstimates` written.  NotFound when there is no registry yet or no such evaluation."""
    from ..operations.exports import export_evaluation

    settings = settings or cli_settings()
    missing = f"evaluation {evaluation_id} not found: nothing is stored under {settings.home} (LEARNEST_HOME)"
    with registry_database(settings, missing) as database:
        return export_evaluation(database, BlobStore(settings.home / "blobs"), evaluation_id, path, fmt, flight_id)

