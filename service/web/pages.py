"""The web pages' routes: server-rendered HTML for people, on the same app as the JSON API (no JavaScript).

Pages   /                       flights (newest first; search: ?q=) and the upload form
        /ui/flights/{id}        metadata, quality, trajectory plot (x-y, z-t), models trained on it, train form
        /ui/models              registered models (search: ?q=)
        /ui/models/{name}       versions, aliases (+ form), loss curves, evaluations, evaluate form
        /ui/jobs, /ui/jobs/{id} state, progress, stage and time left; a job page reloads itself every second
                                until it is done and has a cancel button while it is
Forms   POST /ui/flights, /ui/models, /ui/evaluations, /ui/diagnoses, /ui/models/{name}/aliases,
        /ui/jobs/{id}/cancel take the
        same request models as the JSON routes (service.web.forms), call the same service functions
        (service.operations.uploads, service.jobs, service.operations.catalog) and answer 303 to the page of what
        they made, or an HTML error page with the API's status code and message.

The evaluations list, version pages, comparisons and delete confirmations are service.web.registry_pages; the
evaluation and diagnosis reports (/evaluations/{id}/report.html, /diagnoses/{id}/report.html) are
service.web.report_pages, whose routers `router` serves with these pages.

Every page is a Jinja2 template extending templates/base.html with autoescaping on (service.web.rendering), so
text from users (names, notes, file names, error messages) is escaped unless a template says otherwise - and
none does.
"""
from __future__ import annotations

import json
import logging

from fastapi import APIRouter, Depends, File, Form, Query, Request, UploadFile
from fastapi.responses import FileResponse, HTMLResponse

from learnest.ingest.flight import Flight as CanonicalFlight
from learnest.models.presets import (
    MHE_HORIZON,
)
from learnest.workflows.headline import diagnosis_headline, evaluation_headline

from ..api.deps import Offset, RowId, actor, creator, get_services
from ..jobs.diagnosis import start_diagnosis
from ..jobs.evaluation import start_evaluation
from ..jobs.runner import ACTIVE, seconds_left
from ..jobs.services import Services
from ..jobs.training import start_training
from ..local import figures
from ..operations import catalog
from ..operations.uploads import add_flights, recut_flight
from ..storage.tables import FlightRecord, Job
from . import flight_plots, forms, page_cache, zoomable
from .registry_figures import loss_curves_of
from .rendering import PAGE_SIZE, error_page, html_errors, page
from .report_pages import diagnosis_reports, reports

log = logging.getLogger("learnest.web")

EVALUATIONS_SHOWN = 20   # on a model's page

pages = APIRouter(include_in_schema=False)


# -- flights ---------------------------------------------------------------------------------------------
@pages.get("/", response_class=HTMLResponse)
def flights_page(request: Request, offset: Offset = 0, q: str = Query("", max_length=200),
                 services: Services = Depends(get_services)):
    """The home page: flights newest first (PAGE_SIZE per page, from `offset`; those whose name contains `q`)
    and the upload form."""
    total, rows = catalog.list_flights(services.db, *catalog.name_contains(q.strip()), limit=PAGE_SIZE,
                                       offset=offset, newest_first=True)
    return page("flights.html", "Flights", flights=rows, total=total, offset=offset, q=q,
                key=forms.form_access(request))


