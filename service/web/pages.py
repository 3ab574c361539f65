"""The web pages' routes: server-rendered HTML for people, on the same app as the JSON API (no JavaScript).

Pages   /                       flights (newest first; search: ?q=) and the upload form
        /ui/flights/{id}        metadata, quality, trajectory plot (x-y, z-t), models trained on it, train form
        /ui/models              registered models (search: ?q=)
        /ui/models/{name}       versions, aliases (+ form), loss curves, evaluations, evaluate form
        /ui/jobs, /ui/jobs/{id} state, progress, stage and time left; a job page reloads itself every second
                                until it is done and has a cancel button while it is
        /evaluations/{id}/report.html
                                the Fig. 3-style box plot, per-flight MSE table, estimated vs reference velocity
                                of one chosen flight (documented in the OpenAPI schema with the JSON report)
        /diagnoses/{id}/report.html
                                effects with units, intervals and alternatives, residual over time before/after,
                                held-out error before/after per flight (linear axes)
Forms   POST /ui/flights, /ui/models, /ui/evaluations, /ui/diagnoses, /ui/models/{name}/aliases,
        /ui/jobs/{id}/cancel take the
        same request models as the JSON routes (service.web.forms), call the same service functions
        (service.operations.uploads, service.jobs, service.operations.catalog) and answer 303 to the page of what
        they made, or an HTML error page with the API's status code and message.

The evaluations list, version pages, comparisons and delete confirmations are service.web.registry_pages.

Every page is a Jinja2 template extending templates/base.html with autoescaping on, so text from users
(names, notes, file names, error messages) is escaped unless a template says otherwise - and none does.
"""
from __future__ import annotations

import functools
import json
import logging
from collections.abc import Callable
from typing import Literal

from fastapi import APIRouter, Depends, File, Form, Query, Request, UploadFile
from fastapi.responses import FileResponse, HTMLResponse
from jinja2 import Environment, PackageLoader, StrictUndefined, select_autoescape
from pydantic import ValidationError
from sqlalchemy import func, select

from learnest.errors import LearnestError
from learnest.ingest.baseline import centred_window
from learnest.ingest.flight import Flight as CanonicalFlight
from learnest.models.crazyflie import UNITS as CRAZYFLIE_UNITS
from learnest.models.presets import (
    CRAZYFLIE_TRAINING,
    DIAGNOSIS_SPLIT_RULE,
    METHODS,
    MHE_HORIZON,
    SG_WINDOW,
    SG_WINDOW_RANGE,
)

from ..api.deps import MAX_ROW_ID, Offset, RowId, get_services
from ..jobs.diagnosis import start_diagnosis
from ..jobs.evaluation import start_evaluation
from ..jobs.result_cache import EstimatorSettings
from ..jobs.runner import ACTIVE, seconds_left
from ..jobs.services import Services
from ..jobs.training import start_training
from ..operations import catalog
from ..operations.exports import evaluation_estimates
from ..operations.uploads import add_flights, recut_flight
from ..storage import references
from ..storage.tables import Diagnosis, Evaluation, FlightRecord, Job, ReportFigure, Result
from . import evaluation_plots, figures, flight_plots, forms, page_cache, zoomable
from .headline import diagnosis_headline, diagnosis_split, evaluation_headline, gap_methods
from .registry_figures import loss_curves_of
from .report_figures import velocity_figure

log = logging.getLogger("learnest.web")

PAGE_SIZE = 100
EVALUATIONS_SHOWN = 20   # on a model's page


# -- rendering ---------------------------------------------------------------------------------------------
def _when(moment) -> str:
    return moment.strftime("%Y-%m-%d %H:%M:%S") if moment else ""


TEMPLATES = Environment(loader=PackageLoader("learnest.service.web", "templates"),
                        autoescape=select_autoescape(default=True, default_for_string=True),
                        undefined=StrictUndefined,          # a misspelt variable fails the page (and the tests)
                        finalize=lambda value: "" if value is None else value,  # None shows as nothing
                        trim_blocks=True, lstrip_blocks=True)
