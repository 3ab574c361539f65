"""The Crazyflie prior driven by its motors and battery: one definition in three backends, its physics
against hand-computed published numbers, its inputs from real NanoBench logs, and its use by training,
the UKF and the MHE on simulated flights whose truth is known."""
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from learnest.estimators.mhe import MHE
from learnest.estimators.observers import pretraining_observer
from learnest.estimators.params import EstimatorParams
from learnest.estimators.ukf import run_ukf
from learnest.ingest import units
from learnest.ingest.flight import Flight
from learnest.models import crazyflie as cf
from learnest.models.inputs import MissingInputs, system_inputs
from learnest.models.knode import HybridModel
from learnest.models.systems import make_system
from learnest.models.training import TrainingConfig, train_knode

DATA = Path(__file__).resolve().parents[4] / "shared" / "data"
NANOBENCH = DATA / "nanobench"
needs_data = pytest.mark.skipif(not NANOBENCH.is_dir(), reason="../shared/data/nanobench not present")


def random_inputs(rng, n):
    quat = np.column_stack([rng.normal(0, 0.1, (n, 3)), np.ones(n)])
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    return np.column_stack([quat, rng.uniform(30000, 65000, (n, 4)), rng.uniform(3.0, 4.1, n)])


def test_three_backends_agree_for_prior_and_knode():
    rng = np.random.default_rng(1)
    system = make_system("crazyflie")
    x = rng.normal(size=(6, 9))
    x[:, 2] = rng.uniform(0.02, 2.0, 6)          # heights on both sides of the ground-effect clamp
    u = random_inputs(rng, 6)
    layers = [(rng.normal(size=(8, 18)) * 1e-5, rng.normal(size=8)), (rng.normal(size=(9, 8)), rng.normal(size=9))]
    from learnest.models.knode import Residual
    for model in (HybridModel(system, "prior"), HybridModel(system, "knode", Residual(layers))):
        f_np = model.step(x, u, 0.01)
        import torch  # not at module level: collection must not import torch

        f_torch = model.step(torch.as_tensor(x), torch.as_tensor(u), 0.01).numpy()
        X, U = ca.SX.sym("x", 9), ca.SX.sym("u", 9)
        step = ca.Function("f", [X, U], [model.step(X, U, 0.01)])
        f_ca = np.array([np.asarray(step(x[i], u[i])).ravel() for i in range(len(x))])
        assert np.max(np.abs(f_np - f_torch)) < 1e-9
        assert np.max(np.abs(f_np - f_ca)) < 1e-9


@pytest.mark.parametrize("params", [cf.PUBLIC, cf.IDENTIFIED], ids=["public", "identified"])
@pytest.mark.parametrize("vbat", [3.3, 3.7, 4.1])
def test_hover_at_the_nominal_hover_pwm_gives_zero_acceleration(params, vbat):
    system = make_system("crazyflie", prior_params=dict(params))
    pwm = cf.hover_pwm(params, vbat=vbat)
    x = np.array([0.3, -0.2, 50.0, 0, 0, 0, 0, 0, 0])   # far from the floor (ground effect 1 + 1e-8)
    u = np.array([0, 0, 0, 1.0, pwm, pwm, pwm, pwm, vbat])
    assert np.max(np.abs(system.f_prior(x, u))) < 1e-4
    # 5 % more PWM climbs, and an empty battery at the same PWM sinks (gamma > 0)
    assert system.f_prior(x, u * np.r_[1, 1, 1, 1, 1.05, 1.05, 1.05, 1.05, 1])[8] > 0
    assert system.f_prior(x, u * np.r_[np.ones(8), 0.9])[8] < 0


def test_thrust_map_reproduces_foerster_and_its_derived_numbers():
    # Förster's polynomial at PWM 0, 32768, 65535, by hand: a0; a2*32768² + a1*32768 + a0; ...
    for pwm, newton in ((0.0, 5.484560e-4), (32768.0, 0.0572596), (65535.0, 0.1597146)):
        assert cf.motor_thrust(pwm, cf.V_REF, cf.PUBLIC) == pytest.approx(newton, rel=1e-4)
    # 27 g hovers at PWM ≈ 36335 on it (solved by hand: 4 T(p) = 0.027 * 9.80665)
    assert cf.hover_pwm(cf.PUBLIC) == pytest.approx(36335, abs=2)
    # rotor drag: K (kg/rad) x 4 rotors x ω(hover) / m, ω = 0.04076521 p + 380.8359 = 1862.0 rad/s
    assert cf.PUBLIC["k_xy"] == pytest.approx(9.1785e-7 * 4 * 1862.03 / 0.027, rel=1e-4)
    assert cf.PUBLIC["k_z"] == pytest.approx(10.311e-7 * 4 * 1862.03 / 0.027, rel=1e-4)
    # the battery factor: half the voltage ratio to the power gamma
    half = dict(cf.PUBLIC, gamma=2.0)
    assert cf.motor_thrust(40000.0, cf.V_REF / 2, half) == pytest.approx(cf.motor_thrust(40000.0, cf.V_REF, half) / 4)