@pages.post("/ui/flights")
@html_errors
def upload_flight_form(request: Request, files: list[UploadFile | str] = File(default=[]),
                       vehicle: str = Form(""), notes: str = Form(""), pose_topic: str = Form(""),
                       imu_topic: str = Form(""), cut: str = Form(""),
                       services: Services = Depends(get_services)):
    """Upload form: store the flights among the chosen files (as POST /flights/batch does).  One flight read:
    303 to its page; one flight refused: the error page; otherwise a page that says per file what was stored,
    found stored already or refused and why."""
    chosen = forms.chosen_files(files)
    outcomes = add_flights(services.db, services.blobs, chosen, *forms.upload_text(vehicle, notes),
                           pose_topic=pose_topic, imu_topic=imu_topic, cut=cut.strip() or None,
                           decode=services.decoder.decode, created_by=creator(request))
    rows = {o.flight.id: o.flight for o in outcomes if o.flight is not None}
    refused = [o for o in outcomes if o.status == "refused"]
    if len(rows) == 1 and not refused:
        return forms.redirect(f"/ui/flights/{next(iter(rows))}")
    if not rows and len({o.message for o in refused}) == 1:   # one flight (its file(s)), refused
        return error_page(refused[0].http_status or 422, refused[0].message or "refused")
    statuses = [o.status for o in outcomes]
    return page("upload_results.html", "Upload", 201 if "stored" in statuses else 200 if rows else 422,
                outcomes=outcomes,
                stored=len({o.flight.id for o in outcomes if o.status == "stored" and o.flight is not None}),
                existing=len({o.flight.id for o in outcomes
                              if o.status == "existing" and o.flight is not None}), refused=len(refused))


@pages.post("/ui/flights/{flight_id}/cut")
@html_errors
def cut_flight_form(request: Request, flight_id: RowId, cut: str = Form(""),
                    services: Services = Depends(get_services)):
    """Cut form: read the flight's raw file(s) again with the cut asked for (as POST /flights/{id}/cut does),
    then 303 to the flight holding that stretch."""
    row = catalog.get_flight(services.db, flight_id)
    new, _created = recut_flight(services.db, services.blobs, row, cut.strip() or None,
                                 decode=services.decoder.decode, created_by=creator(request))
    return forms.redirect(f"/ui/flights/{new.id}")


@pages.get("/ui/flights/{flight_id}", response_class=HTMLResponse)
@html_errors
def flight_page(request: Request, flight_id: RowId, services: Services = Depends(get_services)):
    """A flight's page: metadata, quality, trajectory plot, models trained on it, train form."""
    row = catalog.get_flight(services.db, flight_id)
    return page("flight.html", f"Flight {row.id}: {row.name}", flight=row,
                trained=catalog.versions_trained_on(services.db, flight_id),
                trajectory=_trajectory(services, row), key=forms.form_access(request),
                metadata=json.dumps(row.meta, indent=1))


def _trajectory(services: Services, row: FlightRecord) -> dict:
    """{"png": data URI of the top view, "channels": zoomable spec of every channel} or {"error": why}: a
    missing or damaged blob is said, the rest of the page shown.  Drawn once per flight content (the blob's
    sha names it), then served from the page cache."""
    return page_cache.pages.get(("flight-figures", row.flight_blob, row.name), lambda: _draw_trajectory(services, row),
                                keep=lambda drawn: "error" not in drawn)


def _draw_trajectory(services: Services, row: FlightRecord) -> dict:
    try:
        flight = CanonicalFlight.from_bytes(services.blobs.read_bytes(row.flight_blob))
    except (OSError, ValueError, KeyError) as err:
        return {"error": type(err).__name__}
    return {"png": figures.png_data_uri(figures.trajectory(flight, row.name)),
            "channels": zoomable.embed(flight_plots.flight_figure(flight))}


# -- models ----------------------------------------------------------------------------------------------
@pages.post("/ui/models")
@html_errors
def train_model_form(request: Request, name: str = Form(""), flight_id: str = Form(""), epochs: str = Form(""),
                     include_bad: str | None = Form(None),
                     flight_ids: list[str] = Form(default=[]), system: str = Form(""), group_by: str = Form(""),
                     services: Services = Depends(get_services)):
    """Train form (a flight's page: that flight; the flight list: the checked flights, several making one
    model of one vehicle): start a training job (as POST /models does), then 303 to the job's page."""
    body = forms.train_request(name, flight_id, epochs, include_bad, flight_ids, system, group_by)
    job, _version = start_training(services, body.name, body.flights(), {"epochs": body.epochs,
                                                                          "system": body.system,
                                                                          "group_by": body.group_by},
                                   include_bad=body.include_bad, created_by=creator(request))
    return forms.redirect(f"/ui/jobs/{job.id}")