def _duration(seconds: float) -> str:
    """"42 s", "3 min 20 s", "1 h 05 min"."""
    seconds = round(seconds)
    if seconds < 60:
        return f"{seconds} s"
    if seconds < 3600:
        return f"{seconds // 60} min {seconds % 60:02d} s"
    return f"{seconds // 3600} h {seconds % 3600 // 60:02d} min"


TEMPLATES.filters["when"] = _when
TEMPLATES.filters["duration"] = _duration
TEMPLATES.globals.update(NAME_PATTERN=references.NAME, METHODS=METHODS, MHE_HORIZON=MHE_HORIZON,
                         VELOCITY_METHODS=figures.VELOCITY_METHODS, MAX_VEHICLE=forms.MAX_VEHICLE,
                         MAX_NOTES=forms.MAX_NOTES, PAGE_SIZE=PAGE_SIZE,
                         DEFAULT_EPOCHS=CRAZYFLIE_TRAINING.epochs, SG_WINDOW=SG_WINDOW,
                         SG_WINDOW_RANGE=SG_WINDOW_RANGE, PLOTLY_JS_ROUTE=zoomable.PLOTLY_JS_ROUTE,
                         DIAGNOSIS_SPLIT_RULE=DIAGNOSIS_SPLIT_RULE,
                         MIN_GAP_S=flight_plots.MIN_GAP_S,
                         VELOCITY_SG_S=flight_plots.VELOCITY_SG_S)


def page(template: str, title: str, status: int = 200, refresh_s: float | None = None, **context) -> HTMLResponse:
    """Render templates/`template` (which extends base.html) as a response.

    Parameters
    ----------
    template : str
        File name under templates/.
    title : str
        The page's <title> and <h1> (escaped).
    status : int
        HTTP status of the answer.
    refresh_s : float, optional
        Reload the page after this many seconds (pages of running jobs).
    **context
        The template's variables.
    """
    html = TEMPLATES.get_template(template).render(title=title, refresh_s=refresh_s, **context)
    return HTMLResponse(html, status_code=status)


def error_page(status: int, message: str) -> HTMLResponse:
    """The API's status code and message as a page (a form post never gets JSON back)."""
    return page("error.html", f"Error {status}", status, message=message)


def html_errors(handler: Callable) -> Callable:
    """Show the service's errors (LearnestError: its status) and bad form fields (422) as an error page."""
    @functools.wraps(handler)
    def wrapper(*args, **kwargs):
        try:
            return handler(*args, **kwargs)
        except ValidationError as err:
            return error_page(422, forms.validation_message(err))
        except LearnestError as err:
            return error_page(err.status, str(err))
    return wrapper


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
                key=forms.key_state(request, services.settings))


@pages.post("/ui/flights")
@html_errors
def upload_flight_form(request: Request, files: list[UploadFile | str] = File(default=[]),
                       vehicle: str = Form(""), notes: str = Form(""), pose_topic: str = Form(""),
                       imu_topic: str = Form(""), cut: str = Form(""), api_key: str = Form(""),
                       services: Services = Depends(get_services)):
    """Upload form: store the flights among the chosen files (as POST /flights/batch does).  One flight read:
    303 to its page; one flight refused: the error page; otherwise a page that says per file what was stored,
    found stored already or refused and why."""
    forms.require_key(request, services.settings, api_key)
    chosen = forms.chosen_files(files)
    outcomes = add_flights(services.db, services.blobs, chosen, *forms.upload_text(vehicle, notes),
                           pose_topic=pose_topic, imu_topic=imu_topic, cut=cut.strip() or None,
                           decode=services.decoder.decode)
    rows = {o.flight.id: o.flight for o in outcomes if o.flight is not None}
    refused = [o for o in outcomes if o.status == "refused"]
    if len(rows) == 1 and not refused:
        return forms.redirect(f"/ui/flights/{next(iter(rows))}", services.settings, api_key)
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
def cut_flight_form(request: Request, flight_id: RowId, cut: str = Form(""), api_key: str = Form(""),
                    services: Services = Depends(get_services)):
    """Cut form: read the flight's raw file(s) again with the cut asked for (as POST /flights/{id}/cut does),
    then 303 to the flight holding that stretch."""
    forms.require_key(request, services.settings, api_key)
    row = catalog.get_flight(services.db, flight_id)
    new, _created = recut_flight(services.db, services.blobs, row, cut.strip() or None,
                                 decode=services.decoder.decode)
    return forms.redirect(f"/ui/flights/{new.id}", services.settings, api_key)