def test_ground_effect_follows_cheeseman_bennett_and_stays_finite_on_the_floor():
    r = 0.0225
    assert cf.ground_effect(np.array(0.1), r) == pytest.approx(1 / (1 - (r / 0.4) ** 2), rel=1e-4)
    assert cf.ground_effect(np.array(1.0), r) == pytest.approx(1.0, abs=1e-3)
    assert 1.0 < cf.ground_effect(np.array(0.0), r) < 1.02


def test_unit_converters():
    assert units.millivolts(np.array([3712.0]))[0] == pytest.approx(3.712)
    assert units.rpm(np.array([60.0]))[0] == pytest.approx(2 * np.pi)
    assert units.millimetres(np.array([1500]))[0] == pytest.approx(1.5)
    converted = units.pwm_16bit(np.array([0, 40000, 65535, 70000, -3]))
    assert converted[:3].tolist() == [0, 40000, 65535] and np.isnan(converted[3:]).all()


def _flight_without_inputs(n=50):
    t = np.arange(n) * 0.01
    return Flight(t, np.zeros((n, 3)), np.zeros((n, 3)), np.tile([0, 0, 0, 1.0], (n, 1)), {}, {"name": "bare"})


def test_a_flight_without_motor_inputs_names_them_and_the_kinematic_prior_still_works():
    flight = _flight_without_inputs()
    with pytest.raises(MissingInputs, match=r"motor PWM.*battery voltage.*'quadrotor'\) works"):
        system_inputs(flight, make_system("crazyflie"))
    assert system_inputs(flight, make_system("quadrotor")).shape == (50, 0)


@needs_data
def test_inputs_read_from_nanobench_in_their_units():
    from learnest.ingest import read_flights
    flight = read_flights([NANOBENCH / "B2_circle_medium_rep2.csv"])[0]
    u = system_inputs(flight, make_system("crazyflie"))
    assert u.shape == (len(flight.t), 9)
    np.testing.assert_allclose(np.linalg.norm(u[:, :4], axis=1), 1.0, atol=1e-9)
    pwm, vbat = u[:, 4:8], u[:, 8]
    assert 0 <= pwm.min() and pwm.max() <= 65535 and 40000 < np.median(pwm) < 65535   # counts, flying
    assert 2.8 < vbat.min() and vbat.max() < 4.3                                       # volts, not mV
    cmd = flight.channels["thrust_cmd"][:, 0]
    # the logged PWM is the firmware's battery compensation of the thrust command: duty = volts(cmd)/vbat
    thrust_g = cmd / 65536 * 60
    duty = (-0.0006239 * thrust_g**2 + 0.088 * thrust_g) / vbat
    assert np.median(np.abs(duty - pwm.mean(1) / 65535)) < 0.03


def test_ukf_and_mhe_with_the_crazyflie_prior_track_a_simulated_flight_better_than_the_kinematic_prior():
    truth = make_system("crazyflie", n_samples=400)
    run = truth.simulate(3)
    kinematic = make_system("quadrotor")
    x0 = run.x[0] + np.r_[0.01, -0.01, 0.01, 0.05, -0.05, 0.05, 0.2, -0.2, 0.2]
    errors = {}
    for label, model, u in (("crazyflie", HybridModel(truth, "prior"), run.u),
                            ("quadrotor", HybridModel(kinematic, "prior"), np.zeros((len(run.t), 0)))):
        est = run_ukf(EstimatorParams(model, truth.dt, truth.Q, truth.R, truth.P0, x0), run.y, u).means
        errors[label] = np.mean((est[:, 3:] - run.x[:, 3:]) ** 2)
    # same Q, R, P0 for both (the kinematic defaults): the gain comes from the model alone
    assert errors["crazyflie"] < 0.7 * errors["quadrotor"]
    mhe = MHE(EstimatorParams(HybridModel(truth, "prior"), truth.dt, truth.Q, truth.R, truth.P0, x0), horizon=8)
    est = mhe.run(run.y[:80], run.u[:80]).means
    assert np.mean((est[20:, 3:6] - run.x[20:80, 3:6]) ** 2) < 1e-3


