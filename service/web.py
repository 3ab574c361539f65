"""Server-rendered HTML pages for people, on the same app as the JSON API (no JavaScript).

Pages   /                       flights (newest first) and the upload form
        /ui/flights/{id}        metadata, quality, trajectory plot (x-y, z-t), models trained on it, train form
        /ui/models              registered models
        /ui/models/{name}       versions, aliases (+ form), loss curves, evaluations, evaluate form
        /ui/jobs, /ui/jobs/{id} state and progress; a job page reloads itself every second until it is done
        /evaluations/{id}/report.html (routers/evaluations.py) shows `report_extras` from here: estimated vs
                                reference velocity for one chosen flight, and links back to these pages
Forms   POST /ui/flights, /ui/models, /ui/evaluations, /ui/models/{name}/aliases call the same code as the
        JSON routes and answer 303 to the page of what they made (so a reload never posts twice), or an HTML
        error page with the API's status code and message.

API key: with LEARNEST_API_KEY set, a form write needs the key, typed into the form's "API key" field; the
answer then stores it in an HttpOnly, SameSite=Strict cookie (`learnest_api_key`, for the browser session),
so later forms need not ask again.  SameSite=Strict keeps other sites' forms from using that cookie.  Pages
themselves (GET) need no key, as in the JSON API.  Every string that comes from a user (names, notes, file
names, error messages) is escaped with html.escape.
"""
from __future__ import annotations

import base64
import functools
import hmac
import html
import io
import json
import logging
from typing import Callable

import numpy as np
from fastapi import APIRouter, Depends, File, Form, Query, Request, Response, UploadFile
from fastapi.responses import HTMLResponse, RedirectResponse
from matplotlib.figure import Figure  # the object API: no pyplot global state shared between request threads
from pydantic import ValidationError
from sqlalchemy import func, select

from learnest.errors import InvalidInput, LearnestError, NotFound
from learnest.estimators.evaluate import METHODS
from learnest.ingest.flight import Flight as CanonicalFlight

from . import registry
from .config import Settings
from .db import Evaluation, Flight, Job, ModelVersion, RegisteredModel
from .jobs import ACTIVE, Services
from .routers import evaluations as evaluation_routes
from .routers import flights as flight_routes
from .routers import models as model_routes
from .routers.deps import get_services
from .schemas import AliasIn, EvaluationRequest, TrainRequest

log = logging.getLogger("learnest.web")
router = APIRouter(include_in_schema=False)

COOKIE = "learnest_api_key"
PAGE_SIZE = 100
VELOCITY_METHODS = ("ukf", "knode-ukf")
NAME_PATTERN = r"[A-Za-z0-9][A-Za-z0-9._\-]{0,99}"   # registry.NAME, for the browser's own check


# -- HTML building blocks -------------------------------------------------------------------------------
def esc(value) -> str:
    return "" if value is None else html.escape(str(value))


STYLE = """body{font-family:system-ui,sans-serif;max-width:1100px;margin:1em auto;padding:0 1em;color:#222}
nav{border-bottom:1px solid #ddd;padding-bottom:.5em} nav a{margin-right:1.2em}
table{border-collapse:collapse;margin:.5em 0} th,td{border:1px solid #ccc;padding:3px 8px;text-align:left}
th{background:#f3f3f3} .ok{color:#060} .bad{color:#a00} .muted{color:#777}
form.box{border:1px solid #ddd;background:#fafafa;padding:.6em 1em;margin:1em 0}
label{display:inline-block;margin:.25em 1.2em .25em 0} fieldset{border:1px solid #ddd;margin:.4em 0}
img{max-width:100%} pre{background:#f6f6f6;padding:.5em;overflow:auto;max-height:30em}"""


