"""/diagnoses: `learnest diagnose` on stored flights as a job; the report is service.diagnose.diagnose_flights'
JSON, plus "registered" when the repaired model was registered as a new version."""
from __future__ import annotations

from fastapi import APIRouter, Depends, Request, Response
from fastapi.responses import JSONResponse

from ...jobs.diagnosis import start_diagnosis
from ...jobs.services import Services
from ...operations.catalog import row_and_job
from ...storage.database import Database
from ...storage.tables import Diagnosis
from ..deps import RowId, creator, get_db, get_services, pending
from ..report_models import DiagnosisReportOut
from ..schemas import DiagnosisAccepted, DiagnosisPending, DiagnosisRequest

router = APIRouter(prefix="/diagnoses", tags=["diagnoses"])


@router.post("", status_code=202, response_model=DiagnosisAccepted)
def create_diagnosis(body: DiagnosisRequest, request: Request, response: Response,
                     services: Services = Depends(get_services)):
    """Trace the residual to named effects, add them, retrain the KNODE on top and score before/after; with
    `register`, the repaired model becomes the next version of that name (parent: `model`)."""
    job_id, diagnosis_id = start_diagnosis(services, body.flights, body.model, body.register_as, body.methods,
                                           body.epochs, body.system, force=body.force, created_by=creator(request))
    response.headers["Location"] = f"/diagnoses/{diagnosis_id}"
    return {"job_id": job_id, "diagnosis_id": diagnosis_id}


@router.get("/{diagnosis_id}", response_model=DiagnosisReportOut,
            responses={200: {"description": "the report (diagnose_flights' JSON)"},
                                          202: {"model": DiagnosisPending, "description": "not finished yet"},
                                          409: {"description": "the diagnosis job failed"}})
def diagnosis_report(diagnosis_id: RowId, db: Database = Depends(get_db)):
    """The diagnosis report: 200 when the job succeeded, 202 with its state while it runs, 409 if it failed."""
    diagnosis, job = row_and_job(db, Diagnosis, diagnosis_id, "diagnosis")
    if job.state != "succeeded":
        return pending("diagnosis", diagnosis, job)
    # the stored JSON as it is (its schema, DiagnosisReportOut, documents it; old reports keep their keys)
    return JSONResponse({**diagnosis.report, "registered": diagnosis.registered})