@pages.get("/ui/flights/{flight_id}", response_class=HTMLResponse)
@html_errors
def flight_page(request: Request, flight_id: RowId, services: Services = Depends(get_services)):
    """A flight's page: metadata, quality, trajectory plot, models trained on it, train form."""
    row = catalog.get_flight(services.db, flight_id)
    return page("flight.html", f"Flight {row.id}: {row.name}", flight=row,
                trained=catalog.versions_trained_on(services.db, flight_id),
                trajectory=_trajectory(services, row), key=forms.key_state(request, services.settings),
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
                     include_bad: str | None = Form(None), api_key: str = Form(""),
                     flight_ids: list[str] = Form(default=[]), system: str = Form(""),
                     services: Services = Depends(get_services)):
    """Train form (a flight's page: that flight; the flight list: the checked flights, several making one
    model of one vehicle): start a training job (as POST /models does), then 303 to the job's page."""
    forms.require_key(request, services.settings, api_key)
    body = forms.train_request(name, flight_id, epochs, include_bad, flight_ids, system)
    job, _version = start_training(services, body.name, body.flights(), {"epochs": body.epochs,
                                                                          "system": body.system},
                                   include_bad=body.include_bad)
    return forms.redirect(f"/ui/jobs/{job.id}", services.settings, api_key)


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
                key=forms.key_state(request, services.settings))


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
                    api_key: str = Form(""), services: Services = Depends(get_services)):
    """Alias form: point name@alias at a version, then 303 to the model's page."""
    forms.require_key(request, services.settings, api_key)
    catalog.set_alias(services.db, name, alias.strip(), forms.alias_version(version))
    return forms.redirect(f"/ui/models/{name}", services.settings, api_key)


@pages.post("/ui/evaluations")
@html_errors
def evaluate_form_post(request: Request, model: str = Form(""), flights: list[str] = Form(default=[]),
                       methods: list[str] = Form(default=[]), horizon: str = Form(str(MHE_HORIZON)),
                       include_bad: str | None = Form(None), sg_window: str = Form(""), api_key: str = Form(""),
                       services: Services = Depends(get_services)):
    """Evaluate form: start an evaluation job (as POST /evaluations does), then 303 to the job's page."""
    forms.require_key(request, services.settings, api_key)
    body = forms.evaluation_request(model, flights, methods, horizon, include_bad, sg_window)
    settings = EstimatorSettings(tuple(body.methods), body.horizon, body.include_bad, body.sg_window)
    job_id, _evaluation_id, _state = start_evaluation(services, body.model, body.flights, settings)
    return forms.redirect(f"/ui/jobs/{job_id}", services.settings, api_key)


