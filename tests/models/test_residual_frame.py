"""The body-frame residual (`models.residual_frame`): one function in every backend, stored with its frame, and
with the symmetry of the physics: trained only on counter-clockwise circles, it scores the same on clockwise ones."""
from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest
import torch

from learnest.errors import InvalidInput
from learnest.estimators.algorithm1 import Algorithm1
from learnest.estimators.prepared import system_for
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.knode import HybridModel, Residual
from learnest.models.presets import CRAZYFLIE_TRAINING
from learnest.models.residual_frame import BODY_FEATURES, check_frame, features
from learnest.models.systems import make_system
from learnest.workflows.flights import train_on_flights

DRAG_TRUTH = {**cf.IDENTIFIED, "k_xy": 3 * cf.IDENTIFIED["k_xy"]}   # rotor drag the prior underestimates 3-fold


def _random_body_residual(seed: int = 0) -> Residual:
    rng = np.random.default_rng(seed)
    hidden = (rng.normal(size=(5, 6)) * 0.3, rng.normal(size=5))
    return Residual([hidden, (rng.normal(size=(3, 5)), rng.normal(size=3))], "body")


def _states_and_inputs(rows: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(rows, 9))
    q = rng.normal(size=(rows, 4))
    u = np.hstack([q / np.linalg.norm(q, axis=1, keepdims=True), rng.uniform(3e4, 5e4, (rows, 4)),
                   rng.uniform(3.5, 4.1, (rows, 1))])
    return x, u


def test_a_body_residual_is_one_function_in_numpy_torch_and_casadi():
    residual = _random_body_residual()
    x, u = _states_and_inputs(7)
    batch = residual(x, u)
    assert batch.shape == (7, 9) and np.all(batch[:, :6] == 0.0)
    np.testing.assert_allclose(residual(torch.as_tensor(x), torch.as_tensor(u)).numpy(), batch, atol=1e-12)
    xs, us = ca.SX.sym("x", 9), ca.SX.sym("u", 9)
    as_function = ca.Function("f", [xs, us], [residual(xs, us)])
    for row in range(7):
        np.testing.assert_allclose(np.asarray(as_function(x[row], u[row])).ravel(), batch[row], atol=1e-12)
    symbolic, theta, values = residual.parametric()
    with_weights = ca.Function("g", [xs, us, theta], [symbolic(xs, us)])
    np.testing.assert_allclose(np.asarray(with_weights(x[0], u[0], values)).ravel(), batch[0], atol=1e-12)


def test_the_body_features_are_height_body_velocity_mean_thrust_and_battery():
    x, u = _states_and_inputs(4)
    z = features("body", x, u)
    assert z.shape == (4, len(BODY_FEATURES))
    qx, qy, qz, qw = u[:, :4].T
    for row in range(4):
        from scipy.spatial.transform import Rotation

        R = Rotation.from_quat([qx[row], qy[row], qz[row], qw[row]]).as_matrix()
        np.testing.assert_allclose(z[row, 1:4], R.T @ x[row, 3:6], atol=1e-12)
    np.testing.assert_allclose(z[:, 0], x[:, 2])
    np.testing.assert_allclose(z[:, 4], u[:, 4:8].mean(axis=1))
    np.testing.assert_allclose(z[:, 5], u[:, 8])


def test_a_model_keeps_its_frame_through_a_file_and_an_unknown_frame_is_refused(tmp_path):
    system = make_system("crazyflie")
    model = HybridModel(system, "knode", _random_body_residual())
    model.save(tmp_path / "m.json")
    loaded = HybridModel.load(tmp_path / "m.json")
    assert loaded.residual.frame == "body"
    x, u = _states_and_inputs(3)
    np.testing.assert_array_equal(loaded.f_c(x, u), model.f_c(x, u))
    assert Residual.from_dict({"layers": []}).frame == "state"       # a file written before frames existed
    with pytest.raises(InvalidInput, match="residual frame must be one of"):
        Residual.from_dict({"layers": [], "frame": "world"})
    with pytest.raises(InvalidInput, match="needs 9 states"):
        check_frame("body", 9, 0)                                     # the kinematic quadrotor has no attitude


def _flights(seeds, turn: int):
    return [simulate_crazyflie(SimulatedFlight(truth=DRAG_TRUTH, duration_s=20.0, turn=turn), seed=s) for s in seeds]


def _one_step_gain_pct(model: HybridModel, flight) -> float:
    """How much lower (%) the model's mean squared one-step prediction error (eq. 8) is than the prior's, on the
    flight's observer states."""
    _, zeta, u, _ = Algorithm1().observe_flight(flight, "crazyflie")
    errors = []
    for candidate in (model, HybridModel(system_for(flight, "crazyflie"), "prior")):
        candidate = HybridModel(replace(candidate.system, dt=flight.dt), candidate.kind, candidate.residual)
        errors.append(np.mean(np.sum((candidate.step(zeta[:-1], u[:-1], flight.dt) - zeta[1:]) ** 2, axis=1)))
    return float(100 * (1 - errors[0] / errors[1]))


def test_trained_on_counter_clockwise_circles_the_body_residual_scores_the_same_on_clockwise_ones():
    """Five simulated flights with a 3-fold rotor drag, all circling counter-clockwise, train a pooled KNODE.  Three
    other flights are scored, each flown both ways (mirror images: same radius, speeds and climbs).  The body-frame
    residual's gain over the prior is the same both ways within 2 points; a state-frame residual that reads the
    attitude, trained the same way, loses over 20 points on the clockwise ones (it learned the turn's sense)."""
    train = _flights(range(5), turn=1)
    counter, clockwise = _flights(range(5, 8), turn=1), _flights(range(5, 8), turn=-1)
    body = train_on_flights(train, CRAZYFLIE_TRAINING, system="crazyflie").model
    assert body.residual.frame == "body"
    gains = [(_one_step_gain_pct(body, a), _one_step_gain_pct(body, b)) for a, b in zip(counter, clockwise)]
    for ccw, cw in gains:
        assert ccw > 20 and abs(ccw - cw) < 2.0, gains
    sees_attitude = train_on_flights(train, replace(CRAZYFLIE_TRAINING, residual_frame="state"), system="crazyflie",
                                     blind_attitude=False).model
    assert sees_attitude.residual.frame == "state"
    state = [(_one_step_gain_pct(sees_attitude, a), _one_step_gain_pct(sees_attitude, b))
             for a, b in zip(counter, clockwise)]
    assert all(ccw - cw > 20 for ccw, cw in state), state
