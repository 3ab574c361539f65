"""Request and response bodies of the HTTP API (pydantic), kept apart from the storage tables
(service.storage.tables).  The reports' response schemas are built from the typed reports: service.api.report_models."""
from __future__ import annotations

from datetime import datetime
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, field_validator, model_validator

from learnest.estimators.evaluation_settings import EvaluationSettings, Noise
from learnest.models.presets import (
    CRAZYFLIE_TRAINING,
    DIAGNOSIS_SPLIT_RULE,
    EVALUATION_METHODS,
    SG_WINDOW_RANGE,
    parse_methods,
)

from ..storage.references import NAME

NAME_REGEX = rf"^{NAME}$"  # references.NAME: one definition of a valid name

# The one integer-range rule of every id and version number a request names, in a path, a query, a JSON body
# or a form: ids are SQL BIGINTs, so a larger number names nothing, and the database driver cannot even bind it
# (SQLite: OverflowError, a 500).  Checked at the boundary, it is a 422 that says the range.
MAX_ROW_ID = 2**63 - 1
RowIdValue = Annotated[int, Field(ge=1, le=MAX_ROW_ID)]


class Strict(BaseModel):
    """A request body: unknown fields are an error (a misspelt "epoch" must not silently train 150 epochs), and
    so is a value of another JSON type (``"epochs": true`` was read as 1, ``"5"`` as 5, ``"flights": [true]``
    as flight 1).  The web forms, whose every field is text, validate the same models with ``strict=False``
    (service.web.forms)."""

    model_config = ConfigDict(extra="forbid", strict=True)


# -- flights ------------------------------------------------------------------------------------------
class Quality(BaseModel):
    ok: bool
    issues: list[str] = []


class SourceFile(BaseModel):
    name: str = Field(description="the client's file name (metadata only)")
    sha256: str
    size_bytes: int
    role: str = Field(description='"log", or "sidecar" for a NanoBench *_metadata.yaml or a crazyswarm2 infoNNN.yaml')


class FlightOut(BaseModel):
    id: int
    name: str
    adapter: str
    vehicle: str | None
    notes: str | None
    duration_s: float
    rate_hz: float
    samples: int
    quality: Quality
    clock_offset_s: float | None
    sha256: str = Field(description="sha256 over the sorted sha256s of the raw files: the dedupe key")
    sources: list[SourceFile]
    created_at: datetime
    created_by: str | None = Field(None, description="the name of the token that made it (None: no token)")


class FlightDetail(FlightOut):
    meta: dict[str, Any] = Field(description="the normalized flight's metadata (rates, streams, gaps, ...)")


class FlightPage(BaseModel):
    items: list[FlightOut]
    total: int
    limit: int
    offset: int


# -- models -------------------------------------------------------------------------------------------
class TrainRequest(Strict):
    name: str = Field(pattern=NAME_REGEX, description="registered model name")
    flight_id: RowIdValue | None = Field(None, description="one flight (the paper's protocol: time blocks of it "
                                                          "validate); or give flight_ids")
    flight_ids: list[RowIdValue] | None = Field(
        None, min_length=1, max_length=1000,
        description="several flights of one vehicle, trained on as one model (one pooled loss)")
    validation_ids: list[RowIdValue] | None = Field(
        None, max_length=1000, description="flights held out whole to choose the kept epoch (default with several "
                                           "flights: one in five)")
    epochs: int | None = Field(None, ge=1, le=100_000)
    hidden: int | None = Field(None, ge=1, le=4096)
    lr: float | None = Field(None, gt=0, le=1)
    system: Literal["quadrotor", "crazyflie"] = Field(
        "quadrotor", description="the prior: the paper's kinematic chain, or the Crazyflie driven by its motors "
                                 "and battery (the flight must carry motor PWM and battery voltage, rotor "
                                 "speed, or the controller's thrust in N)")
    group_by: str | None = Field(
        None, max_length=200, description="several flights: the groups held out in turn to choose how much of the "
                                          "residual to keep: 'family' (the trajectory family the logs declare; the "
                                          "default), 'name:REGEX' (one capture group of each flight's name) or "
                                          "'none' (the whole residual)")
    noise: Literal["paper", "identified"] = Field(
        "identified", description="'identified' (the default): the model's and its prior's process noise identified "
                                  "on the training flights by the UKF's likelihood (innovations and hidden mocap), "
                                  "stored with the version, and used by every evaluation of it; 'paper': the "
                                  "system's fixed noise")
    ensemble: int = Field(1, ge=1, le=10, description="several flights: residuals trained from different seeds; their "
                          "mean is the model and their disagreement on a flight joins its process noise")
    parent: str | None = Field(None, description='"name:version" or "name@alias" this version derives from')
    include_bad: bool = Field(False, description="train even if the flight failed the quality checks")

    @model_validator(mode="after")
    def one_way_to_name_flights(self) -> TrainRequest:
        if (self.flight_id is None) == (self.flight_ids is None):
            raise ValueError("give flight_id (one flight) or flight_ids (several), not both or neither")
        return self

    def flights(self) -> int | list[int]:
        """The flight id, or the list of ids, to train on."""
        return self.flight_id if self.flight_id is not None else list(self.flight_ids or [])


