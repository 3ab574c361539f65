"""Reading the registry in this process (`learnest flights list`, `models list|show`, `alias set`): a model
by its reference, the stored flights and models, one model or version with its lineage, an alias moved."""
from __future__ import annotations

from sqlalchemy import select

from learnest.errors import Conflict, NotFound
from learnest.models.knode import HybridModel

from ..config import Settings
from ..operations import catalog
from ..storage import audit, registry
from ..storage.database import Database
from ..storage.tables import RegisteredModel
from .services import registry_database


def load_model(ref: str, settings: Settings | None = None) -> HybridModel:
    """The model a reference names.

    Raises
    ------
    InvalidInput
        `ref` does not parse.
    NotFound, Conflict
        It names nothing usable (no such model/version/alias, not ready, no database yet, an older
        schema); the message lists the registered models (except when there is no database).
    """
    parsed = registry.parse_ref(ref)  # InvalidInput (a ValueError) says which forms are accepted
    settings = settings or Settings()
    # no database yet: say so instead of creating an empty one (Settings.url puts SQLite at home/learnest.db)
    if settings.database_url is None and not (settings.home / "learnest.db").is_file():
        raise NotFound(f"no model {ref!r}: nothing is registered under {settings.home} (LEARNEST_HOME); "
                         "`learnest train FILE... --name NAME` registers one")
    try:
        return registry.load_model_ref(str(parsed), settings)
    except (NotFound, Conflict) as err:
        raise type(err)(f"{err} (registered models: {', '.join(known_models(settings)) or 'none'})") from None


def known_models(settings: Settings) -> list[str]:
    """Names of every registered model in the database `settings` points to, sorted."""
    database = Database(settings.url)
    try:
        with database.transaction() as session:
            return list(session.scalars(select(RegisteredModel.name).order_by(RegisteredModel.name)))
    finally:
        database.dispose()


def list_flights(q: str | None = None, limit: int = 1000, settings: Settings | None = None) -> dict:
    """{"items": [...], "total"}: the stored flights by id (those whose name contains ``q``)."""
    with registry_database(settings) as db:
        total, rows = catalog.list_flights(db, *catalog.name_contains(q), limit=limit)
    return {"total": total, "items": [{
        "id": r.id, "name": r.name, "adapter": r.adapter, "vehicle": r.vehicle, "duration_s": r.duration_s,
        "rate_hz": r.rate_hz, "samples": r.samples, "quality": r.quality, "sha256": r.sha256,
        "created_at": r.created_at.isoformat()} for r in rows]}


def list_models(q: str | None = None, settings: Settings | None = None) -> dict:
    """{"items": [...], "total"}: the registered models by name (those whose name contains ``q``)."""
    with registry_database(settings) as db:
        models = catalog.list_models(db, q=q)
    return {"total": len(models), "items": [{
        "name": m.model.name, "versions": m.version_count, "latest_version": m.latest_version,
        "aliases": m.aliases, "created_at": m.model.created_at.isoformat()} for m in models]}


def show_model(ref: str, settings: Settings | None = None) -> dict:
    """"NAME": the model with its versions and aliases; "NAME:N" or "NAME@ALIAS": that version with its
    hyperparameters, metrics, timing, lineage and evaluations (service.operations.comparison.version_lineage)."""
    from ..operations.comparison import version_lineage
    from ..storage.references import parse_ref

    parsed = parse_ref(ref)
    with registry_database(settings) as db:
        if parsed.version is None and parsed.alias is None:
            detail = catalog.get_model(db, parsed.name)
            return {"name": parsed.name, "aliases": detail.aliases, "latest_version": detail.latest_version,
                    "versions": [_version_json(v, detail.aliases) for v in detail.versions]}
        with db.transaction() as session:
            row = registry.get_version(session, parsed.name, parsed.version) if parsed.version is not None \
                else registry.resolve(session, parsed)
            aliases = registry.aliases_of(session, parsed.name)
        lineage = version_lineage(db, row.name, row.version)
    lineage["evaluations"] = [{**e, "created_at": e["created_at"].isoformat()} for e in lineage["evaluations"]]
    return {**_version_json(row, aliases), "prior": row.prior, "code_version": row.code_version,
            "lineage": lineage}


def _version_json(row, aliases: dict[str, int]) -> dict:
    return {"ref": f"{row.name}:{row.version}", "name": row.name, "version": row.version, "status": row.status,
            "error": row.error, "aliases": sorted(a for a, v in aliases.items() if v == row.version),
            "training_flight": {"id": row.training_flight_id, "name": row.training_flight_name},
            "training_flights": registry.training_flights_of(row),
            "validation_flights": list(row.validation_flights or []),
            "learned": (row.metrics or {}).get("learned"), "learned_note": (row.metrics or {}).get("learned_note"),
            "noise": (row.metrics or {}).get("noise") or {"model": None, "prior": None},
            "parent": row.parent, "hyperparameters": row.hyperparameters, "metrics": row.metrics,
            "training_seconds": row.training_seconds, "created_at": row.created_at.isoformat()}


def set_alias(name: str, version: int, alias: str, settings: Settings | None = None) -> dict:
    """Point NAME@ALIAS at VERSION (as PUT /models/{name}/aliases/{alias}); returns what it did, with the
    version the alias pointed at before (None if it is new)."""
    with registry_database(settings) as db:
        with db.transaction() as session:
            before = registry.aliases_of(session, name).get(alias)
            registry.set_alias(session, name, alias, version)
            audit.record(session, None, "alias.set", f"alias {name}@{alias}", {"version": version})
    return {"name": name, "alias": alias, "version": version, "previous_version": before}

