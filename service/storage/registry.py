"""Model registry, after MLflow: registered model -> immutable integer versions -> movable aliases.

A reference is "name:version", "name@alias" or "name" (its latest ready version).  A version number is
reserved when training is requested; the row is usable only once its status is "ready".

From Python or the CLI: `load_model_ref("quad@production")` -> HybridModel.
"""
from __future__ import annotations

import importlib.metadata
import json
import platform
import tempfile
from collections.abc import Sequence
from pathlib import Path

from sqlalchemy import func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from learnest.errors import Conflict, NotFound
from learnest.models.knode import HybridModel

from ..config import Settings
from .blobs import BlobStore
from .database import Database, discard_blobs
from .references import ModelRef, check_name, parse_ref
from .tables import FlightRecord, ModelAlias, ModelVersion, RegisteredModel, utcnow

LIBRARIES = ("torch", "casadi", "filterpy", "numpy", "scipy", "torchdiffeq")


# -- lookups ------------------------------------------------------------------------------------------
def get_version(session: Session, name: str, version: int) -> ModelVersion:
    """The row of ``name:version`` whatever its status; `NotFound` if there is none."""
    row = session.scalar(select(ModelVersion).where(ModelVersion.name == name, ModelVersion.version == version))
    if row is None:
        raise NotFound(f"model {name!r} has no version {version}")
    return row


def get_model(session: Session, name: str) -> RegisteredModel:
    """The registered model ``name``; `NotFound` if there is none."""
    model = session.get(RegisteredModel, name)
    if model is None:
        raise NotFound(f"no registered model named {name!r}")
    return model


def resolve(session: Session, ref: str | ModelRef) -> ModelVersion:
    """The ready ModelVersion a reference points to (NotFound / Conflict otherwise)."""
    ref = parse_ref(ref) if isinstance(ref, str) else ref
    get_model(session, ref.name)
    version = ref.version
    if ref.alias is not None:
        alias = session.get(ModelAlias, (ref.name, ref.alias))
        if alias is None:
            raise NotFound(f"model {ref.name!r} has no alias {ref.alias!r}")
        version = alias.version
    if version is None:
        version = session.scalar(select(func.max(ModelVersion.version))
                                 .where(ModelVersion.name == ref.name, ModelVersion.status == "ready"))
        if version is None:
            raise NotFound(f"model {ref.name!r} has no ready version yet")
    row = get_version(session, ref.name, version)
    if row.status != "ready":
        raise Conflict(f"{ref.name}:{version} is not usable: status {row.status!r}"
                       + (f" ({row.error})" if row.error else ""))
    return row


def aliases_of(session: Session, name: str) -> dict[str, int]:
    """{alias: version} of model ``name``, in alias order."""
    rows = session.scalars(select(ModelAlias).where(ModelAlias.name == name).order_by(ModelAlias.alias))
    return {row.alias: row.version for row in rows}


# -- writes -------------------------------------------------------------------------------------------
def flight_entry(flight: FlightRecord) -> dict:
    """A flight as the lineage records it: {"id", "name", "sha256"} (the sha256 of its raw files)."""
    return {"id": flight.id, "name": flight.name, "sha256": flight.sha256}


def training_flights_of(row: ModelVersion) -> list[dict]:
    """Every training flight of a version ({"id", "name", "sha256"}), the single ``training_flight_*`` of a
    row stored without the list."""
    if row.training_flights:
        return list(row.training_flights)
    if row.training_flight_name is None and row.training_flight_id is None:
        return []
    return [{"id": row.training_flight_id, "name": row.training_flight_name, "sha256": row.training_flight_sha256}]


def reserve_version(session: Session, name: str, *, job_id: int | None, flight: FlightRecord, hyperparameters: dict,
                    parent: str | None, training_flights: Sequence[FlightRecord] = (),
                    validation_flights: Sequence[FlightRecord] = ()) -> ModelVersion:
    """Take the next version number of `name` (status "training").  Two concurrent requests may pick the
    same number: the unique (name, version) constraint rejects one, and the caller retries.

    ``flight`` is the (first) training flight; ``training_flights`` every training flight (default:
    ``flight`` alone) and ``validation_flights`` those held out whole, recorded as lineage."""
    check_name(name)
    model = session.get(RegisteredModel, name)
    if model is None:
        model = RegisteredModel(name=name, created_at=utcnow(), last_version=0)
        session.add(model)
        session.flush()
    # never a number handed out before, also when that version was deleted since (last_version)
    latest = max(session.scalar(select(func.max(ModelVersion.version)).where(ModelVersion.name == name)) or 0,
                 model.last_version or 0)
    model.last_version = latest + 1
    row = ModelVersion(name=name, version=latest + 1, status="training", job_id=job_id,
                       training_flight_id=flight.id, training_flight_sha256=flight.sha256,
                       training_flight_name=flight.name, parent=parent, hyperparameters=hyperparameters,
                       training_flights=[flight_entry(f) for f in (training_flights or [flight])],
                       validation_flights=[flight_entry(f) for f in validation_flights], created_at=utcnow())
    session.add(row)
    session.flush()
    return row


