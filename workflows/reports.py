"""The diagnosis and evaluation reports as types (`learnest.records.Record`: `to_dict` gives back the stored
JSON, key for key).

`diagnose_flights` and `evaluate_flights` return their reports as dicts; the service reads them into
`DiagnosisReport` and `EvaluationReport` where it stores and serves them, and the API's response schemas are
built from these classes (`service.api.report_models`).  Units are in each field's doc.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from learnest.estimators.yardsticks import FlightYardsticks, Headline
from learnest.records import Record, doc


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


@dataclass(frozen=True)
class FlightScore(Record):
    """One flight of an evaluation: excluded (with the reason), or scored by every method."""

    SCHEMA: ClassVar[dict[str, Any]] = {"yardsticks": FlightYardsticks | None}

    flight: str = field(default="", metadata=doc("the flight's name"))
    excluded: bool = field(default=False, metadata=doc("not scored (quality, training flight, failed): see reason"))
    reason: str | None = field(default=None, metadata=doc("why it was excluded"))
    yardsticks: dict[str, Any] | None = field(default=None, metadata=doc(
        "mocap_gaps first (position RMSE in the gaps, m), fast_reference (velocity RMSE, m/s), paper_sg (the "
        "paper's MSE) (`estimators.yardsticks.FlightYardsticks`); None for an excluded flight"))
    mse: dict[str, float] = field(default_factory=dict, metadata=doc(
        "{method: the paper's MSE over [p, v, a] against the Savitzky-Golay references, SI units squared}"))
    gain_interval_pct: dict[str, list[float] | None] = field(default_factory=dict, metadata=doc(
        '{"knode-ukf_vs_ukf": [low, high] 95 % interval of the KNODE\'s gain over its prior, %}'))
    warnings: list[str] = field(default_factory=list, metadata=doc("how the flight differs from the training "
                                                                   "flight (vehicle, rates, attitude source, ...)"))
    noise: dict[str, str] = field(default_factory=dict, metadata=doc(
        '{method: "identified" (the model\'s own noise, identified on its training flights) or "paper" (the '
        "system's fixed noise)}"))

    @property
    def typed_yardsticks(self) -> FlightYardsticks | None:
        """The yardsticks as `FlightYardsticks` (None for an excluded flight)."""
        from learnest.estimators.yardsticks import FastReference, MocapGaps, PaperSG

        y = self.yardsticks
        if not y:
            return None
        return FlightYardsticks(MocapGaps(**y["mocap_gaps"]), FastReference(**y["fast_reference"]),
                                PaperSG(**y["paper_sg"]))


@dataclass(frozen=True)
class EvaluationReport(Record):
    """An evaluation: the headline (the mocap-gap yardstick) first, then every flight."""

    NESTED: ClassVar[dict[str, tuple[str, type[Record]]]] = {"flights": ("list", FlightScore)}
    SCHEMA: ClassVar[dict[str, Any]] = {"headline": Headline | None}

    model: str | None = field(default=None, metadata=doc('"name:version" of the model evaluated'))
    headline: dict[str, Any] | None = field(default=None, metadata=doc(
        "the KNODE's median gain on the mocap-gap yardstick, the flights it is better on, and worse beyond their "
        "interval (`estimators.yardsticks.Headline`)"))
    learned: bool | None = field(default=None, metadata=doc(
        "the model's own flag: False when its residual did not improve held-out prediction (it equals its "
        "prior); None when unknown"))
    learned_note: str | None = field(default=None, metadata=doc("what learned: false means, in words"))
    noise: dict[str, str] = field(default_factory=dict, metadata=doc(
        '{method: "identified" or "paper"}: the noise each method ran with (each model its own, identified on '
        "its training flights, or the system's fixed noise); a comparison is like with like when both sides "
        "say the same"))
    flights: list[FlightScore] = field(default_factory=list, metadata=doc("every flight, scored or excluded"))
    flights_scored: int = field(default=0, metadata=doc("flights scored"))
    median: dict[str, float] = field(default_factory=dict, metadata=doc("{method: median MSE over the scored "
                                                                        "flights, SI units squared}"))
    improvement_pct: dict[str, float] = field(default_factory=dict, metadata=doc(
        "{base method: 100 (1 - KNODE / prior) of the medians, %; positive is better}"))
    units: dict[str, Any] | None = field(default=None, metadata=doc("the units of the numbers"))
    yardstick_definitions: dict[str, str] | None = field(default=None, metadata=doc("what each yardstick measures"))
