"""/models: train a new version (a job), browse registered models and versions, move aliases, download
weights.  MLflow's concepts: registered model -> immutable integer versions -> movable aliases."""
from __future__ import annotations

import json

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.responses import JSONResponse

from learnest.models.metadata import ModelMetadata

from ...jobs.services import Services
from ...jobs.training import start_training
from ...operations import catalog, comparison, deletion
from ...storage import registry
from ...storage.blobs import BlobStore
from ...storage.database import Database
from ...storage.tables import ModelVersion
from ..deps import RowId, actor, creator, get_blobs, get_db, get_services
from ..report_models import ModelMetadataOut, VersionLineage
from ..schemas import AliasIn, AliasOut, Dependents, ModelOut, ModelPage, TrainAccepted, TrainRequest, VersionOut

router = APIRouter(prefix="/models", tags=["models"])


def version_out(row: ModelVersion, aliases: dict[str, int], full: bool = True) -> dict:
    """A version row as the API's JSON (VersionOut); `full=False` leaves out prior, losses, timing, code and
    library versions and the weights' sha256 (for a model's list of versions).
    """
    out = {"name": row.name, "version": row.version, "status": row.status, "job_id": row.job_id,
           "training_flight": {"id": row.training_flight_id, "sha256": row.training_flight_sha256,
                               "name": row.training_flight_name},
           "training_flights": registry.training_flights_of(row),
           "validation_flights": list(row.validation_flights or []),
           "learned": (row.metrics or {}).get("learned"), "learned_note": (row.metrics or {}).get("learned_note"),
           "residual_scale": (row.metrics or {}).get("residual_scale"),
           "residual_scale_groups": list((row.metrics or {}).get("residual_scale_groups") or []),
           "residual_scale_note": (row.metrics or {}).get("residual_scale_note"),
           "noise": (row.metrics or {}).get("noise") or {"model": None, "prior": None},
           "parent": row.parent, "hyperparameters": row.hyperparameters, "metrics": row.metrics,
           "error": row.error, "aliases": sorted(a for a, v in aliases.items() if v == row.version),
           "created_at": row.created_at, "created_by": row.created_by, "ready_at": row.ready_at}
    if full:
        out.update({"prior": row.prior, "losses": row.losses, "validation_losses": row.validation_losses,
                    "training_seconds": row.training_seconds,
                    "code_version": row.code_version, "library_versions": row.library_versions,
                    "weights_sha256": row.weights_blob})
    return out


@router.post("", status_code=202, response_model=TrainAccepted)
def train_model(body: TrainRequest, request: Request, response: Response,
                services: Services = Depends(get_services)):
    """Train a KNODE on one stored flight (Algorithm 1, the Crazyflie settings of Sec. V-C unless
    overridden) or on several flights of one vehicle (`flight_ids`: one pooled loss, whole flights held out
    for validation, `validation_ids` or one in five) as a job; the next version number of `name` is reserved
    now and usable once ready.  Flights of different vehicles fail the job with a message naming them."""
    job, version = start_training(services, body.name, body.flights(),
                                  {"epochs": body.epochs, "hidden": body.hidden, "lr": body.lr,
                                   "system": body.system, "group_by": body.group_by, "noise": body.noise,
                                   "ensemble": body.ensemble},
                                  parent=body.parent, include_bad=body.include_bad,
                                  validation_ids=body.validation_ids, created_by=creator(request))
    response.headers["Location"] = f"/jobs/{job.id}"
    return {"job_id": job.id, "name": version.name, "version": version.version, "status": version.status}


@router.get("", response_model=ModelPage)
def list_models(q: str | None = Query(None, max_length=100, description="only names containing this "
                                                                        "(case-insensitive)"),
                db: Database = Depends(get_db)):
    """Every registered model by name (or those whose name contains `q`), with its aliases, latest ready
    version and version count."""
    items = [{"name": m.model.name, "created_at": m.model.created_at, "aliases": m.aliases,
              "latest_version": m.latest_version, "version_count": m.version_count}
             for m in catalog.list_models(db, q=q)]
    return {"items": items, "total": len(items)}


@router.get("/{name}", response_model=ModelOut)
def model_detail(name: str, db: Database = Depends(get_db)):
    """A registered model with its aliases and (short) versions; 404 when there is none."""
    model = catalog.get_model(db, name)
    return {"name": model.model.name, "created_at": model.model.created_at, "aliases": model.aliases,
            "latest_version": model.latest_version,
            "versions": [version_out(v, model.aliases, full=False) for v in model.versions]}


@router.get("/{name}/versions/{version}", response_model=VersionOut)
def version_detail(name: str, version: RowId, db: Database = Depends(get_db)):
    """One version, whatever its status; 404 when there is none."""
    with db.transaction() as session:
        row = registry.get_version(session, name, version)
        return version_out(row, registry.aliases_of(session, name))