def render(title: str, body: str, refresh_s: float | None = None) -> str:
    refresh = f'<meta http-equiv="refresh" content="{refresh_s:g}">' if refresh_s else ""
    return (f'<!doctype html><html><head><meta charset="utf-8">{refresh}<title>{esc(title)} - learnest</title>'
            f"<style>{STYLE}</style></head><body><nav><b>learnest</b> <a href='/'>flights</a>"
            f"<a href='/ui/models'>models</a><a href='/ui/jobs'>jobs</a><a href='/docs'>API</a></nav>"
            f"<h1>{esc(title)}</h1>\n{body}\n</body></html>")


def page(title: str, body: str, status: int = 200, refresh_s: float | None = None) -> HTMLResponse:
    return HTMLResponse(render(title, body, refresh_s), status_code=status)


def error_page(status: int, message: str) -> HTMLResponse:
    return page(f"Error {status}", f"<p class='bad' id='error'>{esc(message)}</p>"
                                   "<p class='muted'>Go back to correct the form.</p>", status)


def table(headers: list[str], rows: list[list[str]], table_id: str = "") -> str:
    """`rows` hold ready HTML (escape the values before); headers are escaped here."""
    head = "".join(f"<th>{esc(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{cell}</td>" for cell in row) + "</tr>" for row in rows)
    ident = f" id='{esc(table_id)}'" if table_id else ""
    return f"<table{ident}><tr>{head}</tr>{body}</table>"


def png_img(fig: Figure, alt: str, img_id: str = "") -> str:
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    data = base64.b64encode(buffer.getvalue()).decode()
    ident = f" id='{esc(img_id)}'" if img_id else ""
    return f"<img{ident} alt='{esc(alt)}' src='data:image/png;base64,{data}'>"


def when(moment) -> str:
    return esc(moment.strftime("%Y-%m-%d %H:%M:%S")) if moment else ""


def quality_html(quality: dict) -> str:
    if quality.get("ok"):
        return "<span class='ok'>ok</span>"
    return "<span class='bad'>failed: " + esc("; ".join(quality.get("issues", []))) + "</span>"


def link(href: str, text) -> str:
    return f"<a href='{esc(href)}'>{esc(text)}</a>"


# -- API key for form writes ----------------------------------------------------------------------------
def _key_is_right(settings: Settings, key: str | None) -> bool:
    return settings.api_key is None or (
        bool(key) and hmac.compare_digest(key.encode(), settings.api_key.encode()))


def key_field(request: Request, settings: Settings) -> str:
    """The API-key input of a form: only when the server needs a key and the browser has none stored."""
    if settings.api_key is None:
        return ""
    if _key_is_right(settings, request.cookies.get(COOKIE)):
        return "<span class='muted'>API key: remembered for this browser session</span> "
    return ("<label>API key <input type='password' name='api_key' autocomplete='off' required></label>"
            "<span class='muted'>(kept in a cookie for this browser session)</span> ")


def key_problem(request: Request, settings: Settings, form_key: str) -> HTMLResponse | None:
    """None when the write may go ahead: no key configured, or the right one in the form or the cookie."""
    if _key_is_right(settings, form_key or request.cookies.get(COOKIE)):
        return None
    return error_page(401, "missing or wrong API key: type it into the form's API key field")


def redirect(url: str, settings: Settings, form_key: str) -> RedirectResponse:
    """303 to the new thing's page; a key typed into the form is kept in the cookie from now on."""
    response = RedirectResponse(url, status_code=303)
    if settings.api_key is not None and form_key:
        response.set_cookie(COOKIE, form_key, httponly=True, samesite="strict", path="/")
    return response


def html_errors(handler: Callable) -> Callable:
    """The API's errors as an HTML page with the same status code (a form post never gets JSON back)."""
    @functools.wraps(handler)
    def wrapper(*args, **kwargs):
        try:
            return handler(*args, **kwargs)
        except ValidationError as err:
            return error_page(422, "; ".join(_validation_message(e) for e in err.errors()))
        except LearnestError as err:
            return error_page(err.status, str(err))
    return wrapper


