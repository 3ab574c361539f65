"""Algorithm 1 (`estimators.algorithm1.Algorithm1`) against the paper's protocol written out step by step: the class
must train the same weights, bit for bit, on a simulated record, on given states and on a sample flight, and derive a
flight's system and inputs as the diagnosis did by hand."""
from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.algorithm1 import Algorithm1
from learnest.estimators.flight_training import flight_inputs
from learnest.estimators.observers import full_state_observer, pretraining_observer
from learnest.estimators.prepared import system_for
from learnest.ingest import read_flights
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
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


def test_given_states_train_as_the_trainer_does_bit_for_bit_and_report_every_epoch():
    """`fit_states` (Table I's full-state rows, the simulated diagnosis) is the training phase alone: the trainer's
    weights, losses, kept epoch and progress on the same states, and no observer recorded, since none ran."""
    system = make_system("robot")
    record = system.simulate(10_000, 300)
    zeta = full_state_observer(system, record.x_noisy, system.dt)
    config = replace(PAPER_TRAINING["robot"], epochs=6)
    told: dict[str, list] = {"trainer": [], "ours": []}
    paper = train_knode(system, zeta, record.u, system.dt, config, progress=lambda *a: told["trainer"].append(a))
    ours = Algorithm1(config=config).fit_states(system, zeta, record.u, system.dt,
                                                progress=lambda *a: told["ours"].append(a))
    assert _same_weights(ours.model, paper.model)
    assert (ours.losses, ours.validation_losses) == (paper.losses, paper.validation_losses)
    assert told["ours"] == told["trainer"] and [epoch for epoch, _ in told["ours"]] == list(range(6))
    numbers = ("best_epoch", "best_validation_loss", "prior_validation_loss", "final_loss", "learned", "envelope")
    assert {k: ours.model.meta[k] for k in numbers} == {k: paper.model.meta[k] for k in numbers}
    assert "observer" not in ours.model.meta
    for needs_measurements in (Algorithm1("joint", config), Algorithm1(config=config, rounds=1)):
        with pytest.raises(InvalidInput, match="need the measurements"):
            needs_measurements.fit_states(system, zeta, record.u, system.dt)


def test_a_diagnosis_gets_a_flights_system_and_inputs_as_it_built_them_by_hand():
    """`flight_inputs` with the diagnosis's prior parameters and without the thrust gain is the diagnosis's old
    derivation (its parameters on the flight's grid, the inputs without the gain); the kinematic quadrotor's
    inputs have width 0 either way."""
    heavier = {**cf.IDENTIFIED, "m_kg": 1.1 * cf.IDENTIFIED["m_kg"]}   # a thrust gain training would apply
    flight = simulate_crazyflie(SimulatedFlight(truth=heavier, controller=cf.IDENTIFIED, duration_s=10), seed=0)
    params = {**cf.IDENTIFIED, "tau_s": 0.02}
    system, u, gain = flight_inputs(flight, "crazyflie", params, thrust_gain=False)
    by_hand = replace(system_for(flight, "crazyflie"), prior_params=dict(params))
    assert system == by_hand and gain is None
    assert np.array_equal(u, system_inputs(flight, by_hand))
    assert not np.array_equal(u, flight_inputs(flight, "crazyflie", params)[1])   # training's carries the gain
    quadrotor, none, gain = flight_inputs(flight, "quadrotor")
    assert quadrotor == system_for(flight) and none.shape == (len(flight.t), 0) and gain is None


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
