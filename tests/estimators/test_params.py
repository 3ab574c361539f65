"""One bundle per estimator run (`EstimatorParams`) and the result type each estimator returns."""
from pathlib import Path

import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.covariance import linearized_covariances
from learnest.estimators.kf import run_kf
from learnest.estimators.mhe import MHE
from learnest.estimators.params import EstimatorParams
from learnest.estimators.prepared import prepare
from learnest.estimators.results import FilterResult, MHEResult, SmootherResult
from learnest.estimators.smoother import run_urts
from learnest.estimators.ukf import run_ukf
from learnest.ingest import read_flights
from learnest.models.knode import HybridModel
from learnest.models.noise import NoiseModel
from learnest.models.systems import make_system

SAMPLES = Path(__file__).resolve().parents[2] / "sample_logs"


@pytest.fixture(scope="module")
def linear_case():
    system = make_system("quadrotor")
    run = system.simulate(4, n_samples=40)
    return EstimatorParams(HybridModel(system, "prior"), system.dt, system.Q, system.R, system.P0, run.x_noisy[0]), run


def test_each_estimator_returns_its_own_result_type(linear_case):
    params, run = linear_case
    assert isinstance(run_ukf(params, run.y), FilterResult)
    assert isinstance(run_kf(params, run.y), FilterResult)
    assert isinstance(run_kf(params, run.y, smooth=True), SmootherResult)
    smoothed = run_urts(params, run.y)
    assert isinstance(smoothed, SmootherResult) and smoothed.log_likelihoods is not None   # the forward filter's
    result = MHE(params, horizon=10).run(run.y, run.u)
    assert isinstance(result, MHEResult) and result.covariances is None and result.solver_failures == 0
    np.testing.assert_allclose(result.t, params.dt * np.arange(len(run.y)))


def test_the_mhe_asked_for_covariances_linearises_along_its_estimates(linear_case):
    params, run = linear_case
    result = MHE(params, horizon=10).run(run.y, run.u, covariances=True)
    np.testing.assert_array_equal(result.covariances, linearized_covariances(params, result.means, run.u))
    # an x0 given to the run replaces the bundle's (an MHE built once serves several records)
    moved = MHE(params, horizon=10).run(run.y, run.u, params.x0 + 0.5)
    assert not np.allclose(moved.means[0], result.means[0])


def test_the_mhe_asks_for_a_definite_q_where_the_ukf_takes_a_semi_definite_one(linear_case):
    params, run = linear_case
    singular = EstimatorParams(params.model, params.dt, np.zeros((9, 9)), params.R, params.P0, params.x0)
    assert run_ukf(singular, run.y).means.shape == (40, 9)
    with pytest.raises(InvalidInput, match="Q is not positive definite"):
        MHE(singular)


def test_a_prepared_flight_gives_each_model_its_own_noise_in_its_bundle():
    flight = read_flights([SAMPLES / "circle_rep2.csv"])[0]
    system = make_system("quadrotor")
    inflated = NoiseModel(tuple(3 * np.asarray(system.process_noise_std)), system.meas_noise_std, system.initial_std)
    model = HybridModel(system, "prior", noise=inflated)
    prepared = prepare(model, flight)
    own, prior = prepared.params, prepared.prior_params
    assert own.model is prepared.model and prior.model is prepared.prior
    assert own.dt == prior.dt == flight.dt and own.x0 is prior.x0 is prepared.x0
    np.testing.assert_allclose(own.Q, inflated.Q)
    np.testing.assert_allclose(prior.Q, inflated.Q)      # a prior-only model's prior is itself
    paper = prepare(model, flight, noise="paper")
    np.testing.assert_allclose(paper.params.Q, system.Q)