def _validation_message(error: dict) -> str:
    field = ".".join(str(part) for part in error.get("loc", ()))
    return f"{field}: {error.get('msg', 'invalid')}" if field else error.get("msg", "invalid")


def _optional(text: str | None) -> str | None:
    """An empty form field means "not given" (the API's default)."""
    text = (text or "").strip()
    return text or None


# -- flights ---------------------------------------------------------------------------------------------
def upload_form(request: Request, settings: Settings) -> str:
    return f"""<form class='box' id='upload-form' method='post' action='/ui/flights' enctype='multipart/form-data'>
<b>Upload a flight</b><br>
<label>log file(s) of one flight <input type='file' name='files' multiple required></label>
<label>vehicle <input name='vehicle' maxlength='200'></label>
<label>notes <input name='notes' maxlength='10000' size='30'></label>
{key_field(request, settings)}<button type='submit'>upload</button>
<div class='muted'>One flight per upload: a NanoBench CSV (with its *_metadata.yaml), a Crazyflie uSD log, an MCAP
file, or a Vicon CSV export together with its cfclient log. Identical content is stored once.</div></form>"""


@router.get("/", response_class=HTMLResponse)
def flights_page(request: Request, offset: int = Query(0, ge=0), services: Services = Depends(get_services)):
    with services.db.transaction() as session:
        total = session.scalar(select(func.count(Flight.id)))
        rows = session.scalars(select(Flight).order_by(Flight.id.desc()).limit(PAGE_SIZE).offset(offset)).all()
    listing = table(["id", "name", "format", "vehicle", "duration", "quality", "uploaded (UTC)"],
                    [[str(r.id), link(f"/ui/flights/{r.id}", r.name), esc(r.adapter), esc(r.vehicle),
                      f"{r.duration_s:.1f} s", quality_html(r.quality), when(r.created_at)] for r in rows],
                    "flights")
    pager = _pager("/", offset, total)
    body = upload_form(request, services.settings) + f"<p>{total} flight(s).</p>" + listing + pager
    return page("Flights", body)


def _pager(path: str, offset: int, total: int) -> str:
    links = []
    if offset > 0:
        links.append(link(f"{path}?offset={max(0, offset - PAGE_SIZE)}", "newer"))
    if offset + PAGE_SIZE < total:
        links.append(link(f"{path}?offset={offset + PAGE_SIZE}", "older"))
    return f"<p>{' | '.join(links)}</p>" if links else ""


@router.post("/ui/flights")
@html_errors
def upload_flight_form(request: Request, files: list[UploadFile | str] = File(default=[]),
                       vehicle: str = Form(""), notes: str = Form(""), api_key: str = Form(""),
                       services: Services = Depends(get_services)):
    denied = key_problem(request, services.settings, api_key)
    if denied:
        return denied
    chosen = [f for f in files if not isinstance(f, str) and f.filename]  # no file chosen: a nameless empty part
    if not chosen:
        raise InvalidInput("choose the log file(s) of one flight to upload")
    if len(vehicle) > 200 or len(notes) > 10_000:
        raise InvalidInput("vehicle: at most 200 characters; notes: at most 10000")
    flight = flight_routes.upload_flight(Response(), chosen, _optional(vehicle), _optional(notes),
                                         services.db, services.blobs)
    return redirect(f"/ui/flights/{flight['id']}", services.settings, api_key)


