"""One error contract: option errors are `InvalidInput` naming the valid choices (422 through the API), and a
covariance the UKF had to repair is reported once per run with `NumericalWarning`."""
from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest

from learnest.errors import InvalidInput, NumericalWarning
from learnest.estimators.mhe import MHE
from learnest.estimators.params import EstimatorParams
from learnest.estimators.ukf import run_ukf
from learnest.models.knode import HybridModel
from learnest.models.systems import make_system


@pytest.mark.parametrize(("options", "named"), [
    ({"horizon": 0}, "at least 1"), ({"horizon": 2.5}, "at least 1"),
    ({"solver": "newton"}, "gauss-newton, ipopt"), ({"arrival": "none"}, "ekf, fixed"),
    ({"hessian": "bfgs"}, "cost, exact"), ({"max_iter": 0}, "positive integer"),
])
def test_bad_mhe_options_are_invalid_input_naming_the_choices(options, named):
    system = make_system("quadrotor")
    with pytest.raises(InvalidInput, match=named):
        MHE(EstimatorParams(HybridModel(system, "prior"), system.dt, system.Q, system.R, system.P0, np.zeros(9)),
            **options)


def test_a_repaired_covariance_warns_once_per_run():
    """Measurement noise of 1e-24 makes the posterior covariance a difference of nearly equal numbers: it
    comes out indefinite on many steps, each repaired; one run says so once, with the count."""
    system = make_system("quadrotor")
    model = HybridModel(system, "prior")
    y = np.random.default_rng(0).normal(size=(200, model.n_meas)) * 0.01
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, np.zeros(model.n))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_ukf(replace(params, R=np.eye(model.n_meas) * 1e-24), y, None)
    repaired = [w for w in caught if issubclass(w.category, NumericalWarning)]
    assert len(repaired) == 1 and "repaired" in str(repaired[0].message)
    assert int(str(repaired[0].message).split(" at ")[1].split()[0]) > 1   # many steps, one warning
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_ukf(params, y, None)   # a well-posed run repairs nothing and says nothing
    assert not [w for w in caught if issubclass(w.category, NumericalWarning)]