@pages.post("/ui/diagnoses")
@html_errors
def diagnose_form_post(request: Request, flights: list[str] = Form(default=[]), model: str = Form(""),
                       system: str = Form("quadrotor"), methods: list[str] = Form(default=[]), epochs: str = Form(""),
                       register_checked: str | None = Form(None, alias="register"), register_as: str = Form(""),
                       api_key: str = Form(""),
                       services: Services = Depends(get_services)):
    """Diagnose form: start a diagnosis job (as POST /diagnoses does), then 303 to the job's page."""
    forms.require_key(request, services.settings, api_key)
    body = forms.diagnosis_request(flights, model, system, methods, epochs, register_checked, register_as)
    job_id, _diagnosis_id = start_diagnosis(services, body.flights, body.model, body.register_as, body.methods,
                                            body.epochs, body.system)
    return forms.redirect(f"/ui/jobs/{job_id}", services.settings, api_key)


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
    active, key = job.state in ACTIVE, forms.key_state(request, services.settings)
    # no reload while the cancel form asks for the key: a reload every second would wipe it mid-typing
    answer = None   # a finished evaluation's or diagnosis' answer, as its report page says it first
    if job.state == "succeeded" and evaluation is not None and evaluation.report:
        answer = evaluation_headline(evaluation.report)["sentence"]
    elif job.state == "succeeded" and diagnosis is not None and diagnosis.report:
        answer = diagnosis_headline(diagnosis.report)
    return page("job.html", f"Job {job.id}", refresh_s=1 if active and key != "ask" else None, job=job, answer=answer,
                eta_s=seconds_left(job),
                active=active, subject=job_subject(job), evaluation=evaluation, key=key, diagnosis=diagnosis,
                model_name=evaluation.model_ref.split(":", 1)[0] if evaluation else None,
                result=json.dumps(job.result, indent=1) if job.result else None)


@pages.post("/ui/jobs/{job_id}/cancel")
@html_errors
def cancel_job_form(request: Request, job_id: RowId, api_key: str = Form(""),
                    services: Services = Depends(get_services)):
    """Cancel button: cancel the job (as POST /jobs/{id}/cancel does), then 303 back to its page."""
    forms.require_key(request, services.settings, api_key)
    services.runner.cancel(job_id)
    return forms.redirect(f"/ui/jobs/{job_id}", services.settings, api_key)


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


# -- the evaluation report ---------------------------------------------------------------------------------
# A page of its own API path (/evaluations/...), documented next to the JSON report; its errors stay the
# API's JSON ones (404 unknown, 409 failed), as before it joined the site template.
reports = APIRouter(tags=["evaluations"])


@reports.get("/evaluations/{evaluation_id}/report.html", response_class=HTMLResponse,
             responses={202: {"description": "not finished yet (the page reloads itself)"},
                        409: {"description": "the evaluation job failed"}})
def evaluation_report_page(evaluation_id: RowId,
                           flight: int | None = Query(None, ge=1, le=MAX_ROW_ID,
                                                      description="flight id of the time series "
                                                                  "(default: the first scored flight)"),
                           group: Literal["p", "v", "a"] = Query("v", description="state group of the time "
                                                                "series: position, velocity or acceleration"),
                           services: Services = Depends(get_services)):
    """The evaluation report for people: per-flight MSE table and paired dots (prior vs KNODE), and for one
    flight the error over time with its running RMS and the estimates against the reference (zoomable),
    read from the stored estimates."""
    evaluation, job = catalog.row_and_job(services.db, Evaluation, evaluation_id, "evaluation")
    if job.state != "succeeded":
        return page("report_pending.html", f"Evaluation {evaluation.id}", status=202, refresh_s=2, job=job)
    # a finished evaluation's report is written once and its ids are never reused: the page changes only with
    # its flights' stored estimates (a flight deleted since) and figures, so it is drawn once per those, flight
    # and state group, then served from the page cache
    # keyed on the flight the page shows (any other ?flight= shows the first scored one): arbitrary ids in
    # the query cannot make an anonymous client redraw the same page again and again
    entries = dict(zip(evaluation.flight_ids, (evaluation.report or {}).get("flights", [])))
    scored = [fid for fid, entry in entries.items() if not entry.get("excluded")]
    flight = flight if flight in scored else (scored[0] if scored else None)
    key = ("evaluation-report", evaluation.id, flight, group, _report_inputs(services, evaluation))
    body = page_cache.pages.get(key, lambda: _report_page(services, evaluation, flight, group),
                                keep=lambda drawn: drawn[1])
    return HTMLResponse(body[0])


