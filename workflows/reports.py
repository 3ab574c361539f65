"""The diagnosis and evaluation reports as types (`learnest.records.Record`: `to_dict` gives back the stored
JSON, key for key).

The diagnosis workflow builds its `DiagnosisReport` (`workflows.diagnosis.diagnosis_report`), the evaluation its
`EvaluationReport` (`estimators.evaluation_report`, re-exported here: `estimators.evaluate.summarize` builds it);
each is serialised once, where it is stored or handed to a user as a dict.  The API's response schemas are built
from these classes (`service.api.report_models`).  Units are in each field's doc.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from learnest.estimators.evaluation_report import EvaluationReport, FlightScore
from learnest.records import Record, doc

__all__ = ["DiagnosisEffect", "DiagnosisFlight", "DiagnosisReport", "EvaluationReport", "FlightScore",
           "RepairVerdict"]


@dataclass(frozen=True)
class DiagnosisEffect(Record):
    """One named effect the diagnosis added to the prior (or measurement model), with its fitted values."""

    id: str = field(default="", metadata=doc('the effect, e.g. "accel_bias", "drag", "mass", "thrust_gain"'))
    channel: str | None = field(default=None, metadata=doc('the residual channel it explains ("accelerometer", '
                                                            '"translational dynamics", ...)'))
    params: dict[str, float] = field(default_factory=dict, metadata=doc("{parameter: fitted value, in `units`}"))
    nominal: dict[str, float] = field(default_factory=dict, metadata=doc("{parameter: the prior's value}"))
    units: dict[str, str] = field(default_factory=dict, metadata=doc("{parameter: unit (SI)}"))
    ci95: dict[str, list[float]] = field(default_factory=dict,
                                         metadata=doc("{parameter: [low, high] 95 % interval, in `units`}"))
    identified: dict[str, bool] = field(default_factory=dict,
                                        metadata=doc("{parameter: the data determine it (only these repair)}"))
    at_bound: dict[str, bool] = field(default_factory=dict,
                                      metadata=doc("{parameter: the fit ended at a bound of its range (no value)}"))
    bounds: dict[str, list[float]] = field(default_factory=dict, metadata=doc("{parameter: [lower, upper]}"))
    explained_fraction: float | None = field(default=None,
                                             metadata=doc("fraction of the residual's sum of squares it explains"))
    equation: str | None = field(default=None, metadata=doc("the effect with its values, in words"))
    alternatives: list[dict[str, Any]] = field(default_factory=list,
                                               metadata=doc("effects the data cannot tell apart from this one"))


@dataclass(frozen=True)
class RepairVerdict(Record):
    """Whether the repaired model improves the held-out flights (a repair that does not is not registered)."""

    improves: bool = field(default=False, metadata=doc("the repair improves the held-out flights"))
    method: str | None = field(default=None, metadata=doc("the score the verdict is on"))
    reason: str | None = field(default=None, metadata=doc("why, in words"))


@dataclass(frozen=True)
class DiagnosisFlight(Record):
    """One held-out flight, scored before and after the repair."""

    flight: str = field(default="", metadata=doc("the flight's name"))
    before: dict[str, float] = field(default_factory=dict, metadata=doc(
        "{method: score before, MSE over [p, v, a] (SI units squared) or specific-force RMSE, m/s²}"))
    after: dict[str, float] = field(default_factory=dict, metadata=doc("{method: score after, as before}"))
    repair_gain_interval_pct: dict[str, list[float] | None] = field(
        default_factory=dict, metadata=doc("{method: [low, high] 95 % interval of the repair's gain, %}"))


@dataclass(frozen=True)
class DiagnosisReport(Record):
    """A diagnosis: the effects found, the before/after scores and the split of the flights.

    Crazyflie reports also carry ``thrust_source``, ``vehicle_fits_prior``, ``repair`` (and ``prior``,
    ``declared_mass_kg``, ``candidates``, ``thrust_map_fit``); the service adds ``registered`` or
    ``not_registered``.
    """

    NESTED: ClassVar[dict[str, tuple[str, type[Record]]]] = {
        "effects": ("list", DiagnosisEffect), "repair": ("one", RepairVerdict), "per_flight": ("list", DiagnosisFlight)}

    system: str = field(default="quadrotor", metadata=doc('the prior diagnosed, "quadrotor" or "crazyflie"'))
    effects: list[DiagnosisEffect] = field(default_factory=list, metadata=doc("the effects added, most explaining "
                                                                              "first"))
    confounded: list[dict[str, Any]] = field(default_factory=list,
                                             metadata=doc("pairs of effects the data cannot tell apart"))
    thrust_source: str | None = field(default=None, metadata=doc('where the thrust comes from: "pwm" (motor PWM and '
                                                                 'battery), "rpm" (rotor speed) or "thrust_n" (N)'))
    vehicle_fits_prior: dict[str, Any] | None = field(default=None, metadata=doc(
        "whether the vehicle's thrust over mass matches the prior's: ok, thrust_gain, message"))
    repair: RepairVerdict | None = field(default=None, metadata=doc("whether the repair improves held-out flights"))
    fitting_flights: list[str] = field(default_factory=list, metadata=doc("the flights the effects were fitted on"))
    scored_flights: list[str] = field(default_factory=list, metadata=doc("the flights scored before and after"))
    split: str | None = field(default=None, metadata=doc("how the flights were split, in words"))
    before: dict[str, float] = field(default_factory=dict, metadata=doc("{method: median score before over the "
                                                                        "scored flights}"))
    after: dict[str, float] = field(default_factory=dict, metadata=doc("{method: median score after}"))
    per_flight: list[DiagnosisFlight] = field(default_factory=list, metadata=doc("each scored flight"))
    improved_flights: dict[str, str] = field(default_factory=dict,
                                             metadata=doc('{method: "k/n" flights the repair improved}'))
    registered: dict[str, Any] | None = field(default=None, metadata=doc(
        "the version the repaired model was registered as {name, version, parent}, or None"))

    @property
    def improves(self) -> bool:
        """The repair verdict (True for a stored report that carries none)."""
        return True if self.repair is None else self.repair.improves
