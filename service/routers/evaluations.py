"""/evaluations: batch KNODE-UKF / KNODE-MHE (and their priors) over stored flights as a job; the report
is service.experiment.evaluate_flights' JSON, plus an HTML page with the Fig. 3-style box plot."""
from __future__ import annotations

import base64
import html
import io
import threading

from fastapi import APIRouter, Depends, Query, Response
from fastapi.responses import HTMLResponse

from ..db import Database, Evaluation
from ..jobs import EstimatorSettings, Services, start_evaluation
from ..schemas import EvaluationAccepted, EvaluationPending, EvaluationRequest
from .deps import get_db, get_services, pending, require_api_key, row_and_job

router = APIRouter(prefix="/evaluations", tags=["evaluations"])
_plot_lock = threading.Lock()  # matplotlib's pyplot state is global


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
def evaluation_report(evaluation_id: int, db: Database = Depends(get_db)):
    evaluation, job = row_and_job(db, Evaluation, evaluation_id, "evaluation")
    if job.state != "succeeded":
        return pending("evaluation", evaluation, job)
    return evaluation.report


@router.get("/{evaluation_id}/report.html", response_class=HTMLResponse)
def evaluation_html(evaluation_id: int, flight: int | None = Query(None, description="flight id of the velocity "
                                                                   "plot (default: the first scored flight)"),
                    db: Database = Depends(get_db), services: Services = Depends(get_services)):
    from ..web import report_extras  # the web pages import this module

    evaluation, job = row_and_job(db, Evaluation, evaluation_id, "evaluation")
    if job.state != "succeeded":
        return HTMLResponse(f"<p>evaluation {evaluation.id}: {html.escape(job.state)} "
                            f"({job.progress:.0%})</p>", status_code=202)
    return HTMLResponse(render_report(evaluation.id, evaluation.report, evaluation.settings,
                                      extra=report_extras(services, evaluation, flight)))


def _boxplot_png(report: dict) -> str | None:
    from ..plots import mse_boxplot

    if not any(not f.get("excluded") and f.get("mse") for f in report["flights"]):
        return None
    buffer = io.BytesIO()
    with _plot_lock:
        mse_boxplot(report, buffer)
    return base64.b64encode(buffer.getvalue()).decode()


def render_report(evaluation_id: int, report: dict, settings: dict, extra: str = "") -> str:
    """`extra`: ready HTML appended to the page (the velocity plot of service.web.report_extras)."""
    esc = html.escape
    methods = list(report.get("median", {}))
    header = "".join(f"<th>{esc(m)}</th>" for m in methods)
    rows = []
    for f in report["flights"]:
        if f.get("excluded"):
            rows.append(f"<tr><td>{esc(f['flight'])}</td><td colspan='{max(1, len(methods))}'>excluded: "
                        f"{esc(str(f.get('reason')))}</td></tr>")
        else:
            cells = "".join(f"<td>{f['mse'][m] * 1e3:.3f}</td>" if f["mse"].get(m) is not None else "<td>-</td>"
                            for m in methods)
            rows.append(f"<tr><td>{esc(f['flight'])}</td>{cells}</tr>")
    median = "".join(f"<td><b>{v * 1e3:.3f}</b></td>" if v is not None else "<td>-</td>"
                     for v in report.get("median", {}).values())
    improvements = "".join(f"<li>{esc(k)}: {v:+.1f} % (median MSE)</li>"
                           for k, v in report.get("improvement_pct", {}).items() if v is not None)
    png = _boxplot_png(report)
    figure = (f"<img alt='MSE box plot' src='data:image/png;base64,{png}'>" if png
              else "<p>no scored flights: no box plot</p>")
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>evaluation {evaluation_id}: {esc(str(report.get('model')))}</title>
<style>body{{font-family:sans-serif;margin:2em}} table{{border-collapse:collapse}}
td,th{{border:1px solid #ccc;padding:4px 8px;text-align:right}} td:first-child{{text-align:left}}</style></head>
<body><h1>Evaluation {evaluation_id}: model {esc(str(report.get('model')))}</h1>
<p>settings: methods {esc(', '.join(settings.get('methods', [])))}, MHE horizon {esc(str(settings.get('horizon')))},
include bad flights: {esc(str(settings.get('include_bad')))}. MSE over [p, v, a] against Savitzky-Golay
references, &times; 1e-3.</p>
{figure}
<table><tr><th>flight</th>{header}</tr>
{''.join(rows)}
<tr><td><b>median</b></td>{median}</tr></table>
<ul>{improvements}</ul>
{extra}
</body></html>"""