@router.get("/ui/flights/{flight_id}", response_class=HTMLResponse)
@html_errors
def flight_page(request: Request, flight_id: int, services: Services = Depends(get_services)):
    row = flight_routes.get_flight(services.db, flight_id)
    with services.db.transaction() as session:
        trained = session.scalars(select(ModelVersion).where(ModelVersion.training_flight_id == flight_id)
                                  .order_by(ModelVersion.name, ModelVersion.version)).all()
    facts = table(["", ""], [[esc(k), v] for k, v in (
        ("format", esc(row.adapter)), ("vehicle", esc(row.vehicle)), ("notes", esc(row.notes)),
        ("duration", f"{row.duration_s:.2f} s"), ("grid", f"{row.rate_hz:.0f} Hz, {row.samples} samples"),
        ("clock offset", "" if row.clock_offset_s is None else f"{row.clock_offset_s:+.3f} s"),
        ("quality", quality_html(row.quality)), ("sha256", f"<code>{esc(row.sha256)}</code>"),
        ("uploaded (UTC)", when(row.created_at)),
        ("downloads", link(f"/flights/{row.id}/raw", "raw file(s)") + " | "
                      + link(f"/flights/{row.id}/data", "normalized CSV")))], "flight-facts")
    sources = table(["file", "bytes", "role"], [[esc(f.original_name), str(f.size_bytes), esc(f.role)]
                                                for f in row.files])
    models = ("<p>" + ", ".join(link(f"/ui/models/{v.name}", f"{v.name}:{v.version}") + f" ({esc(v.status)})"
                                for v in trained) + "</p>") if trained else "<p class='muted'>none yet</p>"
    body = (facts + "<h2>Files</h2>" + sources
            + "<h2>Trajectory</h2>" + trajectory_html(services, row)
            + "<h2>Models trained on this flight</h2>" + models
            + train_form(request, services.settings, row)
            + f"<details><summary>metadata</summary><pre>{esc(json.dumps(row.meta, indent=1))}</pre></details>")
    return page(f"Flight {row.id}: {row.name}", body)


def trajectory_html(services: Services, row: Flight) -> str:
    try:
        flight = CanonicalFlight.from_bytes(services.blobs.read_bytes(row.flight_blob))
    except (OSError, ValueError, KeyError) as err:  # a missing or damaged blob: say so, show the rest
        return f"<p class='bad'>the stored normalized flight cannot be read ({esc(type(err).__name__)})</p>"
    return png_img(trajectory_figure(flight, row.name), "trajectory", "trajectory")


def train_form(request: Request, settings: Settings, row: Flight) -> str:
    include_bad = ("" if row.quality.get("ok") else
                   "<label><input type='checkbox' name='include_bad'> train although the flight failed the "
                   "quality checks</label>")
    return f"""<form class='box' id='train-form' method='post' action='/ui/models'>
<b>Train a model on this flight</b> (Algorithm 1: KF pre-training observer, 2 x 16 tanh)<br>
<input type='hidden' name='flight_id' value='{row.id}'>
<label>model name <input name='name' required maxlength='100' pattern='{NAME_PATTERN}'></label>
<label>epochs <input name='epochs' type='number' min='1' max='100000' placeholder='150'></label>
{include_bad}{key_field(request, settings)}<button type='submit'>train</button>
<div class='muted'>A new version of the model; the name's next version number is taken now.</div></form>"""


@router.post("/ui/models")
@html_errors
def train_model_form(request: Request, name: str = Form(""), flight_id: str = Form(""), epochs: str = Form(""),
                     include_bad: str | None = Form(None), api_key: str = Form(""),
                     services: Services = Depends(get_services)):
    denied = key_problem(request, services.settings, api_key)
    if denied:
        return denied
    body = TrainRequest.model_validate({"name": name.strip(), "flight_id": flight_id, "epochs": _optional(epochs),
                                        "include_bad": include_bad is not None})
    accepted = model_routes.train_model(body, Response(), services)
    return redirect(f"/ui/jobs/{accepted['job_id']}", services.settings, api_key)


# -- models ----------------------------------------------------------------------------------------------
@router.get("/ui/models", response_class=HTMLResponse)
def models_page(services: Services = Depends(get_services)):
    with services.db.transaction() as session:
        models = session.scalars(select(RegisteredModel).order_by(RegisteredModel.name)).all()
        rows = []
        for m in models:
            versions = session.scalars(select(ModelVersion).where(ModelVersion.name == m.name)).all()
            ready = [v.version for v in versions if v.status == "ready"]
            aliases = registry.aliases_of(session, m.name)
            rows.append([link(f"/ui/models/{m.name}", m.name), str(len(versions)),
                         str(max(ready)) if ready else "-",
                         esc(", ".join(f"@{a} -> {v}" for a, v in aliases.items())), when(m.created_at)])
    body = (table(["name", "versions", "latest ready", "aliases", "created (UTC)"], rows, "models") if rows else
            "<p>No models yet: open a flight and train one.</p>")
    return page("Models", body)