class TrainAccepted(BaseModel):
    job_id: int
    name: str
    version: int
    status: str


class TrainingFlight(BaseModel):
    id: int | None
    sha256: str | None
    name: str | None


class VersionSummary(BaseModel):
    name: str
    version: int
    status: Literal["training", "ready", "failed"]
    job_id: int | None
    training_flight: TrainingFlight = Field(description="the first training flight (of one, the only one)")
    training_flights: list[TrainingFlight] = Field(default_factory=list,
                                                   description="every flight the version was trained on")
    validation_flights: list[TrainingFlight] = Field(
        default_factory=list, description="flights held out whole to choose the kept epoch (none for one flight, "
                                          "whose validation is time blocks of it)")
    learned: bool | None = Field(None, description="false when no epoch predicted the held-out data better than the "
                                                   "prior: the version equals its prior (None: not known, e.g. "
                                                   "still training or stored before it was recorded)")
    learned_note: str | None = Field(None, description="what `learned: false` means, in words")
    residual_scale: float | None = Field(None, description="the scale s of the residual kept, f = f_prior + s Δθ "
                                                           "(None: not known, e.g. still training)")
    residual_scale_groups: list[str] = Field(default_factory=list,
                                             description="the groups of training flights held out to choose it")
    residual_scale_note: str | None = Field(None, description="how the scale was chosen, or why none was")
    noise: dict[str, Any] = Field(default_factory=dict, description=(
        "the noise the version's filters run with: {\"model\": ..., \"prior\": ...}, each null (the system's "
        "fixed noise, the paper's) or {source, process_per_step, measurement, initial: standard deviations per "
        "block with units, detail: how it was identified on the training flights}"))
    parent: str | None
    hyperparameters: dict[str, Any]
    metrics: dict[str, Any] | None
    error: str | None
    aliases: list[str]
    created_at: datetime
    created_by: str | None = Field(None, description="the name of the token that made it (None: no token)")
    ready_at: datetime | None


class VersionOut(VersionSummary):
    prior: dict[str, Any] | None
    losses: list[float | None] | None = Field(description="training loss per epoch")
    validation_losses: list[float | None] | None = Field(
        None, description="validation loss per epoch (the held-out tail of the flight; None for versions "
                          "stored before it was kept, or made by a diagnosis)")
    training_seconds: float | None
    code_version: dict[str, Any] | None
    library_versions: dict[str, Any] | None
    weights_sha256: str | None


class ModelOut(BaseModel):
    name: str
    created_at: datetime
    aliases: dict[str, int]
    latest_version: int | None = Field(description="highest ready version")
    versions: list[VersionSummary]


class ModelItem(BaseModel):
    name: str
    created_at: datetime
    aliases: dict[str, int]
    latest_version: int | None
    version_count: int


class ModelPage(BaseModel):
    items: list[ModelItem]
    total: int


class AliasIn(Strict):
    version: RowIdValue


class AliasOut(BaseModel):
    name: str
    alias: str
    version: int


# -- jobs and evaluations -----------------------------------------------------------------------------
class JobOut(BaseModel):
    id: int
    kind: str
    state: Literal["queued", "running", "succeeded", "failed", "cancelled"]
    progress: float
    stage: str | None = Field(None, description='what the job does now: "observer", "epoch 12/150", '
                                                '"knode-mhe on flight3 (2/4)", "MHE build (mhe) on ..."')
    eta_s: float | None = Field(None, description="seconds left, estimated from the pace so far (None: not "
                                                  "known yet, or the job is not running)")
    error: str | None
    result: dict[str, Any] | None
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


# what an evaluation request leaves out: the settings' own defaults
EVALUATION_DEFAULTS = EvaluationSettings()


