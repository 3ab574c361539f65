"""An evaluation's report as its type (`learnest.records.Record`): `FlightScore` per flight, `EvaluationReport`
over them.  `workflows.flights.score_flights` builds each flight's score, `estimators.evaluate.summarize` the
report; the service stores them as their JSON (`to_dict`) and reads a stored entry back at once
(`from_dict`).  Units are in each field's doc."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from learnest.records import Record, doc

from .headline import Headline
from .yardstick_scores import FastReference, FlightYardsticks, MocapGaps, PaperSG


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
        "{\"knode-ukf_vs_ukf\": 100 (1 - KNODE / prior) of the medians, %, ...; positive is better}"))
    units: dict[str, Any] | None = field(default=None, metadata=doc("the units of the numbers"))
    yardstick_definitions: dict[str, str] | None = field(default=None, metadata=doc("what each yardstick measures"))