def test_knode_on_the_crazyflie_prior_learns_a_payload_it_was_not_told_about():
    """Truth: 20 % heavier than the prior believes.  The residual takes (x, u) and must close part of the
    gap in one-step prediction on a separate simulated flight."""
    prior = make_system("crazyflie", n_samples=500)
    truth = prior.with_true_params(m_kg=prior.prior_params["m_kg"] * 1.2)
    train, test = truth.simulate(10), truth.simulate(11)
    zeta = pretraining_observer(truth, train.y, train.u, truth.dt)
    model = train_knode(truth, zeta, train.u, truth.dt, TrainingConfig(hidden=16, epochs=150, lr=1e-2)).model
    prior_model = HybridModel(truth, "prior")

    def one_step_error(m):
        pred = m.step(test.x[:-1], test.u[:-1], truth.dt)
        return np.mean((pred[:, 6:] - test.x[1:, 6:]) ** 2)

    assert one_step_error(model) < 0.5 * one_step_error(prior_model)


def test_the_crazyflie_residual_corrects_only_the_acceleration_rows_and_ignores_where_the_vehicle_is():
    """ṗ = v and v̇ = a are definitions and px, py are not physics: a trained residual leaves the first
    six derivatives exactly alone and gives the same correction anywhere in the room and whatever the
    acceleration state (the observer's filtered accelerometer, whose evolution is the trajectory's jerk).  The paper's
    kinematic prior keeps its full residual."""
    system = make_system("crazyflie", n_samples=200)
    run = system.with_true_params(m_kg=system.prior_params["m_kg"] * 1.2).simulate(4)
    model = train_knode(system, run.x, run.u, system.dt, TrainingConfig(hidden=8, epochs=5, lr=1e-2)).model
    rng = np.random.default_rng(0)
    x, u = rng.normal(size=(7, 9)), random_inputs(rng, 7)
    delta = model.residual(x, u)
    assert np.all(delta[:, :6] == 0.0) and np.all(np.abs(delta[:, 6:]) > 0)
    moved = x.copy()
    moved[:, :2] += rng.normal(0, 5, (7, 2))
    assert np.array_equal(model.residual(moved, u), delta)
    moved[:, 6:9] += rng.normal(0, 3, (7, 3))  # the acceleration state is the observer's filtered accelerometer
    assert np.array_equal(model.residual(moved, u), delta)
    moved[:, 2] += 0.3       # the height is physics (ground effect): it is seen
    assert not np.array_equal(model.residual(moved, u), delta)
    faster = moved.copy()
    faster[:, 3:6] += 0.5    # so is the velocity (rotor drag)
    assert not np.array_equal(model.residual(faster, u), model.residual(moved, u))
    inputs, outputs = make_system("quadrotor").residual_masks()
    assert inputs.all() and outputs.all()


def test_the_two_lags_split_the_relaxation_along_and_across_the_thrust_axis():
    """ȧ = b₃b₃ᵀ(a_cmd − a)/tau_s + (I − b₃b₃ᵀ)(a_cmd − a)/tau_att_s, checked component by component against
    a_cmd computed on its own; equal lags, or no tau_att_s (a stored model's prior), are one relaxation of the
    whole acceleration; torch and CasADi give the same field."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(5, 9))
    x[:, 2] = rng.uniform(0.5, 2.0, 5)
    u = random_inputs(rng, 5)
    two = make_system("crazyflie", prior_params={**cf.IDENTIFIED, "tau_s": 0.03, "tau_att_s": 0.08})
    for xi, ui in zip(x, u):
        gap = np.array(cf.world_acceleration(list(xi[3:6]), xi[2], list(ui), two.prior_params)) - xi[6:9]
        R = np.array(cf.rotation_columns(*ui[:4]))
        b3 = R[:, 2]
        rate = two.f_prior(xi, ui)[6:9]
        assert b3 @ rate == pytest.approx(b3 @ gap / 0.03, rel=1e-9, abs=1e-9)
        across = np.eye(3) - np.outer(b3, b3)
        np.testing.assert_allclose(across @ rate, across @ gap / 0.08, rtol=1e-9, atol=1e-9)
        one = [make_system("crazyflie", prior_params=params).f_prior(xi, ui)[6:9]
               for params in ({**cf.IDENTIFIED, "tau_s": 0.03, "tau_att_s": 0.03},
                              {k: v for k, v in {**cf.IDENTIFIED, "tau_s": 0.03}.items() if k != "tau_att_s"})]
        for field in one:
            np.testing.assert_allclose(field, gap / 0.03, rtol=1e-12, atol=1e-12)
    import torch  # not at module level: collection must not import torch

    model = HybridModel(two, "prior")
    X, U = ca.SX.sym("x", 9), ca.SX.sym("u", 9)
    step = ca.Function("f", [X, U], [model.step(X, U, 0.01)])
    f_np = model.step(x, u, 0.01)
    assert np.max(np.abs(f_np - model.step(torch.as_tensor(x), torch.as_tensor(u), 0.01).numpy())) < 1e-9
    assert np.max(np.abs(f_np - np.array([np.asarray(step(x[i], u[i])).ravel() for i in range(5)]))) < 1e-9