@router.get("/ui/models/{name}", response_class=HTMLResponse)
@html_errors
def model_page(request: Request, name: str, services: Services = Depends(get_services)):
    with services.db.transaction() as session:
        registry.get_model(session, name)
        aliases = registry.aliases_of(session, name)
        versions = session.scalars(select(ModelVersion).where(ModelVersion.name == name)
                                   .order_by(ModelVersion.version)).all()
        evaluations = session.scalars(select(Evaluation)
                                      .where(Evaluation.model_version_id.in_([v.id for v in versions]))
                                      .order_by(Evaluation.id.desc()).limit(20)).all()
        jobs = {j.id: j for j in session.scalars(select(Job).where(Job.id.in_([ev.job_id for ev in evaluations])))}
        flights = session.scalars(select(Flight).order_by(Flight.id.desc()).limit(PAGE_SIZE)).all()
    ready = [v for v in versions if v.status == "ready"]
    body = (versions_table(versions, aliases)
            + "<h2>Training loss</h2>" + (png_img(loss_figure(ready), "training loss", "loss-curve") if ready
                                          else "<p class='muted'>no ready version yet</p>")
            + "<h2>Aliases</h2>" + alias_form(request, services.settings, name, aliases, ready)
            + "<h2>Evaluate</h2>" + evaluate_form(request, services.settings, name, aliases, ready, flights)
            + "<h2>Evaluations</h2>" + evaluations_table(evaluations, jobs))
    return page(f"Model {name}", body)


def versions_table(versions: list[ModelVersion], aliases: dict[str, int]) -> str:
    rows = []
    for v in versions:
        flight = (link(f"/ui/flights/{v.training_flight_id}", v.training_flight_name or v.training_flight_id)
                  if v.training_flight_id else "")
        metrics = v.metrics or {}
        loss = metrics.get("final_loss")
        status = esc(v.status) + (f": <span class='bad'>{esc(v.error)}</span>" if v.error else "")
        weights = link(f"/models/{v.name}/versions/{v.version}/weights", "weights") if v.status == "ready" else ""
        rows.append([str(v.version), status, flight, esc((v.hyperparameters or {}).get("epochs")),
                     "" if loss is None else f"{loss:.4g}", esc(metrics.get("best_epoch")),
                     "" if v.training_seconds is None else f"{v.training_seconds:.1f} s",
                     esc(", ".join("@" + a for a, n in aliases.items() if n == v.version)), esc(v.parent),
                     when(v.created_at), weights])
    return table(["version", "status", "training flight", "epochs", "final loss", "best epoch", "training time",
                  "aliases", "parent", "created (UTC)", ""], rows, "versions")


def alias_form(request: Request, settings: Settings, name: str, aliases: dict[str, int],
               ready: list[ModelVersion]) -> str:
    current = ", ".join(f"{esc(name)}@{esc(a)} -> version {v}" for a, v in aliases.items()) or "none"
    if not ready:
        return f"<p>{current}</p>"
    options = "".join(f"<option value='{v.version}'>{v.version}</option>" for v in reversed(ready))
    return f"""<p id='aliases'>{current}</p><form class='box' method='post' action='/ui/models/{esc(name)}/aliases'>
<label>alias <input name='alias' required maxlength='100' pattern='{NAME_PATTERN}' placeholder='production'></label>
<label>version <select name='version'>{options}</select></label>{key_field(request, settings)}
<button type='submit'>set alias</button></form>"""