@router.get("/{name}/versions/{version}/lineage", response_model=VersionLineage,
            responses={200: {"description": "links to the training flight, parent, children, the diagnosis that "
                                            "produced it (and the effects it added), its job, evaluations, "
                                            "aliases; `exists: false` for a deleted one"}})
def version_lineage(name: str, version: RowId, db: Database = Depends(get_db)) -> dict:
    """Where a version comes from and what was made from it; 404 when there is no such version."""
    return comparison.version_lineage(db, name, version)


@router.get("/{name}/versions/{version}/metadata", response_model=ModelMetadataOut,
            responses={409: {"description": "the version is not ready (no weights yet)"}})
def version_metadata(name: str, version: RowId, db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs)):
    """What the model file says about itself: its meta (training and validation flights with their sha256,
    ``learned``, the training envelope, the integer input ``format_version``, ...) and its prior's parameters;
    404 when there is no such version, 409 when it is not ready."""
    with db.transaction() as session:
        row = registry.resolve(session, registry.ModelRef(name, version))
    data = json.loads(blobs.read_bytes(registry.weights_of(row)))
    # the model file's meta as it is (ModelMetadataOut documents it), read as `HybridModel.load` reads it
    return JSONResponse(ModelMetadata.of_model(data.get("meta"), data.get("prior_params") or {}).to_dict())


@router.get("/{name}/versions/{version}/dependents", response_model=Dependents)
def version_dependents(name: str, version: RowId, db: Database = Depends(get_db)):
    """What a DELETE of this version would delete with it (its evaluations, aliases on it, cached results),
    what keeps a record of it (children, diagnoses), and whether it needs force or is blocked."""
    return deletion.version_dependents(db, name, version)


@router.delete("/{name}/versions/{version}", status_code=204,
               responses={404: {"description": "no such version"},
                          409: {"description": "still training or evaluated right now, or it has evaluations or "
                                               "aliases and force is not set (the message lists them)"}})
def delete_version(name: str, version: RowId, request: Request,
                   force: bool = Query(False, description="also delete its evaluations and the aliases on it"),
                   db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs)):
    """Delete a version (see GET .../dependents first): its cached results go with it, its evaluations and
    aliases only with force=true; children and diagnoses keep its "name:version" as lineage text.  Its
    number is never handed out again; the weights blob is removed after the commit."""
    deletion.delete_version(db, blobs, name, version, force=force, actor=actor(request))
    return Response(status_code=204)


@router.get("/{name}/versions/{version}/weights", response_class=Response,
            responses={200: {"content": {"application/json": {}},
                             "description": "the HybridModel file (models.knode.HybridModel.load reads it)"}})
def version_weights(name: str, version: RowId, db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs)):
    """Download a version's weights; 404 when there is no such version, 409 when it is not ready."""
    with db.transaction() as session:
        row = registry.resolve(session, registry.ModelRef(name, version))
    return Response(blobs.read_bytes(registry.weights_of(row)), media_type="application/json",
                    headers={"Content-Disposition": f'attachment; filename="{name}-{version}.json"'})


@router.get("/{name}/aliases/{alias}", response_model=VersionOut)
def alias_detail(name: str, alias: str, db: Database = Depends(get_db)):
    """The version an alias points to (name@alias)."""
    with db.transaction() as session:
        row = registry.resolve(session, registry.ModelRef(name, alias=alias))
        return version_out(row, registry.aliases_of(session, name))


@router.put("/{name}/aliases/{alias}", response_model=AliasOut)
def put_alias(name: str, alias: str, body: AliasIn, request: Request, db: Database = Depends(get_db)):
    """Point name@alias at a version (creating or moving it); 404 for an unknown model or version, 409 when that
    version is not ready, 422 for a bad alias name.
    """
    catalog.set_alias(db, name, alias, body.version, actor=actor(request))
    return {"name": name, "alias": alias, "version": body.version}


@router.delete("/{name}/aliases/{alias}", status_code=204)
def delete_alias(name: str, alias: str, request: Request, db: Database = Depends(get_db)):
    """Remove an alias; 204, or 404 when the model or the alias does not exist."""
    catalog.delete_alias(db, name, alias, actor=actor(request))
    return Response(status_code=204)


compare_router = APIRouter(tags=["models"])


@compare_router.get("/compare", responses={400: {"description": "fewer than 2 or more than 10 versions"},
                                           404: {"description": "a reference names nothing"}})
def compare(refs: list[str] = Query(..., description="2-10 references (repeat the parameter or separate with "
                                                      "commas): name:version, name@alias or name"),
            db: Database = Depends(get_db)) -> dict:
    """Versions side by side: hyperparameters and metrics (with the keys that differ), training and validation
    loss per epoch, and the MSE per method on the flights every version was evaluated on."""
    return comparison.compare_versions(db, [r.strip() for text in refs for r in text.split(",") if r.strip()])
