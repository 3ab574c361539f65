"""Diagnosis jobs: `learnest diagnose` on stored flights (on the executor), registering the repaired model
as a child version when asked, and storing the report."""
from __future__ import annotations

from learnest.errors import InvalidInput
from learnest.models.presets import diagnosis_fitting_count

from ..storage import registry
from ..storage.database import flights_by_id, flights_not_found, get_row
from ..storage.tables import Diagnosis, utcnow
from . import quotas
from .runner import JobAborted, JobContext
from .services import Services
from .tasks import diagnose_task, diagnosis_metrics
from .training import training_config


def start_diagnosis(services: Services, flight_ids: list[int], model_ref: str | None, register: str | None,
                    methods: list[str], epochs: int, system: str = "quadrotor", force: bool = False,
                    created_by: str | None = None) -> tuple[int, int]:
    """Create the diagnosis and its job and launch it.  -> (job id, diagnosis id).  ``created_by``: the name of
    the token that asks for it, kept on the diagnosis and on the version it registers (None without a token).

    ``register``: registered only if the repair improves the held-out flights (the report's ``repair``
    verdict), unless ``force`` (then with a warning stored in the version's metrics).

    Raises
    ------
    InvalidInput
        For a bad ``register`` name or no flights; `quotas.QuotaExceeded` for more epochs or work than the
        settings allow (on the flights the diagnosis fits: `fitting_samples`).
    NotFound
        If a flight or the model does not exist.
    Conflict
        If the model version is not ready.
    """
    if register is not None:
        registry.check_name(register)
    ids = list(dict.fromkeys(int(i) for i in flight_ids))
    if not ids:
        raise InvalidInput("flights: give at least one flight id (the first is the fitting flight)")
    with services.db.transaction() as session:
        found = flights_by_id(session, ids)
        missing = [i for i in ids if i not in found]
        if missing:
            raise flights_not_found(missing)
        quotas.check_training(services.settings, epochs=epochs, hidden=training_config({})["hidden"],
                              samples=fitting_samples([found[i] for i in ids], system), what="diagnosis")
        if model_ref is not None:
            version = registry.resolve(session, model_ref)
            model_ref = f"{version.name}:{version.version}"
        settings = {"methods": list(methods), "epochs": epochs, "system": system, **({"force": True} if force else {})}
        job = services.runner.create(session, "diagnosis", {"flights": ids, "model": model_ref,
                                                            "register": register, **settings})
        diagnosis = Diagnosis(job_id=job.id, flight_ids=ids, model_ref=model_ref, register_as=register,
                              settings=settings, created_at=utcnow(), created_by=created_by)
        session.add(diagnosis)
        session.flush()
        job_id, diagnosis_id = job.id, diagnosis.id
    services.runner.launch(job_id, lambda ctx: run_diagnosis(services, ctx, diagnosis_id))
    return job_id, diagnosis_id


def fitting_samples(rows, system: str) -> int:
    """Samples of the flights a diagnosis fits its KNODE on, chosen as `workflows.diagnosis` chooses them:
    the flights that pass the quality checks (all, if none does), then the first of them (kinematic prior) or
    the first half, rounded up (input-driven Crazyflie prior).  The quota is charged on these, not on the
    first flight named: a short bad flight named first is dropped, and the big one after it is fitted."""
    used = [row for row in rows if row.quality_ok] or list(rows)
    return sum(int(row.samples) for row in used[:diagnosis_fitting_count(len(used), system)])


def run_diagnosis(services: Services, ctx: JobContext, diagnosis_id: int) -> None:
    """The diagnosis job's work: diagnose on the executor, register the repaired model if asked, store the
    report.  The fitting flight is found by name among the diagnosis' flights (first flight if none matches)."""
    with services.db.transaction() as session:
        diagnosis = get_row(session, Diagnosis, diagnosis_id, "diagnosis")
        flights = flights_by_id(session, diagnosis.flight_ids)
        if len(flights) != len(diagnosis.flight_ids):
            raise InvalidInput("a flight of this diagnosis was deleted before it started")
        blobs = [flights[i].flight_blob for i in diagnosis.flight_ids]
        weights = None
        if diagnosis.model_ref is not None:
            weights = registry.weights_of(registry.resolve(session, diagnosis.model_ref))
        settings, model_ref, register = dict(diagnosis.settings), diagnosis.model_ref, diagnosis.register_as
        created_by = diagnosis.created_by
        first_flight_id = diagnosis.flight_ids[0]
    ctx.progress(0.01, f"reading {len(blobs)} flight(s)")
    out = ctx.wait(services.executor,
                   services.executor.submit(diagnose_task, [services.blobs.read_bytes(b) for b in blobs],
                                            services.blobs.read_bytes(weights) if weights else None,
                                            settings["methods"], settings["epochs"],
                                            settings.get("system", "quadrotor"), ctx.progress_target))
    ctx.progress(0.95, "storing the report" + (f" and registering {register}" if register else ""))
    registered, warning = None, None
    verdict = out["report"].get("repair") or {"improves": False, "reason": "the diagnosis gave no verdict on them"}
    if register is not None and not verdict["improves"]:
        # a repair that does not improve the held-out flights is not registered (models.diagnosis's rule)
        if settings.get("force"):
            warning = ("registered with force although the repair does not improve held-out flights: "
                       f"{verdict['reason']}")
        else:
            out["report"]["not_registered"] = (f"the repair does not improve the held-out flights "
                                               f"({verdict['reason']}); force registers it anyway")
            register = None
    if register is not None:
        if not ctx.runner.is_running(ctx.job_id):  # cancelled while diagnosing: register nothing
            raise JobAborted(ctx.job_id)
        model = registry.model_from_json(out["model_json"])
        # the fitting flight: diagnose_flights skips flights that fail the quality checks, so go by name
        fitting = next((f for f in flights.values() if f.name == out["fitting_flight"]),
                       flights[first_flight_id])
        row = registry.register_model(services.db, services.blobs, register, model, flight=fitting,
                                      hyperparameters=training_config({"epochs": settings["epochs"],
                                                                       "system": model.system.name}),
                                      parent=model_ref, job_id=ctx.job_id, created_by=created_by,
                                      metrics={**diagnosis_metrics(model, out["report"]),
                                               **({"warning": warning} if warning else {})})
        registered = {"name": row.name, "version": row.version, "parent": row.parent,
                      **({"warning": warning} if warning else {})}
    with services.db.transaction() as session:
        diagnosis = get_row(session, Diagnosis, diagnosis_id, "diagnosis")
        # the report's JSON as the task serialised it (`DiagnosisReport.to_dict`), kept as it came
        diagnosis.report, diagnosis.registered = out["report"], registered
        ctx.complete(session, {"diagnosis_id": diagnosis_id, "effects": [e["id"] for e in out["report"]["effects"]],
                               "registered": registered})