def register_model(db: Database, blobs: BlobStore, name: str, model: HybridModel, *, flight: FlightRecord,
                   hyperparameters: dict, parent: str | None = None, job_id: int | None = None,
                   metrics: dict | None = None, created_by: str | None = None) -> ModelVersion:
    """Store a model made outside a training job (a diagnosis' repaired model) as the next ready version of
    `name`: weights, prior (its prior params plus the measurement effects and effect ids in its meta),
    training flight, hyperparameters, parent ("name:version" it was derived from), provenance and the name
    of the token that asked for it (``created_by``)."""
    check_name(name)
    model_json = model_to_json(model)
    prior = {**prior_of(model_json), "measurement_effects": model.meta.get("measurement_effects") or {},
             "effects": model.meta.get("effects") or []}
    weights = None
    try:
        with blobs.writing():  # the weights blob exists before the row that names it commits
            weights = blobs.put_bytes(model_json)
            for attempt in range(20):  # another request may take the same version number first
                try:
                    with db.transaction() as session:
                        if parent is not None:
                            resolved = resolve(session, parent)
                            parent = f"{resolved.name}:{resolved.version}"
                        row = reserve_version(session, name, job_id=job_id, flight=flight,
                                              hyperparameters=hyperparameters, parent=parent)
                        row.status, row.weights_blob, row.ready_at, row.prior = "ready", weights, utcnow(), prior
                        row.metrics, row.created_by = metrics, created_by
                        row.code_version, row.library_versions = code_version(), library_versions()
                    return row
                except IntegrityError:
                    if attempt == 19:
                        raise
    except BaseException:  # the version and its weights appear together or not at all
        if weights is not None:
            discard_blobs(db, blobs, [weights])
        raise
    raise AssertionError("unreachable: the last attempt returns or re-raises")


def fail_versions_of_jobs(session: Session, job_ids: list[int], reason: str) -> None:
    """A training job that died leaves its reserved version "failed" with the reason, never "training"."""
    if not job_ids:
        return
    for row in session.scalars(select(ModelVersion).where(ModelVersion.job_id.in_(job_ids),
                                                          ModelVersion.status == "training")):
        row.status, row.error = "failed", reason


def drop_unfinished_versions(session: Session, job_id: int) -> list[str]:
    """Delete the versions job ``job_id`` reserved and never finished (no weights), and a model name left with
    no version and no alias: what an interrupted `learnest train` leaves is no version at all (the CLI never
    announced the number; the API's reserved versions stay, failed, since their clients know them).
    Returns the "name:version" references removed."""
    rows = session.scalars(select(ModelVersion).where(ModelVersion.job_id == job_id,
                                                      ModelVersion.weights_blob.is_(None))).all()
    for row in rows:
        session.delete(row)
    session.flush()
    for name in {row.name for row in rows}:
        left = session.scalar(select(func.count()).select_from(ModelVersion).where(ModelVersion.name == name))
        aliases = session.scalar(select(func.count()).select_from(ModelAlias).where(ModelAlias.name == name))
        model = get_model(session, name)
        if not left and not aliases and not _had_deletions(model, rows):
            session.delete(model)
        elif model.last_version == max(row.version for row in rows if row.name == name):
            model.last_version -= 1  # the number was never announced: the next training takes it
    return [f"{row.name}:{row.version}" for row in rows]


def _had_deletions(model: RegisteredModel, dropped: Sequence[ModelVersion]) -> bool:
    """Whether ``model`` handed out numbers besides the dropped ones (versions deleted since): then the
    name stays registered, so that those numbers are never reused."""
    return (model.last_version or 0) > sum(row.name == model.name for row in dropped)


