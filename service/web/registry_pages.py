"""Web pages of the registry across rows: the evaluations list, a version's page with
its lineage, versions side by side, and the delete confirmations.

Pages   /ui/evaluations                     evaluations, newest first: MSE per method, KNODE improvement (%),
                                            links to report, model version and flights; a search box (?q=)
        /ui/models/{name}/versions/{v}      hyperparameters, metrics, loss curves (training and validation),
                                            lineage (training flight, parent, children, the diagnosis that
                                            produced it and the effects it added), evaluations, delete button
        /ui/compare?refs=a:1&refs=a:2       versions side by side (service.operations.comparison.compare_versions)
        /ui/{flights/ID|models/NAME/versions/V|evaluations/ID}/delete
                                            GET: what is deleted with it and what keeps a record of it
                                            (service.operations.deletion), and a confirm button; POST: delete (forced:
                                            the page listed the dependents), then 303 to the list it was in
"""
from __future__ import annotations

from fastapi import APIRouter, Depends, Query, Request
from fastapi.responses import HTMLResponse

from ..api.deps import Offset, RowId, actor, get_services
from ..jobs.services import Services
from ..operations import catalog, comparison, deletion
from ..storage import registry
from . import forms, registry_figures
from .rendering import PAGE_SIZE, html_errors, page

router = APIRouter(include_in_schema=False)


# -- evaluations -----------------------------------------------------------------------------------------
@router.get("/ui/evaluations", response_class=HTMLResponse)
def evaluations_page(q: str = Query("", max_length=220), offset: Offset = 0,
                     services: Services = Depends(get_services)):
    """Every evaluation, newest first, with its MSE and improvement columns; ``q`` searches model references."""
    total, items = comparison.list_evaluations(services.db, q=q.strip() or None, limit=PAGE_SIZE, offset=offset)
    methods = sorted({m for item in items for m in item["median_mse"]}, key=_method_order)
    improvements = sorted({k for item in items for k in item["improvement_pct"]})
    return page("evaluations.html", "Evaluations", items=items, total=total, offset=offset, q=q,
                methods=methods, improvements=improvements)


def _method_order(method: str) -> tuple:
    return (method.removeprefix("knode-"), method.startswith("knode-"))  # ukf next to knode-ukf


# -- a version ---------------------------------------------------------------------------------------------
@router.get("/ui/models/{name}/versions/{version}", response_class=HTMLResponse)
@html_errors
def version_page(name: str, version: RowId, services: Services = Depends(get_services)):
    """One version: what it is, where it comes from, what was made from it."""
    with services.db.transaction() as session:
        row = registry.get_version(session, name, version)
    lineage = comparison.version_lineage(services.db, name, version)
    detail = catalog.get_model(services.db, name)
    figure = registry_figures.loss_curves_of([{"ref": f"{name}:{version}", "losses": row.losses,
                                               "validation_losses": row.validation_losses}])
    return page("version.html", f"Model version {name}:{version}", v=row, lineage=lineage, model=detail,
                losses=figure, metrics={k: x for k, x in (row.metrics or {}).items() if not isinstance(x, dict)},
                noise=(row.metrics or {}).get("noise") or {},
                methods=sorted({m for e in lineage["evaluations"] for m in e["median_mse"]}, key=_method_order))


# -- comparing ---------------------------------------------------------------------------------------------
@router.get("/ui/compare", response_class=HTMLResponse)
@html_errors
def compare_page(refs: list[str] = Query(default=[]), services: Services = Depends(get_services)):
    """Versions side by side: the checked versions of a model page, or refs typed into the address."""
    wanted = [r.strip() for text in refs for r in text.split(",") if r.strip()]
    result = comparison.compare_versions(services.db, wanted)
    return page("compare.html", "Compare " + " vs ".join(result["refs"]), c=result,
                losses=registry_figures.loss_curves_of(result["versions"]))


# -- delete confirmations ----------------------------------------------------------------------------------
def _confirm(dependents: dict, action: str, request: Request, services: Services) -> HTMLResponse:
    return page("confirm_delete.html", f"Delete {dependents['target']['label']}?", d=dependents, action=action,
                key=forms.form_access(request, "admin"))


@router.get("/ui/flights/{flight_id}/delete", response_class=HTMLResponse)
@html_errors
def confirm_flight_delete(request: Request, flight_id: RowId, services: Services = Depends(get_services)):
    """What deleting the flight deletes and what keeps a record of it, and the button."""
    return _confirm(deletion.flight_dependents(services.db, flight_id), f"/ui/flights/{flight_id}/delete",
                    request, services)


@router.post("/ui/flights/{flight_id}/delete")
@html_errors
def delete_flight_form(request: Request, flight_id: RowId,
                       services: Services = Depends(get_services)):
    """Delete the flight (as DELETE /flights/{id}), then 303 to the flights."""
    deletion.delete_flight(services.db, services.blobs, flight_id, actor=actor(request))
    return forms.redirect("/")


@router.get("/ui/models/{name}/versions/{version}/delete", response_class=HTMLResponse)
@html_errors
def confirm_version_delete(request: Request, name: str, version: RowId, services: Services = Depends(get_services)):
    """What deleting the version deletes (its evaluations, aliases, cached results) and what keeps it as lineage."""
    return _confirm(deletion.version_dependents(services.db, name, version),
                    f"/ui/models/{name}/versions/{version}/delete", request, services)


@router.post("/ui/models/{name}/versions/{version}/delete")
@html_errors
def delete_version_form(request: Request, name: str, version: RowId,
                        services: Services = Depends(get_services)):
    """Delete the version with what the confirmation page listed (force), then 303 to the model's page."""
    deletion.delete_version(services.db, services.blobs, name, version, force=True, actor=actor(request))
    return forms.redirect(f"/ui/models/{name}")


@router.get("/ui/evaluations/{evaluation_id}/delete", response_class=HTMLResponse)
@html_errors
def confirm_evaluation_delete(request: Request, evaluation_id: RowId, services: Services = Depends(get_services)):
    """What deleting the evaluation deletes (its report figures) and what stays (its job)."""
    return _confirm(deletion.evaluation_dependents(services.db, evaluation_id),
                    f"/ui/evaluations/{evaluation_id}/delete", request, services)


@router.post("/ui/evaluations/{evaluation_id}/delete")
@html_errors
def delete_evaluation_form(request: Request, evaluation_id: RowId,
                           services: Services = Depends(get_services)):
    """Delete the evaluation, then 303 to the evaluations list."""
    deletion.delete_evaluation(services.db, services.blobs, evaluation_id, actor=actor(request))
    return forms.redirect("/ui/evaluations")