def evaluate_form(request: Request, settings: Settings, name: str, aliases: dict[str, int],
                  ready: list[ModelVersion], flights: list[Flight]) -> str:
    if not ready:
        return "<p class='muted'>no ready version to evaluate yet</p>"
    refs = ([(name, f"{name} (latest ready: {ready[-1].version})")]
            + [(f"{name}@{a}", f"{name}@{a} (version {v})") for a, v in aliases.items()]
            + [(f"{name}:{v.version}", f"{name}:{v.version}") for v in reversed(ready)])
    options = "".join(f"<option value='{esc(ref)}'>{esc(text)}</option>" for ref, text in refs)
    flight_boxes = "".join(f"<label><input type='checkbox' name='flights' value='{f.id}'> {f.id}: {esc(f.name)}"
                           f"{'' if f.quality_ok else ' (bad)'}</label>" for f in flights)
    method_boxes = "".join(f"<label><input type='checkbox' name='methods' value='{m}' checked> {m.upper()}</label>"
                           for m in METHODS)
    return f"""<form class='box' id='evaluate-form' method='post' action='/ui/evaluations'>
<label>model <select name='model'>{options}</select></label>
<fieldset><legend>flights (none checked: every stored flight except the model's training flight)</legend>
{flight_boxes}</fieldset>
<fieldset><legend>estimators (the MHE ones take longest)</legend>{method_boxes}</fieldset>
<label>MHE horizon <input type='number' name='horizon' value='20' min='1' max='500'></label>
<label><input type='checkbox' name='include_bad'> also score flights that failed the quality checks</label>
{key_field(request, settings)}<button type='submit'>evaluate</button></form>"""


def evaluations_table(evaluations: list[Evaluation], jobs: dict[int, Job]) -> str:
    if not evaluations:
        return "<p class='muted'>none yet</p>"
    rows = []
    for ev in evaluations:
        job = jobs.get(ev.job_id)
        state = job.state if job else "?"
        report = (link(f"/evaluations/{ev.id}/report.html", "report") if state == "succeeded"
                  else link(f"/ui/jobs/{ev.job_id}", "job"))
        rows.append([str(ev.id), esc(ev.model_ref), str(len(ev.flight_ids)),
                     esc(", ".join(ev.settings.get("methods", []))), esc(state), when(ev.created_at), report])
    return table(["evaluation", "model", "flights", "methods", "state", "created (UTC)", ""], rows, "evaluations")


@router.post("/ui/models/{name}/aliases")
@html_errors
def alias_form_post(request: Request, name: str, alias: str = Form(""), version: str = Form(""),
                    api_key: str = Form(""), services: Services = Depends(get_services)):
    denied = key_problem(request, services.settings, api_key)
    if denied:
        return denied
    model_routes.put_alias(name, alias.strip(), AliasIn.model_validate({"version": version}), services.db)
    return redirect(f"/ui/models/{name}", services.settings, api_key)


@router.post("/ui/evaluations")
@html_errors
def evaluate_form_post(request: Request, model: str = Form(""), flights: list[str] = Form(default=[]),
                       methods: list[str] = Form(default=[]), horizon: str = Form("20"),
                       include_bad: str | None = Form(None), api_key: str = Form(""),
                       services: Services = Depends(get_services)):
    denied = key_problem(request, services.settings, api_key)
    if denied:
        return denied
    if not methods:
        raise InvalidInput("choose at least one estimator")
    body = EvaluationRequest.model_validate({"model": model, "flights": flights or "all-other", "methods": methods,
                                             "horizon": horizon, "include_bad": include_bad is not None})
    accepted = evaluation_routes.create_evaluation(body, Response(), services)
    return redirect(f"/ui/jobs/{accepted['job_id']}", services.settings, api_key)