@pages.get("/ui/models", response_class=HTMLResponse)
def models_page(q: str = Query("", max_length=100), services: Services = Depends(get_services)):
    """The registered models (those whose name contains `q`)."""
    return page("models.html", "Models", models=catalog.list_models(services.db, q=q.strip() or None), q=q)


@pages.get("/ui/models/{name}", response_class=HTMLResponse)
@html_errors
def model_page(request: Request, name: str, services: Services = Depends(get_services)):
    """A model's page: versions, aliases and alias form, loss curves of its ready versions, its latest evaluations and
    the evaluate form.
    """
    model = catalog.get_model(services.db, name)
    ready = [v for v in model.versions if v.status == "ready"]
    _total, flights = catalog.list_flights(services.db, limit=PAGE_SIZE, newest_first=True)
    evaluations = catalog.evaluations_of(services.db, model.versions, EVALUATIONS_SHOWN)
    # the answer of the newest finished evaluation leads the page (what the model does where it was scored)
    latest = next(((ev, evaluation_headline(ev.report)) for ev, job in evaluations
                   if job is not None and job.state == "succeeded" and ev.report), None)
    return page("model.html", f"Model {name}", name=name, model=model, ready=ready, flights=flights,
                latest=latest, evaluations=evaluations,
                losses=loss_curves_of([{"ref": f"{name}:{v.version}", "losses": v.losses,
                                        "validation_losses": v.validation_losses} for v in ready]),
                no_losses=[v.version for v in ready if not v.losses],
                still_falling=[v.version for v in ready if still_falling(v.losses)],
                key=forms.form_access(request))


STILL_FALLING_SHARE = 0.02   # the last tenth of the epochs lowered the loss by more than this share


