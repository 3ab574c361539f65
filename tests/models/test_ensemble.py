"""An ensemble of residuals (`models.ensemble`): its mean is one ordinary network, it is stored with its members, and
on a flight unlike its training flights the members' spread widens the KNODE filter's covariance."""
from __future__ import annotations

from dataclasses import replace

import casadi as ca
import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.prepared import prepare
from learnest.estimators.ukf import run_ukf
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.ensemble import mean_residual, spread_variance
from learnest.models.knode import HybridModel, Residual
from learnest.models.presets import CRAZYFLIE_TRAINING
from learnest.models.residual_scale import scaled_residual
from learnest.models.systems import make_system
from learnest.workflows.flights import train_on_flights


def _member(seed: int) -> Residual:
    rng = np.random.default_rng(seed)
    hidden = (rng.normal(size=(4, 6)) * 0.3, rng.normal(size=4))
    return Residual([hidden, (rng.normal(size=(3, 4)), rng.normal(size=3))], "body")


def _inputs(rows: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(9)
    q = rng.normal(size=(rows, 4))
    u = np.hstack([q / np.linalg.norm(q, axis=1, keepdims=True), rng.uniform(3e4, 5e4, (rows, 4)),
                   rng.uniform(3.5, 4.1, (rows, 1))])
    return rng.normal(size=(rows, 9)), u


def test_the_mean_network_is_exactly_the_members_mean_in_numpy_and_casadi_and_survives_a_file():
    members = [_member(s) for s in range(5)]
    mean = mean_residual(members)
    x, u = _inputs(6)
    expected = np.mean([m(x, u) for m in members], axis=0)
    np.testing.assert_allclose(mean(x, u), expected, atol=1e-12)
    xs, us = ca.SX.sym("x", 9), ca.SX.sym("u", 9)
    symbolic = ca.Function("f", [xs, us], [mean(xs, us)])
    np.testing.assert_allclose(np.asarray(symbolic(x[0], u[0])).ravel(), expected[0], atol=1e-12)
    again = Residual.from_dict(mean.to_dict())
    assert len(again.members) == 5 and again.frame == "body"
    np.testing.assert_allclose(spread_variance(again, x, u, 0.01),
                               1e-4 * np.mean(np.var([m(x, u) for m in members], axis=0), axis=0), atol=1e-15)
    half = scaled_residual(mean, 0.5)
    np.testing.assert_allclose(spread_variance(half, x, u, 0.01), 0.25 * spread_variance(mean, x, u, 0.01), rtol=1e-9)
    with pytest.raises(InvalidInput, match="at least 2"):
        mean_residual(members[:1])
    with pytest.raises(InvalidInput, match="share a frame"):
        mean_residual([members[0], replace(members[1], frame="state")])


DRAG_TRUTH = {**cf.IDENTIFIED, "k_xy": 3 * cf.IDENTIFIED["k_xy"]}   # rotor drag the prior underestimates 3-fold


def _flights(speeds: tuple, seeds) -> list:
    return [simulate_crazyflie(SimulatedFlight(truth=DRAG_TRUTH, duration_s=16.0, speeds=speeds), seed=s)
            for s in seeds]


def test_on_a_flight_unlike_its_training_flights_the_spread_widens_the_knode_covariance():
    """Five members trained on slow circles (0.3-0.5 m/s) of a vehicle with 3-fold rotor drag.  On a fast flight
    (1.8-2.2 m/s, body velocities none of them saw) they disagree more than on a slow one, so the KNODE's process
    noise grows there, and its UKF's acceleration covariance is wider than the same mean network's without its
    members (by 7 % here: against the system's fixed acceleration noise the spread is small)."""
    training = _flights((0.3, 0.4, 0.5), range(4))
    slow, fast = _flights((0.3, 0.4, 0.5), [10])[0], _flights((1.8, 2.0, 2.2), [11])[0]
    result = train_on_flights(training, replace(CRAZYFLIE_TRAINING, ensemble=5), system="crazyflie", group_by="none")
    model = result.model
    assert len(model.residual.members) == 5 and model.meta["ensemble"]["members"] == 5
    on_slow, on_fast = prepare(model, slow), prepare(model, fast)
    a_rows = slice(6, 9)
    q_slow, q_fast = np.diag(on_slow.model.system.Q)[a_rows], np.diag(on_fast.model.system.Q)[a_rows]
    assert np.all(q_fast > q_slow), (q_slow, q_fast)
    assert on_fast.prior.system.Q[6, 6] == pytest.approx(make_system("crazyflie").Q[6, 6])   # the prior has no doubt
    bare = HybridModel(model.system, "knode", replace(model.residual, members=None), model.meta)
    widths = []
    for candidate in (model, bare):
        prepared = prepare(candidate, fast)
        run = run_ukf(prepared.params, prepared.y, prepared.u)
        widths.append(float(np.median(run.covariances[:, 6, 6] + run.covariances[:, 7, 7] + run.covariances[:, 8, 8])))
    assert widths[0] > 1.03 * widths[1], widths
