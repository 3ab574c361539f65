"""/evaluations: batch KNODE-UKF / KNODE-MHE (and their priors) over stored flights as a job; the report
is workflows.flights.evaluate_flights' JSON.  Its HTML page, /evaluations/{id}/report.html, is one
of the web pages (service.web.report_pages)."""
from __future__ import annotations

import os
from collections.abc import Iterator
from typing import BinaryIO

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.responses import StreamingResponse

from learnest.estimators.export import FORMATS, MEDIA_TYPES

from ...config import Settings
from ...jobs.evaluation import start_evaluation
from ...jobs.services import Services
from ...operations import comparison, deletion
from ...operations.catalog import row_and_job
from ...operations.exports import cached_export, export_filename
from ...storage.blobs import CHUNK, BlobStore
from ...storage.database import Database
from ...storage.tables import Evaluation
from ..deps import (
    MAX_ROW_ID,
    Offset,
    RowId,
    actor,
    creator,
    get_blobs,
    get_db,
    get_services,
    get_settings,
    pending,
)
from ..report_models import EvaluationReportOut
from ..schemas import (
    Dependents,
    EvaluationAccepted,
    EvaluationPage,
    EvaluationPending,
    EvaluationRequest,
)

router = APIRouter(prefix="/evaluations", tags=["evaluations"])


@router.post("", status_code=202, response_model=EvaluationAccepted)
def create_evaluation(body: EvaluationRequest, request: Request, response: Response,
                      services: Services = Depends(get_services)):
    """Flights already evaluated with this model version and these settings come from the results cache;
    when all of them do, the job is already "succeeded" in this answer."""
    job_id, evaluation_id, state = start_evaluation(services, body.model, body.flights, body.settings,
                                                    created_by=creator(request))
    response.headers["Location"] = f"/evaluations/{evaluation_id}"
    return {"job_id": job_id, "evaluation_id": evaluation_id, "state": state}


@router.get("", response_model=EvaluationPage)
def list_evaluations(q: str | None = Query(None, max_length=220, description="only evaluations whose model "
                                                                            "reference contains this"),
                     model: str | None = Query(None, max_length=100, description="only this model's evaluations"),
                     limit: int = Query(50, ge=1, le=500), offset: Offset = 0, db: Database = Depends(get_db)):
    """One page of evaluations, newest first: state, model version, median MSE per method and the KNODE
    improvements in percent, with links to the report, the model version and the job."""
    total, items = comparison.list_evaluations(db, q=q, model=model, limit=limit, offset=offset)
    return {"items": items, "total": total, "limit": limit, "offset": offset}


@router.get("/{evaluation_id}/dependents", response_model=Dependents)
def evaluation_dependents(evaluation_id: RowId, db: Database = Depends(get_db)):
    """What a DELETE of this evaluation deletes with it (its report figures) and what stays (its job)."""
    return deletion.evaluation_dependents(db, evaluation_id)


@router.delete("/{evaluation_id}", status_code=204,
               responses={404: {"description": "no such evaluation"},
                          409: {"description": "its job is still queued or running: cancel it first"}})
def delete_evaluation(evaluation_id: RowId, request: Request, db: Database = Depends(get_db),
                      blobs: BlobStore = Depends(get_blobs)):
    """Delete an evaluation and its report figures.  The per-flight results it used stay cached (they are
    shared by every evaluation of that version with those settings, and go with the version or the flight);
    its job stays in the job list."""
    deletion.delete_evaluation(db, blobs, evaluation_id, actor=actor(request))
    return Response(status_code=204)


@router.get("/{evaluation_id}", response_model=EvaluationReportOut, response_model_exclude_unset=True,  # as stored
            responses={200: {"description": "the report (evaluate_flights' JSON)"},
                                           202: {"model": EvaluationPending, "description": "not finished yet"},
                                           409: {"description": "the evaluation job failed"}})
def evaluation_report(evaluation_id: RowId, db: Database = Depends(get_db)):
    """The evaluation report: 200 when the job succeeded, 202 with its state while it runs, 409 if it failed."""
    evaluation, job = row_and_job(db, Evaluation, evaluation_id, "evaluation")
    if job.state != "succeeded":
        return pending("evaluation", evaluation, job)
    return evaluation.report


@router.get("/{evaluation_id}/estimates",
            responses={200: {"description": "the estimates file (CSV, Parquet or MCAP)",
                             "content": {MEDIA_TYPES[f]: {} for f in FORMATS}},
                       202: {"model": EvaluationPending, "description": "not finished yet"},
                       400: {"description": "unknown format (the message names the allowed ones)"},
                       404: {"description": "no such evaluation, or the flight is not one of its flights"},
                       409: {"description": "the job failed, the flight was not scored, or no estimates were "
                                            "stored"},
                       507: {"description": "the export does not fit in the disk budget of estimate exports "
                                            "(LEARNEST_EXPORT_BUDGET_MB)"}})
def evaluation_estimates_file(evaluation_id: RowId,
                              format: str = Query("csv", description=f"one of {', '.join(FORMATS)}"),
                              flight: int | None = Query(None, ge=1, le=MAX_ROW_ID,
                                                         description="only this flight (default: every scored "
                                                                     "flight)"),
                              db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs),
                              settings: Settings = Depends(get_settings)):
    """The per-step state estimates of every method on every scored flight, with the Savitzky–Golay reference,
    the error and the measurement: a tidy table (CSV, Parquet; unit-suffixed columns) or an MCAP with Foxglove
    schemas (topics /learnest/<method>/position|velocity|acceleration|pose and /learnest/reference/...)."""
    if format not in FORMATS:
        raise HTTPException(400, f"unknown format {format!r}; choose one of {', '.join(FORMATS)}")
    evaluation, job = row_and_job(db, Evaluation, evaluation_id, "evaluation")
    if job.state != "succeeded":
        return pending("evaluation", evaluation, job)
    # made once and kept (service.storage.export_cache): every download of it reads the same file, from disk
    handle = cached_export(db, blobs, settings.export_budget_bytes, evaluation_id, format, flight)
    return StreamingResponse(_chunks(handle), media_type=MEDIA_TYPES[format], headers={
        "Content-Length": str(os.fstat(handle.fileno()).st_size),
        "Content-Disposition": f'attachment; filename="{export_filename(evaluation_id, format, flight)}"'})


def _chunks(handle: BinaryIO) -> Iterator[bytes]:
    """The open export, a chunk at a time; closed when sent or when the client is gone."""
    with handle:
        yield from iter(lambda: handle.read(CHUNK), b"")
