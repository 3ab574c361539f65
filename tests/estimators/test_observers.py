"""Pre-training observers: the unscented RTS smoother beats the filter against the simulated truth, and
training with the smoother and the observer -> train -> observer iteration runs."""
import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.algorithm1 import Algorithm1
from learnest.estimators.observers import observe_robot
from learnest.estimators.params import EstimatorParams
from learnest.estimators.smoother import run_urts
from learnest.estimators.ukf import run_ukf
from learnest.models.knode import HybridModel
from learnest.models.presets import TrainingConfig
from learnest.models.systems import make_system


@pytest.fixture(scope="module")
def cartpole_run():
    system = make_system("cartpole")
    return system, system.simulate(3, n_samples=600)          # 1.2 s


def _mse(estimate, truth):
    return np.mean((estimate - truth) ** 2, axis=0)


@pytest.mark.parametrize("kind", ["true", "prior"])
def test_urts_state_error_is_lower_than_the_filters(cartpole_run, kind):
    system, run = cartpole_run
    model = HybridModel(system, kind)
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
    filtered = run_ukf(params, run.y, run.u)
    smoothed = run_urts(params, run.y, run.u)
    f, s = _mse(filtered.means, run.x), _mse(smoothed.means, run.x)
    # every state, the unmeasured rates most: the smoother uses the measurements after each sample too
    assert np.all(s < f), (kind, s, f)
    assert s[1] < 0.5 * f[1] and s[3] < 0.5 * f[3], (kind, s, f)
    assert np.allclose(smoothed.means[-1], filtered.means[-1])  # the last estimate has no future to use
    # a smoothed covariance is never larger than the filtered one (trace), and stays positive definite
    assert np.all(np.trace(smoothed.covariances, axis1=1, axis2=2)
                  <= np.trace(filtered.covariances, axis1=1, axis2=2) + 1e-12)
    assert np.all(np.linalg.eigvalsh(smoothed.covariances) > 0)


def test_robot_observer_with_smoothed_positions_is_closer_to_the_truth():
    system = make_system("robot")
    run = system.simulate(5, n_samples=300)
    filtered = observe_robot(system, run.y, run.u, system.dt)
    smoothed = observe_robot(system, run.y, run.u, system.dt, smooth=True)
    f, s = _mse(filtered, run.x), _mse(smoothed, run.x)
    assert s[0] + s[1] < f[0] + f[1], (s, f)


def test_training_with_the_smoother_and_iteration_runs(cartpole_run):
    system, run = cartpole_run
    y, u = run.y[:200], run.u[:200]                              # it only has to run: keep it short
    config = TrainingConfig(hidden=8, epochs=5, lr=2e-2, validation_fraction=0.0)
    result = Algorithm1("smoother", config, rounds=1).fit(system, y, u, system.dt)
    observer = result.model.meta["observer"]
    assert observer["kind"] == "smoother" and observer["rounds"] == 1
    assert len(observer["misfit"]) == 2 and observer["kept_round"] == int(np.argmin(observer["misfit"]))
    assert all(np.isfinite(observer["misfit"]))
    assert result.model.kind == "knode" and "envelope" in result.model.meta
    with pytest.raises(InvalidInput, match="observer must be one of"):
        Algorithm1("oracle", config)
    with pytest.raises(InvalidInput, match="rounds"):
        Algorithm1(config=config, rounds=-1)
