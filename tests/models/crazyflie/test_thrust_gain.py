"""The per-flight thrust gain of the Crazyflie prior (`models.crazyflie.thrust_gain`): it recovers a payload the prior
does not know from the mocap and the inputs alone, it scales the prior's thrust exactly, estimation uses it
and reports it, and a model keeps being fed the inputs it was trained on."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.crazyflie.thrust_gain import thrust_gain, with_thrust_gain
from learnest.models.inputs import (
    ATTITUDE_CALIBRATED,
    THRUST_GAIN_CALIBRATED,
    flight_thrust_gain,
    system_inputs,
)
from learnest.models.knode import HybridModel, Residual
from learnest.models.systems import make_system
from learnest.service.cli import format_report
from learnest.workflows.flights import evaluate_flights

# a lighter vehicle than NanoBench's (hover PWM 56000 of 65535 at 3.4 V), so the loaded one can still climb
PRIOR = {**cf.IDENTIFIED, "m_kg": 0.016}


def _flight(mass_factor: float, seed: int = 1):
    truth = {**PRIOR, "m_kg": PRIOR["m_kg"] * mass_factor}
    return simulate_crazyflie(SimulatedFlight(truth=truth, controller=PRIOR, duration_s=12, hover_height_m=0.3),
                              seed=seed)


def _system(flight):
    return replace(make_system("crazyflie"), dt=flight.dt, prior_params=dict(PRIOR))


@pytest.mark.parametrize("mass_factor", [1.0, 1.2])
def test_the_gain_is_the_prior_mass_over_the_flown_mass(mass_factor):
    flight = _flight(mass_factor)
    system = _system(flight)
    # thrust per PWM and volt is the prior's; a payload divides the specific force by the mass ratio
    assert flight_thrust_gain(flight, system, system_inputs(flight, system)) == pytest.approx(1.0 / mass_factor,
                                                                                            rel=0.01)


def test_the_scaled_voltage_scales_the_prior_thrust_exactly():
    rng = np.random.default_rng(0)
    u = np.column_stack([np.tile([0.0, 0.0, 0.0, 1.0], (50, 1)), rng.uniform(30000, 60000, (50, 4)),
                         rng.uniform(3.3, 4.1, 50)])
    thrust = lambda inputs: sum(cf.motor_thrust(inputs[:, 4 + i], inputs[:, 8], PRIOR) for i in range(4))
    scaled = with_thrust_gain(u, 0.9, PRIOR["gamma"])
    np.testing.assert_allclose(thrust(scaled), 0.9 * thrust(u), rtol=1e-12)
    np.testing.assert_array_equal(scaled[:, :8], u[:, :8])
    np.testing.assert_array_equal(with_thrust_gain(u, 0.9, 0.0), u)    # a voltage-free map cannot carry it


def test_a_record_that_never_flies_keeps_gain_one_and_nonsense_inputs_are_refused():
    flight = _flight(1.0)
    system = _system(flight)
    u = system_inputs(flight, system)
    grounded = np.column_stack([flight.p[:, :2], np.zeros(len(flight.p))])
    assert thrust_gain(grounded, u, flight.dt, PRIOR) == 1.0
    millivolts = u.copy()
    millivolts[:, 8] *= 1000.0            # a voltage logged in mV and read as V
    with pytest.raises(ValueError, match="times the thrust"):
        thrust_gain(flight.p, millivolts, flight.dt, PRIOR)


def _zero_knode(system, meta):
    net = Residual([(np.zeros((4, system.n + system.n_inputs)), np.zeros(4)), (np.zeros((9, 4)), np.zeros(9))])
    return HybridModel(system, "knode", net, meta)


def test_estimation_on_a_payload_flight_uses_the_gain_and_reports_it():
    flight = _flight(1.2, seed=2)
    system = _system(flight)
    calibrated = evaluate_flights(_zero_knode(system, {"attitude_input": THRUST_GAIN_CALIBRATED}), [flight], ["ukf"])
    before = evaluate_flights(_zero_knode(system, {"attitude_input": ATTITUDE_CALIBRATED}), [flight], ["ukf"])
    entry, old = calibrated["flights"][0], before["flights"][0]
    assert entry["thrust_gain"] == pytest.approx(1 / 1.2, rel=0.01)
    # the prior that knows the flight's thrust gain estimates the state better (simulated truth: the payload)
    assert entry["mse"]["ukf"] < 0.8 * old["mse"]["ukf"], (entry["mse"], old["mse"])
    # a model trained before the gain is fed its own inputs: no gain, and no warning to retrain
    assert "thrust_gain" not in old and not old["warnings"]
    assert f"{flight.name} {entry['thrust_gain']:.3f}" in format_report(calibrated)