class EvaluationRequest(Strict):
    """An evaluation to start.  The bounds below are what the schema documents; the settings are checked by
    their type (`EvaluationSettings`), built once here and handed on as `settings`."""

    model: str = Field(description='"name:version" or "name@alias"')
    flights: list[RowIdValue] | Literal["all-other"] = Field(
        description='flight ids, or "all-other": every stored flight except the model\'s training flight')
    methods: list[str] = Field(default_factory=lambda: list(EVALUATION_DEFAULTS.methods),
                               description=f"any of {', '.join(EVALUATION_METHODS)} (onboard: the vehicle's own "
                                           "estimate, scored on the fast reference where the log carries it)")
    horizon: int = Field(EVALUATION_DEFAULTS.horizon, ge=1, le=500, description="MHE horizon N")
    include_bad: bool = Field(EVALUATION_DEFAULTS.include_bad,
                              description="also score flights that fail the quality checks")
    sg_window: int = Field(EVALUATION_DEFAULTS.sg_window, ge=SG_WINDOW_RANGE[0], le=SG_WINDOW_RANGE[1],
                           description="Savitzky-Golay window of the reference states, samples (default: the "
                                       "paper's 150, about 1.5 s at 100 Hz; shorter follows fast manoeuvres, "
                                       "whose velocity peaks a 1.5-s window clips)")
    gap_s: float = Field(EVALUATION_DEFAULTS.gap_s, ge=0.0, le=30.0,
                         description="mocap-gap yardstick: how long the mocap position is hidden from the estimators "
                                     "in each gap, s (0: no gaps)")
    gap_every_s: float = Field(EVALUATION_DEFAULTS.gap_every_s, gt=0.0, le=300.0,
                               description="mocap-gap yardstick: one gap every this many seconds, after the first "
                                           "5 s of the kept flight; longer than gap_s")
    noise: Noise = Field(
        EVALUATION_DEFAULTS.noise,
        description="'identified': the KNODE and its prior each with its own noise identified on the training "
                    "flights (the system's fixed noise for a model trained without it); 'paper': both with the "
                    "system's fixed noise")
    _settings: EvaluationSettings = PrivateAttr(default=EVALUATION_DEFAULTS)

    @model_validator(mode="after")
    def settings_in_bounds(self) -> EvaluationRequest:
        # the settings' one check (InvalidInput is a ValueError: a 422 naming the field); one sample of each
        # flight's grid and MAX_GAPS per flight are checked when the job is created (service.jobs.evaluation)
        self._settings = EvaluationSettings(tuple(self.methods), self.horizon, self.include_bad, self.sg_window,
                                            self.gap_s, self.gap_every_s, self.noise)
        return self

    @property
    def settings(self) -> EvaluationSettings:
        """The request's settings, as its validation built them."""
        return self._settings


class EvaluationAccepted(BaseModel):
    job_id: int
    evaluation_id: int
    state: str


class EvaluationPending(BaseModel):
    evaluation_id: int
    job_id: int
    state: str
    progress: float


# -- diagnoses ----------------------------------------------------------------------------------------
class DiagnosisRequest(Strict):
    flights: list[RowIdValue] = Field(min_length=1, description="flight ids, in order: " + DIAGNOSIS_SPLIT_RULE
                               + " (the report names them in `fitting_flights` and `scored_flights`)")
    model: str | None = Field(None, description='the KNODE analysed, "name:version" or "name@alias" (default: '
                              "one trained on the fitting flight)")
    register_as: str | None = Field(None, alias="register", pattern=NAME_REGEX,
                                    description="register the repaired model as the next version of this name "
                                                "(parent: `model`), only if it improves the held-out flights by "
                                                "the evaluation's interval rule (the report's `repair` says)")
    force: bool = Field(False, description="register even a repair that does not improve the held-out flights, "
                                           "with a warning stored in the version")
    methods: list[str] = Field(default_factory=lambda: ["ukf", "knode-ukf"],
                               description="estimators scored before and after")
    epochs: int = Field(CRAZYFLIE_TRAINING.epochs, ge=1, le=100_000,
                        description=f"KNODE training epochs (Sec. V-C: {CRAZYFLIE_TRAINING.epochs})")
    system: Literal["quadrotor", "crazyflie"] = Field(
        "quadrotor", description='the prior diagnosed: "quadrotor" (kinematic) or "crazyflie" (driven by motors '
                                 "and battery; its flights need motor PWM and battery voltage)")

    @field_validator("methods")
    @classmethod
    def known_methods(cls, methods: list[str]) -> list[str]:
        return parse_methods(",".join(methods))


class DiagnosisAccepted(BaseModel):
    job_id: int
    diagnosis_id: int


class DiagnosisPending(BaseModel):
    diagnosis_id: int
    job_id: int
    state: str
    progress: float


# -- the registry across rows: dependents, evaluations list, lineage, comparison ---------------------------
class DependentItem(BaseModel):
    kind: str = Field(description='"evaluation", "alias", "results", "model version", "diagnosis", "job", ...')
    label: str
    href: str | None = None
    model_config = ConfigDict(extra="allow")


class Dependents(BaseModel):
    target: dict[str, Any]
    deleted_with_it: list[DependentItem] = Field(description="deleted together with the object")
    keeps_a_record: list[DependentItem] = Field(description="stays, keeping the object's id/name as lineage text")
    requires_force: bool = Field(description="DELETE answers 409 unless force=true (things a user made or points "
                                             "at would be deleted with it)")
    blocked: str | None = Field(description="why it cannot be deleted now, whatever force says (still computing)")


class EvaluationItem(BaseModel):
    id: int
    job_id: int
    state: str
    model_ref: str
    model: str
    version: int | None
    flight_ids: list[int]
    flights_scored: int | None
    methods: list[str]
    median_mse: dict[str, float] = Field(description="median over the scored flights of the MSE over [p, v, a]")
    improvement_pct: dict[str, float] = Field(description='"knode-ukf_vs_ukf": 100 (1 - KNODE/prior), positive '
                                                          "is better")
    created_at: datetime
    created_by: str | None = Field(None, description="the name of the token that made it (None: no token)")
    links: dict[str, str]


class EvaluationPage(BaseModel):
    items: list[EvaluationItem]
    total: int
    limit: int
    offset: int