# -- jobs ------------------------------------------------------------------------------------------------
@router.get("/ui/jobs", response_class=HTMLResponse)
def jobs_page(services: Services = Depends(get_services)):
    with services.db.transaction() as session:
        jobs = session.scalars(select(Job).order_by(Job.id.desc()).limit(PAGE_SIZE)).all()
    rows = [[link(f"/ui/jobs/{j.id}", j.id), esc(j.kind), esc(j.state), f"{j.progress:.0%}",
             esc(_job_subject(j)), when(j.created_at), when(j.finished_at)] for j in jobs]
    running = any(j.state in ACTIVE for j in jobs)
    return page("Jobs", table(["job", "kind", "state", "progress", "subject", "created (UTC)", "finished (UTC)"],
                              rows, "jobs") if rows else "<p>No jobs yet.</p>", refresh_s=2 if running else None)


def _job_subject(job: Job) -> str:
    payload = job.payload or {}
    if job.kind == "training":
        return f"{payload.get('name')} on flight {payload.get('flight_id')}"
    return f"{payload.get('model')} on {len(payload.get('flights') or [])} flight(s)"


@router.get("/ui/jobs/{job_id}", response_class=HTMLResponse)
@html_errors
def job_page(job_id: int, services: Services = Depends(get_services)):
    with services.db.transaction() as session:
        job = session.get(Job, job_id)
        if job is None:
            raise NotFound(f"job {job_id} not found")
        evaluation = session.scalar(select(Evaluation).where(Evaluation.job_id == job_id))
    active = job.state in ACTIVE
    facts = table(["", ""], [
        ["kind", esc(job.kind)], ["subject", esc(_job_subject(job))],
        ["state", f"<b id='job-state'>{esc(job.state)}</b>"],
        ["progress", f"<progress max='1' value='{job.progress:.3f}'></progress> {job.progress:.0%}"],
        ["created / started / finished (UTC)", " / ".join(when(m) or "-" for m in
                                                         (job.created_at, job.started_at, job.finished_at))]])
    error = f"<p class='bad' id='job-error'>{esc(job.error)}</p>" if job.error else ""
    note = "<p class='muted'>This page reloads every second until the job is done.</p>" if active else ""
    return page(f"Job {job.id}", facts + error + _job_links(job, evaluation) + note
                + (f"<details><summary>result</summary><pre>{esc(json.dumps(job.result, indent=1))}</pre></details>"
                   if job.result else ""), refresh_s=1 if active else None)


def _job_links(job: Job, evaluation: Evaluation | None) -> str:
    links = []
    if job.kind == "training" and (job.payload or {}).get("name"):
        links.append(link(f"/ui/models/{job.payload['name']}", f"model {job.payload['name']}"))
    if evaluation is not None:
        if job.state == "succeeded":
            links.append(f"<a id='report-link' href='/evaluations/{evaluation.id}/report.html'>"
                         f"evaluation {evaluation.id} report</a>")
        name = evaluation.model_ref.split(":", 1)[0]
        links.append(link(f"/ui/models/{name}", f"model {name}"))
    return f"<p>{' | '.join(links)}</p>" if links else ""


# -- the evaluation report's extras (routers/evaluations.py adds them to report.html) -------------------------
def report_extras(services: Services, evaluation: Evaluation, flight_id: int | None) -> str:
    """Estimated vs reference velocity of one scored flight of the evaluation (a form picks which), and links
    back to the pages.  A flight that cannot be plotted gets a message, never a broken report."""
    name = evaluation.model_ref.split(":", 1)[0]
    links = (f"<p>{link(f'/ui/models/{name}', f'model {name}')} | {link(f'/ui/jobs/{evaluation.job_id}', 'job')}"
             f" | {link(f'/evaluations/{evaluation.id}', 'report JSON')}</p>")
    scored = [(fid, entry["flight"]) for fid, entry in zip(evaluation.flight_ids, evaluation.report["flights"])
              if not entry.get("excluded")]
    if not scored:
        return links + "<p>no scored flight: no velocity plot</p>"
    chosen = flight_id if flight_id in {fid for fid, _ in scored} else scored[0][0]
    options = "".join(f"<option value='{fid}'{' selected' if fid == chosen else ''}>{esc(label)}</option>"
                      for fid, label in scored)
    picker = (f"<form method='get'><label>flight <select name='flight'>{options}</select></label>"
              "<button type='submit'>show</button></form>")
    try:
        figure = velocity_section_image(services, evaluation.model_version_id, chosen)
    except Exception as err:  # a deleted or unreadable flight: say so, keep the rest of the report
        log.warning("velocity plot of flight %s failed: %s", chosen, err)
        figure = f"<p class='bad'>no velocity plot for flight {chosen}: {esc(err)}</p>"
    return (f"<h2>Velocity: estimated ({', '.join(m.upper() for m in VELOCITY_METHODS)}) vs SG reference</h2>"
            + picker + figure + links)


