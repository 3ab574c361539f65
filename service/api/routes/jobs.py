"""/jobs: the state, progress and result of long work (training, evaluations, diagnoses), and cancelling it."""
from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Depends, Query

from ...jobs.runner import seconds_left
from ...jobs.services import Services
from ...operations import catalog
from ...storage.database import Database
from ...storage.tables import Job
from ..deps import Offset, RowId, get_db, get_services
from ..schemas import JobOut

router = APIRouter(prefix="/jobs", tags=["jobs"])


def job_out(job: Job) -> dict:
    """A job row as the API's JSON (JobOut)."""
    return {"id": job.id, "kind": job.kind, "state": job.state, "progress": job.progress,
            "stage": job.stage if job.state == "running" else None, "eta_s": seconds_left(job), "error": job.error,
            "result": job.result, "created_at": job.created_at, "started_at": job.started_at,
            "finished_at": job.finished_at}


@router.get("/{job_id}", response_model=JobOut)
def job_detail(job_id: RowId, db: Database = Depends(get_db)):
    """One job: state, progress, error and result; 404 when there is none."""
    return job_out(catalog.get_job(db, job_id))


@router.post("/{job_id}/cancel", response_model=JobOut,
             responses={404: {"description": "no such job"}, 409: {"description": "the job already finished"}})
def cancel_job(job_id: RowId, services: Services = Depends(get_services)):
    """Cancel a queued or running job: it is "cancelled" in this answer, its worker stops (a running task gets
    LEARNEST_CANCEL_GRACE_S to stop, then is killed) and nothing it computed is stored; a training job's
    reserved version is failed.  Cancelling a cancelled job changes nothing; 409 for a finished one."""
    return job_out(services.runner.cancel(job_id))


@router.get("", response_model=dict)
def list_jobs(state: Literal["queued", "running", "succeeded", "failed", "cancelled"] | None = None,
              kind: str | None = None, limit: int = Query(50, ge=1, le=500), offset: Offset = 0,
              db: Database = Depends(get_db)):
    """Newest first."""
    conditions = [c for c in (Job.state == state if state else None, Job.kind == kind if kind else None)
                  if c is not None]
    total, jobs = catalog.list_jobs(db, *conditions, limit=limit, offset=offset)
    return {"items": [JobOut(**job_out(j)).model_dump(mode="json") for j in jobs], "total": total}