def still_falling(losses: list | None) -> bool:
    """Whether a training loss was still falling at its last epoch: the best of its last tenth of epochs
    is more than `STILL_FALLING_SHARE` below the best before it (more epochs would likely lower it)."""
    values = [x for x in (losses or []) if x is not None]
    if len(values) < 10:
        return False
    tail = max(1, len(values) // 10)
    return min(values[-tail:]) < (1.0 - STILL_FALLING_SHARE) * min(values[:-tail])


@pages.post("/ui/models/{name}/aliases")
@html_errors
def alias_form_post(request: Request, name: str, alias: str = Form(""), version: str = Form(""),
                    services: Services = Depends(get_services)):
    """Alias form: point name@alias at a version, then 303 to the model's page."""
    catalog.set_alias(services.db, name, alias.strip(), forms.alias_version(version), actor=actor(request))
    return forms.redirect(f"/ui/models/{name}")


@pages.post("/ui/evaluations")
@html_errors
def evaluate_form_post(request: Request, model: str = Form(""), flights: list[str] = Form(default=[]),
                       methods: list[str] = Form(default=[]), horizon: str = Form(str(MHE_HORIZON)),
                       include_bad: str | None = Form(None), sg_window: str = Form(""),
                       services: Services = Depends(get_services)):
    """Evaluate form: start an evaluation job (as POST /evaluations does), then 303 to the job's page."""
    body = forms.evaluation_request(model, flights, methods, horizon, include_bad, sg_window)
    job_id, _evaluation_id, _state = start_evaluation(services, body.model, body.flights, body.settings,
                                                      created_by=creator(request))
    return forms.redirect(f"/ui/jobs/{job_id}")


@pages.post("/ui/diagnoses")
@html_errors
def diagnose_form_post(request: Request, flights: list[str] = Form(default=[]), model: str = Form(""),
                       system: str = Form("quadrotor"), methods: list[str] = Form(default=[]), epochs: str = Form(""),
                       register_checked: str | None = Form(None, alias="register"), register_as: str = Form(""),
                       services: Services = Depends(get_services)):
    """Diagnose form: start a diagnosis job (as POST /diagnoses does), then 303 to the job's page."""
    body = forms.diagnosis_request(flights, model, system, methods, epochs, register_checked, register_as)
    job_id, _diagnosis_id = start_diagnosis(services, body.flights, body.model, body.register_as, body.methods,
                                            body.epochs, body.system, created_by=creator(request))
    return forms.redirect(f"/ui/jobs/{job_id}")


# -- jobs ------------------------------------------------------------------------------------------------
@pages.get("/ui/jobs", response_class=HTMLResponse)
def jobs_page(services: Services = Depends(get_services)):
    """The latest jobs (PAGE_SIZE), newest first; reloads every 2 s while one of them is active."""
    _total, jobs = catalog.list_jobs(services.db, limit=PAGE_SIZE)
    running = any(j.state in ACTIVE for j in jobs)
    return page("jobs.html", "Jobs", refresh_s=2 if running else None,
                jobs=[(j, job_subject(j)) for j in jobs])


@pages.get("/ui/jobs/{job_id}", response_class=HTMLResponse)
@html_errors
def job_page(request: Request, job_id: RowId, services: Services = Depends(get_services)):
    """A job's page: state, progress and result; reloads every second while the job is active (and offers
    to cancel it)."""
    job = catalog.get_job(services.db, job_id)
    evaluation = catalog.evaluation_of_job(services.db, job_id)
    diagnosis = catalog.diagnosis_of_job(services.db, job_id) if job.kind == "diagnosis" else None
    active, key = job.state in ACTIVE, forms.form_access(request)
    answer = None   # a finished evaluation's or diagnosis' answer, as its report page says it first
    if job.state == "succeeded" and evaluation is not None and evaluation.report:
        answer = evaluation_headline(evaluation.report)["sentence"]
    elif job.state == "succeeded" and diagnosis is not None and diagnosis.report:
        answer = diagnosis_headline(diagnosis.report)
    return page("job.html", f"Job {job.id}", refresh_s=1 if active else None, job=job, answer=answer,
                eta_s=seconds_left(job),
                active=active, subject=job_subject(job), evaluation=evaluation, key=key, diagnosis=diagnosis,
                model_name=evaluation.model_ref.split(":", 1)[0] if evaluation else None,
                result=json.dumps(job.result, indent=1) if job.result else None)


@pages.post("/ui/jobs/{job_id}/cancel")
@html_errors
def cancel_job_form(job_id: RowId,
                    services: Services = Depends(get_services)):
    """Cancel button: cancel the job (as POST /jobs/{id}/cancel does), then 303 back to its page."""
    services.runner.cancel(job_id)
    return forms.redirect(f"/ui/jobs/{job_id}")


def job_subject(job: Job) -> str:
    """What a job works on, in a few words ("quad on flight 3", "quad:1 on 4 flight(s)")."""
    payload = job.payload or {}
    if job.kind == "training":
        if len(payload.get("flight_ids") or []) > 1:
            return f"{payload.get('name')} on {len(payload['flight_ids'])} flights"
        return f"{payload.get('name')} on flight {payload.get('flight_id')}"
    if job.kind == "diagnosis":
        return f"diagnosis of {payload.get('model') or 'a model trained on the fitting flight'} on " \
               f"{len(payload.get('flights') or [])} flight(s)"
    return f"{payload.get('model')} on {len(payload.get('flights') or [])} flight(s)"


@pages.get(zoomable.PLOTLY_JS_ROUTE)
def plotly_js():
    """plotly.js from the installed `plotly` package (pages need no CDN); cached by browsers for a day."""
    return FileResponse(zoomable.plotly_js_path(), media_type="text/javascript",
                        headers={"Cache-Control": "public, max-age=86400"})


# One router for the app: the pages (left out of the OpenAPI schema) and the report (in it).
router = APIRouter()
router.include_router(pages)
router.include_router(reports)
router.include_router(diagnosis_reports)