def velocity_section_image(services: Services, version_id: int, flight_id: int) -> str:
    with services.db.transaction() as session:
        version, flight = session.get(ModelVersion, version_id), session.get(Flight, flight_id)
        if flight is None:
            raise NotFound(f"flight {flight_id} was deleted")
        weights, flight_blob, title = version.weights_blob, flight.flight_blob, \
            f"{version.name}:{version.version} on {flight.name}"
    return _velocity_img(services.blobs, weights, flight_blob, title)


@functools.lru_cache(maxsize=32)  # the same plot is asked for again on every reload of the report
def _velocity_img(blobs, weights_sha: str, flight_sha: str, title: str) -> str:
    from .experiments.flights import evaluate_flight

    model = registry.model_from_json(blobs.read_bytes(weights_sha))
    flight = CanonicalFlight.from_bytes(blobs.read_bytes(flight_sha))
    out = evaluate_flight(model, flight, list(VELOCITY_METHODS), keep_estimates=True)
    estimates = {m: r["estimates"] for m, r in out["results"].items()}
    return png_img(velocity_figure(flight.t, out["reference"], estimates, title), "velocity", "velocity-plot")


# -- figures (matplotlib's object API) ---------------------------------------------------------------------
def trajectory_figure(flight: CanonicalFlight, name: str) -> Figure:
    fig = Figure(figsize=(10, 4), layout="constrained")
    top, height = fig.subplots(1, 2, width_ratios=[1, 1.6])
    top.plot(flight.p[:, 0], flight.p[:, 1], lw=1)
    top.set(xlabel="x (m)", ylabel="y (m)", title=f"{name}: top view", aspect="equal")
    height.plot(flight.t, flight.p[:, 2], lw=1)
    height.set(xlabel="t (s)", ylabel="z (m)", title="height")
    for ax in (top, height):
        ax.grid(alpha=0.3)
    return fig


def loss_figure(versions: list[ModelVersion]) -> Figure:
    fig = Figure(figsize=(7, 3.5), layout="constrained")
    ax = fig.subplots()
    for v in versions:
        losses = np.array([np.nan if x is None else x for x in (v.losses or [])], float)
        if len(losses):
            ax.plot(np.arange(1, len(losses) + 1), losses, marker="." if len(losses) < 30 else None,
                    label=f"version {v.version}")
    ax.set(xlabel="epoch", ylabel="training loss", yscale="log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return fig


def velocity_figure(t: np.ndarray, reference: np.ndarray, estimates: dict[str, np.ndarray], title: str) -> Figure:
    """vx, vy, vz (state columns 3-5) of each estimator against the Savitzky-Golay reference."""
    fig = Figure(figsize=(10, 7), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    for k, (ax, label) in enumerate(zip(axes, ("vx", "vy", "vz"))):
        ax.plot(t, reference[:, 3 + k], color="black", lw=1.5, label="SG reference")
        for method, values in estimates.items():
            ax.plot(t, values[:, 3 + k], lw=1, label=method.upper())
        ax.set_ylabel(f"{label} (m/s)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize="small", ncol=len(estimates) + 1)
    axes[0].set_title(title)
    axes[-1].set_xlabel("t (s)")
    return fig