def _report_inputs(services: Services, evaluation: Evaluation) -> tuple:
    """What a finished evaluation's page is drawn from besides its report: the estimates blob of each of its
    flights (a deleted flight has none) and the stored report figures."""
    key = EstimatorSettings.from_dict(evaluation.settings).key
    with services.db.transaction() as session:
        shas = {row.id: row.sha256 for row in session.scalars(
            select(FlightRecord).where(FlightRecord.id.in_(list(evaluation.flight_ids))))}
        blobs = dict(session.execute(select(Result.flight_sha256, Result.estimates_blob).where(
            Result.model_version_id == evaluation.model_version_id, Result.settings_key == key,
            Result.flight_sha256.in_(list(shas.values())))).all())
        figures_stored = session.scalar(select(func.count(ReportFigure.id))
                                        .where(ReportFigure.evaluation_id == evaluation.id))
    return tuple(sorted((i, blobs.get(sha)) for i, sha in shas.items())), figures_stored


def _report_page(services: Services, evaluation: Evaluation, flight: int | None, group: str) -> tuple[bytes, bool]:
    """(the report page's HTML, whether it is final: False while its velocity figure is still computed)."""
    report = evaluation.report or {}
    title = f"Evaluation {evaluation.id}: model {report.get('model')}"
    entries = dict(zip(evaluation.flight_ids, report["flights"], strict=True))
    scored = [(fid, entry["flight"]) for fid, entry in entries.items() if not entry.get("excluded")]
    chosen = flight if flight in {fid for fid, _ in scored} else (scored[0][0] if scored else None)
    settings = EstimatorSettings.from_dict(evaluation.settings)
    series = _stored_series(services, evaluation, chosen, group, centred_window(settings.sg_window),
                            entries.get(chosen))
    head = evaluation_headline(report)
    gain = figures.gain_per_flight(head)
    # evaluated before estimates were stored: the velocity figure computed once by a task (report_figures)
    velocity = _velocity(services, evaluation, chosen) if chosen is not None and "figure" not in series else {}
    waiting = velocity.get("pending") or velocity.get("busy")
    paired = evaluation_plots.paired_figure(report)
    response = page("report.html", title, refresh_s=2 if waiting else None, evaluation=evaluation, report=report,
                head=head, gain_png=figures.png_data_uri(gain, dpi=100) if gain else None,
                gap_methods=gap_methods(report),
                gap_settings=_gap_settings(report),
                methods=list(report.get("median", {})), settings=evaluation.settings,
                sg_window=settings.sg_window, sg_window_used=centred_window(settings.sg_window),
                paired=zoomable.embed(paired) if paired else None,
                paired_png=figures.png_data_uri(figures.paired_mse(report), dpi=110) if figures.has_scores(report)
                else None,
                scored=scored, chosen=chosen, chosen_entry=entries.get(chosen), group=group,
                GROUPS=evaluation_plots.GROUPS, MSE_UNITS=evaluation_plots.MSE_UNITS, series=series,
                velocity=velocity, model_name=evaluation.model_ref.split(":", 1)[0])
    return bytes(response.body), not waiting


