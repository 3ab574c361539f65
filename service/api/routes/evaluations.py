"""/evaluations: batch KNODE-UKF / KNODE-MHE (and their priors) over stored flights as a job; the report
is service.experiments.flights.evaluate_flights' JSON.  Its HTML page, /evaluations/{id}/report.html, is one
of the web pages (service.web.pages)."""
from __future__ import annotations

from fastapi import APIRouter, Depends, Response

from ...catalog import row_and_job
from ...jobs.evaluation import start_evaluation
from ...jobs.result_cache import EstimatorSettings
from ...jobs.services import Services
from ...storage.database import Database
from ...storage.tables import Evaluation
from ..deps import RowId, get_db, get_services, pending, require_api_key
from ..schemas import EvaluationAccepted, EvaluationPending, EvaluationRequest

router = APIRouter(prefix="/evaluations", tags=["evaluations"])


@router.post("", status_code=202, response_model=EvaluationAccepted, dependencies=[Depends(require_api_key)])
def create_evaluation(body: EvaluationRequest, response: Response, services: Services = Depends(get_services)):
    """Flights already evaluated with this model version and these settings come from the results cache;
    when all of them do, the job is already "succeeded" in this answer."""
    settings = EstimatorSettings(tuple(body.methods), body.horizon, body.include_bad)
    job_id, evaluation_id, state = start_evaluation(services, body.model, body.flights, settings)
    response.headers["Location"] = f"/evaluations/{evaluation_id}"
    return {"job_id": job_id, "evaluation_id": evaluation_id, "state": state}


@router.get("/{evaluation_id}", responses={200: {"description": "the report (evaluate_flights' JSON)"},
                                           202: {"model": EvaluationPending, "description": "not finished yet"},
                                           409: {"description": "the evaluation job failed"}})
def evaluation_report(evaluation_id: RowId, db: Database = Depends(get_db)):
    """The evaluation report: 200 when the job succeeded, 202 with its state while it runs, 409 if it failed."""
    evaluation, job = row_and_job(db, Evaluation, evaluation_id, "evaluation")
    if job.state != "succeeded":
        return pending("evaluation", evaluation, job)
    return evaluation.report
