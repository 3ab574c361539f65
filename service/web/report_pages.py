"""The report pages: an evaluation's and a diagnosis's report for people, each on its own API path and
documented in the OpenAPI schema next to the JSON report.  Their errors stay the API's JSON ones (404 unknown,
409 failed); a report not finished yet is a page that reloads itself (202).

/evaluations/{id}/report.html   per-flight MSE table and paired dots (prior vs KNODE), and for one chosen flight
                                the error over time with its running RMS and the estimates against the reference
/diagnoses/{id}/report.html     effects with units, intervals and alternatives, residual over time before/after,
                                held-out error before/after per flight (linear axes)
"""
from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Depends, Query
from fastapi.responses import HTMLResponse
from sqlalchemy import func, select

from learnest.errors import LearnestError
from learnest.estimators.evaluation_settings import EvaluationSettings
from learnest.ingest.baseline import centred_window
from learnest.models.crazyflie import UNITS as CRAZYFLIE_UNITS
from learnest.workflows.headline import diagnosis_headline, diagnosis_split, evaluation_headline, gap_methods

from ..api.deps import MAX_ROW_ID, RowId, get_services
from ..jobs.result_cache import settings_key
from ..jobs.services import Services
from ..local import figures
from ..operations import catalog
from ..operations.exports import evaluation_estimates
from ..storage.tables import Diagnosis, Evaluation, FlightRecord, ReportFigure, Result
from . import evaluation_plots, page_cache, zoomable
from .rendering import page, with_identity
from .report_figures import velocity_figure

# -- the evaluation report ---------------------------------------------------------------------------------
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
    return HTMLResponse(with_identity(body[0].decode("utf-8")))


def _report_inputs(services: Services, evaluation: Evaluation) -> tuple:
    """What a finished evaluation's page is drawn from besides its report: the estimates blob of each of its
    flights (a deleted flight has none) and the stored report figures."""
    key = settings_key(EvaluationSettings.from_json(evaluation.settings))
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
    settings = EvaluationSettings.from_json(evaluation.settings)
    series = _stored_series(services, evaluation, chosen, group, centred_window(settings.sg_window),
                            entries.get(chosen))
    head = evaluation_headline(report)
    gain = figures.gain_per_flight(head)
    # evaluated before estimates were stored: the velocity figure computed once by a task (report_figures)
    velocity = _velocity(services, evaluation, chosen) if chosen is not None and "figure" not in series else {}
    waiting = velocity.get("pending") or velocity.get("busy")
    paired = evaluation_plots.paired_figure(report)
    response = page("report.html", title, refresh_s=2 if waiting else None, identify=False, evaluation=evaluation,
                report=report,
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



# -- the diagnosis report -----------------------------------------------------------------------------------
diagnosis_reports = APIRouter(tags=["diagnoses"])


@diagnosis_reports.get("/diagnoses/{diagnosis_id}/report.html", response_class=HTMLResponse,
                       responses={202: {"description": "not finished yet (the page reloads itself)"},
                                  409: {"description": "the diagnosis job failed"}})
def diagnosis_report_page(diagnosis_id: RowId, services: Services = Depends(get_services)):
    """The diagnosis report for people: effects with units, 95 % intervals and alternatives, the residual over
    time before and after, and the held-out error before and after (linear axes)."""
    from learnest.workflows.diagnosis import (  # numpy only; kept off app start
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