def _stored_series(services: Services, evaluation: Evaluation, flight_id: int | None, group: str,
                   window_used: int, entry: dict | None = None) -> dict:
    """{"figure": spec JSON, "clipping": `reference_clipping`, "difference": KNODE − prior spec JSON or None,
    "gaps": the mocap gaps shaded} from the flight's stored estimates, or {"missing": why} (no flight, or
    evaluated before estimates were stored)."""
    if flight_id is None:
        return {"missing": "no scored flight"}
    try:
        [estimates] = evaluation_estimates(services.db, services.blobs, evaluation.id, flight_id)
    except LearnestError as err:
        return {"missing": str(err)}
    gaps = evaluation_plots.gap_windows(entry, estimates.t)
    difference = evaluation_plots.difference_figure(estimates, group, gaps)
    return {"figure": zoomable.embed(evaluation_plots.error_figure(estimates, group)),
            "clipping": evaluation_plots.reference_clipping(estimates, window_used),
            "difference": zoomable.embed(difference) if difference else None, "gaps": gaps}


def _gap_settings(report: dict) -> dict | None:
    """The gap length and spacing of the first flight scored on the mocap-gap yardstick (the report's
    settings; the same for every flight of an evaluation), or None."""
    for f in report.get("flights", []):
        gaps = (f.get("yardsticks") or {}).get("mocap_gaps") or {}
        if gaps.get("gap_s") is not None and gaps.get("every_s") is not None:
            return {"gap_s": gaps["gap_s"], "every_s": gaps["every_s"]}
    return None


def _velocity(services: Services, evaluation: Evaluation, flight_id: int) -> dict:
    """The stored velocity figure, or that it is being computed (service.web.report_figures)."""
    return velocity_figure(services, evaluation, flight_id)


@pages.get(zoomable.PLOTLY_JS_ROUTE)
def plotly_js():
    """plotly.js from the installed `plotly` package (pages need no CDN); cached by browsers for a day."""
    return FileResponse(zoomable.plotly_js_path(), media_type="text/javascript",
                        headers={"Cache-Control": "public, max-age=86400"})


# -- the diagnosis report -----------------------------------------------------------------------------------
diagnosis_reports = APIRouter(tags=["diagnoses"])


@diagnosis_reports.get("/diagnoses/{diagnosis_id}/report.html", response_class=HTMLResponse,
                       responses={202: {"description": "not finished yet (the page reloads itself)"},
                                  409: {"description": "the diagnosis job failed"}})
def diagnosis_report_page(diagnosis_id: RowId, services: Services = Depends(get_services)):
    """The diagnosis report for people: effects with units, 95 % intervals and alternatives, the residual over
    time before and after, and the held-out error before and after (linear axes)."""
    from learnest.service.experiments.diagnosis import (  # numpy only; kept off app start
        confounded_label,
        how_much,
        unchanged_prior_note,
    )

    diagnosis, job = catalog.row_and_job(services.db, Diagnosis, diagnosis_id, "diagnosis")
    if job.state != "succeeded":
        return page("report_pending.html", f"Diagnosis {diagnosis.id}", status=202, refresh_s=2, job=job)
    report = diagnosis.report or {}
    series = report.get("residual_series") or {}
    prior = (report.get("prior") or {}).get("params", {})
    flights = catalog.flight_names(services.db, diagnosis.flight_ids)
    return page("diagnosis.html", f"Diagnosis {diagnosis.id}: {report.get('system')}", diagnosis=diagnosis,
                report=report, flights=flights, headline=diagnosis_headline(report),
                split=diagnosis_split(report, [name or f"flight {fid} (deleted)" for fid, name in flights]),
                prior=[(k, v, CRAZYFLIE_UNITS[k]) for k, v in prior.items() if k in CRAZYFLIE_UNITS],
                summary=figures.png_data_uri(figures.diagnosis_summary(report), dpi=110),
                series=figures.png_data_uri(figures.residual_series(series), dpi=110) if series else None,
                note=unchanged_prior_note(report), registered=diagnosis.registered, how_much=how_much,
                confounded_label=confounded_label,
                model_name=diagnosis.model_ref.split(":", 1)[0] if diagnosis.model_ref else None)


# One router for the app: the pages (left out of the OpenAPI schema) and the report (in it).
router = APIRouter()
router.include_router(pages)
router.include_router(reports)
router.include_router(diagnosis_reports)
