"""Algorithm 1 (`estimators.algorithm1.Algorithm1`) against the paper's protocol written out step by step: the class
must train the same weights, bit for bit, on a simulated record and on a sample flight."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.algorithm1 import Algorithm1
from learnest.estimators.observers import pretraining_observer
from learnest.estimators.prepared import system_for
from learnest.ingest import read_flights
from learnest.models.inputs import system_inputs
from learnest.models.presets import CRAZYFLIE_TRAINING, PAPER_TRAINING
from learnest.models.systems import make_system
from learnest.models.training import train_knode

SAMPLES = Path(__file__).resolve().parents[2] / "sample_logs"


def _same_weights(a, b) -> bool:
    return all(np.array_equal(wa, wb) and np.array_equal(ba, bb)
               for (wa, ba), (wb, bb) in zip(a.residual.layers, b.residual.layers))


def test_one_record_with_the_filter_observer_is_the_papers_protocol_bit_for_bit():
    system = make_system("cartpole")
    record = system.simulate(10_000, 300)
    config = replace(PAPER_TRAINING["cartpole"], epochs=8)
    paper = train_knode(system, pretraining_observer(system, record.y, record.u, system.dt), record.u, system.dt,
                        config)
    ours = Algorithm1("filter", config).fit(system, record.y, record.u, system.dt)
    assert _same_weights(ours.model, paper.model) and ours.losses == paper.losses
    assert ours.model.meta["observer"] == {"kind": "filter", "rounds": 0, "kept_round": 0, "misfit": []}
    # the observer as an object: the same observer, the same weights; its name is recorded
    custom = Algorithm1(pretraining_observer, config).fit(system, record.y, record.u, system.dt)
    assert _same_weights(custom.model, paper.model) and custom.model.meta["observer"]["kind"] == "pretraining_observer"


def test_one_flight_is_the_papers_protocol_bit_for_bit_and_records_its_lineage():
    flight = read_flights([SAMPLES / "circle_rep1.csv"])[0]
    config = replace(CRAZYFLIE_TRAINING, epochs=4)
    prior = system_for(flight)
    u = system_inputs(flight, prior, thrust_gain=True)
    paper = train_knode(prior, pretraining_observer(prior, flight.measurements(), u, prior.dt), u, prior.dt, config)
    ours = Algorithm1(config=config).fit_flights([flight])
    assert _same_weights(ours.model, paper.model) and ours.validation_losses == paper.validation_losses
    meta = ours.model.meta
    assert meta["validation"] == "held-out time blocks of the flight" and meta["validation_flights"] == []
    assert [f["name"] for f in meta["training_flights"]] == [flight.name] == [meta["training_flight"]]


def test_choices_algorithm_1_cannot_run_are_refused_before_any_training():
    with pytest.raises(InvalidInput, match="observer must be one of"):
        Algorithm1("oracle")
    with pytest.raises(InvalidInput, match="observer must be one of"):
        Algorithm1(42)   # type: ignore[arg-type]
    with pytest.raises(InvalidInput, match="rounds must be at least 0"):
        Algorithm1(rounds=-1)
    flights = read_flights([SAMPLES / "circle_rep1.csv", SAMPLES / "circle_rep2.csv"])
    with pytest.raises(InvalidInput, match="one record"):
        Algorithm1("joint").fit_flights(flights)
    with pytest.raises(InvalidInput, match="one record"):
        Algorithm1(rounds=1).fit_flights(flights)