def set_alias(session: Session, name: str, alias: str, version: int) -> ModelAlias:
    """Point ``alias`` of model ``name`` at ``version`` (creating or moving it).

    Raises
    ------
    InvalidInput
        If the alias is not a valid name.
    NotFound
        If the model or the version does not exist.
    Conflict
        If the version is not ready.
    """
    check_name(alias, "alias")
    get_model(session, name)
    row = get_version(session, name, version)
    if row.status != "ready":
        raise Conflict(f"{name}:{version} has status {row.status!r}; only ready versions can carry an alias")
    existing = session.get(ModelAlias, (name, alias))
    if existing is None:
        existing = ModelAlias(name=name, alias=alias, version=version, updated_at=utcnow())
        session.add(existing)
    else:
        existing.version, existing.updated_at = version, utcnow()
    return existing


def delete_alias(session: Session, name: str, alias: str) -> None:
    """Remove ``alias`` of model ``name``; `NotFound` if the model or the alias does not exist."""
    get_model(session, name)
    existing = session.get(ModelAlias, (name, alias))
    if existing is None:
        raise NotFound(f"model {name!r} has no alias {alias!r}")
    session.delete(existing)


# -- weights ------------------------------------------------------------------------------------------
def model_to_json(model: HybridModel) -> bytes:
    """HybridModel's own file format (HybridModel.save), as bytes for the blob store."""
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "model.json"
        model.save(path)
        return path.read_bytes()


def model_from_json(data: bytes) -> HybridModel:
    """Inverse of `model_to_json` (through a temporary file and `HybridModel.load`)."""
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "model.json"
        path.write_bytes(data)
        return HybridModel.load(path)


def prior_of(model_json: bytes) -> dict:
    """``system``, ``kind`` and ``prior_params`` of a serialised model."""
    data = json.loads(model_json)
    return {"system": data["system"], "kind": data["kind"], "prior_params": data["prior_params"]}


def weights_of(row: ModelVersion) -> str:
    """The sha of a version's weights blob; `NotFound` if it has none (a version still training or failed)."""
    if row.weights_blob is None:
        raise NotFound(f"{row.name}:{row.version} has no stored weights (status {row.status!r})")
    return row.weights_blob


def load_version(blobs: BlobStore, row: ModelVersion) -> HybridModel:
    """The model stored in a version's weights blob."""
    return model_from_json(blobs.read_bytes(weights_of(row)))


def load_model_ref(ref: str, settings: Settings | None = None) -> HybridModel:
    """The model a registry reference names, from the service's database and blob folder (LEARNEST_HOME,
    LEARNEST_DATABASE_URL).  model.meta carries "name", "version" and "ref".

    It never migrates: an older schema is a `Conflict` that says how to upgrade it.

    Raises
    ------
    InvalidInput
        If ``ref`` does not parse.
    NotFound
        If the model, version or alias does not exist.
    Conflict
        If the version is not ready, or the database's schema is older than this learnest.
    """
    settings = settings or Settings()
    database = Database(settings.url)
    try:
        database.require_current_schema()
        with database.transaction() as session:
            row = resolve(session, ref)
        model = load_version(BlobStore(settings.home / "blobs"), row)
    finally:
        database.dispose()
    model.meta.update({"name": row.name, "version": row.version, "ref": f"{row.name}:{row.version}"})
    return model


# -- provenance ---------------------------------------------------------------------------------------
def code_version() -> dict:
    """Package version + git commit (read from .git without running git; LEARNEST_GIT_COMMIT overrides,
    e.g. in a Docker image built without .git)."""
    try:
        version = importlib.metadata.version("learnest")
    except importlib.metadata.PackageNotFoundError:
        version = None
    return {"package": "learnest", "version": version,
            "git_commit": Settings().git_commit or _git_head(Path(__file__).resolve().parents[1])}


def _git_head(repo: Path) -> str | None:
    git = repo / ".git"
    try:
        head = (git / "HEAD").read_text().strip()
        if not head.startswith("ref: "):
            return head or None  # detached HEAD holds the commit itself
        ref = head[5:]
        loose = git / ref
        if loose.is_file():
            return loose.read_text().strip()
        for line in (git / "packed-refs").read_text().splitlines():
            if line.endswith(" " + ref):
                return line.split()[0]
    except OSError:
        pass
    return None


def library_versions() -> dict:
    """{"python": version, library: installed version or None} for the numerical libraries in ``LIBRARIES``."""
    versions: dict[str, str | None] = {"python": platform.python_version()}
    for name in LIBRARIES:
        try:
            versions[name] = importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            versions[name] = None
    return versions
