"""Motor heating in the Crazyflie prior (`models.crazyflie.motor_heating`): the thermal state is the first-order step
response it claims and causal, it scales the prior's thrust exactly, it recovers the thrust of a simulated
vehicle whose motors warm, and estimation applies it only to priors that have it."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from learnest.models import crazyflie as cf
from learnest.models.crazyflie.identify import flight_arrays, predict_body_force
from learnest.models.crazyflie.motor_heating import (
    P_REF_V2,
    hover_power,
    thermal_state,
    with_motor_heating,
)
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.crazyflie.thrust_gain import with_thrust_gain
from learnest.models.inputs import (
    ATTITUDE_CALIBRATED,
    THRUST_GAIN_CALIBRATED,
    flight_thrust_gain,
    slice_keeping_heat,
    system_inputs,
    thrust_calibration,
)
from learnest.models.knode import HybridModel, Residual
from learnest.models.systems import make_system
from learnest.service.cli import format_report
from learnest.workflows.flights import evaluate_flights

# a fast-warming vehicle (6 % of thrust lost in 30 s) without motor lag: the static map is the whole truth
WARM = {**cf.IDENTIFIED, "m_kg": 0.016, "tau_s": 0.0, "tau_th_s": 20.0, "kappa_th": 0.08}
COLD = {**WARM, "kappa_th": 0.0}


def _hover_inputs(n: int, volts: float = 3.7) -> np.ndarray:
    pwm = cf.hover_pwm(cf.IDENTIFIED)   # the reference hover: P = 1
    return np.column_stack([np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)), np.full((n, 4), pwm), np.full(n, volts)])


def test_the_thermal_state_is_the_first_order_step_response_and_causal():
    dt, tau = 0.01, 20.0
    u = _hover_inputs(3000)
    h = thermal_state(u, dt, tau)
    k = np.arange(3000)
    # the reference vehicle hovering at V_ref is P = 1 by construction: h is 1 − exp(−t/τ), sampled exactly
    np.testing.assert_allclose(h, 1.0 - np.exp(-k * dt / tau), rtol=0, atol=1e-12)
    later = u.copy()
    later[1500:, 4:8] = 0.0                       # motors off from sample 1500: nothing before it changes
    np.testing.assert_array_equal(thermal_state(later, dt, tau)[:1501], h[:1501])
    # the scale kappa_th was identified with: refitting the thrust map must not move it silently
    assert P_REF_V2 == pytest.approx(hover_power(cf.IDENTIFIED), rel=1e-5)
    # a heavier vehicle works its motors harder and warms more: P_REF is a fixed electrical scale
    assert hover_power({**cf.IDENTIFIED, "m_kg": 0.023}) > 1.2 * P_REF_V2


def test_the_heating_scales_the_prior_thrust_by_one_minus_kappa_h_exactly():
    dt = 0.01
    rng = np.random.default_rng(0)
    u = _hover_inputs(2000)
    u[:, 4:8] *= rng.uniform(0.9, 1.1, (2000, 4))
    u[:, 8] = np.linspace(4.1, 3.4, 2000)
    thrust = lambda inputs: sum(cf.motor_thrust(inputs[:, 4 + i], inputs[:, 8], WARM) for i in range(4))
    heated, loss_pct = with_motor_heating(u, dt, WARM)
    factor = 1.0 - WARM["kappa_th"] * thermal_state(u, dt, WARM["tau_th_s"])
    np.testing.assert_allclose(thrust(heated), factor * thrust(u), rtol=1e-12)
    np.testing.assert_array_equal(heated[:, :8], u[:, :8])
    assert loss_pct == pytest.approx(100 * (1 - factor.min()))
    assert 0 < loss_pct < 100 * WARM["kappa_th"] * 1.5
    for cannot in ({**WARM, "gamma": 0.0}, COLD, {k: v for k, v in WARM.items() if k != "kappa_th"}):
        unchanged, none = with_motor_heating(u, dt, cannot)   # a voltage-free map, or a prior without heating
        np.testing.assert_array_equal(unchanged, u)
        assert none == 0.0


def _warm_flight(seed: int):
    settings = SimulatedFlight(truth=WARM, controller=WARM, duration_s=30, hover_height_m=0.3, accel_noise=0.0)
    return simulate_crazyflie(settings, seed=seed)


@pytest.mark.parametrize("seed", [1, 2])
def test_a_vehicle_whose_motors_warm_is_predicted_from_its_inputs(seed):
    """Simulated truth: the motors lose thrust as they warm.  With the heating the prior's body-z specific
    force matches the true one (noise-free accelerometer) and its thrust gain is 1; without it the gain takes
    the mean loss and the drift stays."""
    flight = _warm_flight(seed)
    errors = {}
    for label, params in (("with", WARM), ("without", COLD)):
        system = replace(make_system("crazyflie"), dt=flight.dt, prior_params=dict(params))
        u = system_inputs(flight, system)
        gain = flight_thrust_gain(flight, system, u)
        u = system_inputs(flight, system, thrust_gain=True)
        predicted = np.asarray(cf.specific_force_body(list(np.gradient(flight.p, flight.dt, axis=0).T), flight.p[:, 2],
                                                      list(u.T), params)[0][2], dtype=float)
        airborne = flight.p[:, 2] > 0.2
        errors[label] = (np.sqrt(np.mean((predicted - flight.channels["acc_body"][:, 2])[airborne] ** 2)), gain)
    assert errors["with"][1] == pytest.approx(1.0, abs=2e-3)            # nothing left for the gain to take
    assert errors["without"][1] < 0.98                                   # the gain absorbs the mean loss ...
    assert errors["with"][0] < 0.25 * errors["without"][0], errors       # ... but not the drift


def _zero_knode(system, meta):
    net = Residual([(np.zeros((4, system.n + system.n_inputs)), np.zeros(4)), (np.zeros((9, 4)), np.zeros(9))])
    return HybridModel(system, "knode", net, meta)


def test_estimation_heats_the_motors_of_priors_that_have_it_and_reports_the_loss():
    """A model keeps its own prior: one trained before the heating (no kappa_th in its stored parameters) is
    evaluated without it, and the simulated warm vehicle is estimated better by the prior that knows it."""
    flight = _warm_flight(3)
    reports = {}
    before_heating = {k: v for k, v in COLD.items() if k not in ("kappa_th", "tau_th_s")}
    for label, params in (("warm", WARM), ("before", before_heating)):
        system = replace(make_system("crazyflie"), dt=flight.dt, prior_params=dict(params))
        reports[label] = evaluate_flights(_zero_knode(system, {"attitude_input": THRUST_GAIN_CALIBRATED}), [flight],
                                          ["ukf"])
    entry, before = reports["warm"]["flights"][0], reports["before"]["flights"][0]
    # 30 s of flight cost the warm motors about 1 − exp(−30/20) of their 8 %
    assert 4.0 < entry["heating_thrust_loss_pct"] < 8.0
    assert entry["thrust_gain"] == pytest.approx(1.0, abs=3e-3)
    assert "heating_thrust_loss_pct" not in before and before["thrust_gain"] < 0.98 and not before["warnings"]
    assert entry["mse"]["ukf"] < before["mse"]["ukf"], (entry["mse"], before["mse"])
    assert f"{flight.name} {entry['heating_thrust_loss_pct']:.1f}" in format_report(reports["warm"])


def test_estimation_inputs_are_the_heating_then_the_gain_and_reports_say_what_was_applied():
    flight = _warm_flight(4)
    system = replace(make_system("crazyflie"), dt=flight.dt, prior_params=dict(WARM))
    raw = system_inputs(flight, system, motor_heating=False)
    heated, loss = with_motor_heating(raw, flight.dt, WARM)
    gain = flight_thrust_gain(flight, system, heated)
    np.testing.assert_array_equal(system_inputs(flight, system), heated)
    np.testing.assert_array_equal(system_inputs(flight, system, thrust_gain=True),
                                  with_thrust_gain(heated, gain, WARM["gamma"]))
    assert thrust_calibration(flight, system) == {"heating_thrust_loss_pct": loss, "thrust_gain": gain}
    assert thrust_calibration(flight, system, thrust_gain=False) == {"heating_thrust_loss_pct": loss}
    # a voltage exponent that cannot carry a factor: nothing applied, and the report says gain 1, no loss
    flat = replace(system, prior_params={**WARM, "gamma": 0.05})
    np.testing.assert_array_equal(system_inputs(flight, flat, thrust_gain=True), raw)
    assert thrust_calibration(flight, flat) == {"heating_thrust_loss_pct": 0.0, "thrust_gain": 1.0}
    # a model scored without the gain (a diagnosis's repaired one) still reports the heating its prior applied
    report = evaluate_flights(_zero_knode(system, {"attitude_input": ATTITUDE_CALIBRATED}), [flight], ["ukf"])
    entry = report["flights"][0]
    assert entry["heating_thrust_loss_pct"] == pytest.approx(loss, abs=1e-5) and "thrust_gain" not in entry


def test_a_slice_of_a_flight_starts_as_warm_as_the_flight_was_there():
    """The diagnosis scores the last 40 % of a single flight: sliced with its history the motors are as warm as
    in the whole flight at that sample, so the slice's heated inputs and predicted specific force are the whole
    flight's; sliced plainly they restart cold and the prior over-predicts the thrust."""
    flight = _warm_flight(5)
    system = replace(make_system("crazyflie"), dt=flight.dt, prior_params=dict(WARM))
    cut = int(0.6 * len(flight.t))
    # the motors and the heated voltage (the attitude's thrust-axis calibration is per record)
    whole = system_inputs(flight, system)[cut:, 4:]
    warm, cold = slice_keeping_heat(flight, cut, len(flight.t)), flight.slice(cut, len(flight.t))
    np.testing.assert_allclose(system_inputs(warm, system)[:, 4:], whole, rtol=1e-12)
    assert np.all(system_inputs(cold, system)[1:, 8] > whole[1:, 4])    # cold motors: more thrust per volt
    # and the diagnosis's prediction of the body-z specific force from the inputs (before its low-pass)
    full = thermal_state(flight_arrays(flight).u, flight.dt, WARM["tau_th_s"])[cut:]
    arrays = flight_arrays(warm)
    np.testing.assert_allclose(thermal_state(arrays.u, flight.dt, WARM["tau_th_s"], arrays.extra["motor_power_before"]),
                               full, rtol=1e-12)
    middle = slice(200, -200)   # away from the low-pass's edges
    assert np.max(np.abs(predict_body_force(arrays, WARM)[middle, 2]
                         - predict_body_force(flight_arrays(cold), WARM)[middle, 2])) > 0.05
    # a slice of a slice carries the whole history
    second = slice_keeping_heat(warm, 100, len(warm.t))
    np.testing.assert_allclose(system_inputs(second, system)[:, 4:], whole[100:], rtol=1e-12)
