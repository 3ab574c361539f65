"""How much of a learned residual to trust (`models.residual_scale`, `estimators.group_training`):
known answers.

- s·Δθ is exactly s times the network's output, masks kept; s = 0 steps exactly as the prior.
- The choice rule on tables with a known answer: the largest scale meeting the goal on every held-out group,
  else the scale better on the most held-out flights, else the prior.
- Simulated Crazyflie flights whose truth is the prior, scored with a residual that is a constant vertical
  error (0.3 m/s² of acceleration it settles on): the gap score is worse than the prior's at every scale, less so
  the smaller the scale, and the rule falls back to the prior (scale 0).
"""
import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.group_training import gap_gains_by_scale, group_summary, train_with_scale_choice
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.inputs import training_meta
from learnest.models.knode import HybridModel, Residual
from learnest.models.residual_scale import choose_scale, scaled_model, scaled_residual
from learnest.models.systems import make_system


def _random_residual(rng, n_in=18, hidden=16, n_out=9):
    out = rng.normal(size=(n_out, hidden))
    out[:6] = 0.0   # masked rows (the Crazyflie residual writes only the ȧ rows)
    return Residual([(rng.normal(size=(hidden, n_in)), rng.normal(size=hidden)),
                     (out, np.concatenate([np.zeros(6), rng.normal(size=3)]))])


def test_scaled_residual_is_s_times_the_output_with_its_masks():
    rng = np.random.default_rng(0)
    residual = _random_residual(rng)
    x, u = rng.normal(size=(50, 9)), rng.normal(size=(50, 9))
    for scale in (0.0, 0.25, 1.0):
        out = scaled_residual(residual, scale)(x, u)
        np.testing.assert_allclose(out, scale * residual(x, u), rtol=1e-12, atol=1e-15)
        assert np.all(out[:, :6] == 0.0)


def test_scale_zero_steps_exactly_as_the_prior():
    system = make_system("crazyflie")
    rng = np.random.default_rng(1)
    knode = HybridModel(system, "knode", _random_residual(rng), {"name": "k"})
    x = np.tile([0.0, 0.0, 1.0, 0.1, -0.2, 0.05, 0.0, 0.0, 0.0], (4, 1))
    u = np.tile([0.0, 0.0, 0.0, 1.0, *[cf.hover_pwm(system.prior_params, vbat=3.7)] * 4, 3.7], (4, 1))
    off = scaled_model(knode, 0.0)
    np.testing.assert_array_equal(off.step(x, u, 0.01), HybridModel(system, "prior").step(x, u, 0.01))
    assert off.meta["residual_scale"] == 0.0 and off.meta["name"] == "k"
    assert not np.array_equal(knode.step(x, u, 0.01), off.step(x, u, 0.01))


@pytest.mark.parametrize("scale", [-0.1, 1.5, float("nan"), "1"])
def test_a_scale_outside_0_1_is_refused(scale):
    with pytest.raises(InvalidInput, match="residual scale"):
        scaled_residual(_random_residual(np.random.default_rng(2)), scale)


def _group(gains, worse=0):
    return {"gains_pct": list(gains), "worse_beyond": worse}


def test_rule_takes_the_largest_scale_that_meets_the_goal_on_every_group():
    results = {1.0: [_group([5, -1, 8]), _group([-3, -2, 1])],             # one group's median below 0
               0.75: [_group([4, 2, 6]), _group([3, 1, 2], worse=1)],      # a flight worse beyond its interval
               0.5: [_group([3, 2, 4]), _group([1, 2, 1])],                # meets it
               0.25: [_group([2, 1, 2]), _group([1, 1, 1])]}               # meets it too, but smaller
    assert choose_scale(results) == 0.5


def test_rule_falls_back_to_the_scale_better_on_most_flights_then_to_the_prior():
    no_pass = {1.0: [_group([9, 9, -5], worse=1)], 0.5: [_group([2, 3, 1], worse=1)],
               0.25: [_group([1, 1, 1], worse=1)]}
    assert choose_scale(no_pass) == 0.5                                   # 3 flights better, ties to the larger
    nothing_better = {1.0: [_group([-4, -2], worse=2)], 0.5: [_group([-1, 0], worse=1)]}
    assert choose_scale(nothing_better) == 0.0


def test_choosing_needs_two_groups():
    with pytest.raises(InvalidInput, match="at least two groups"):
        train_with_scale_choice({"circle": []})


def test_a_residual_that_is_a_constant_error_is_scaled_to_the_prior_on_simulated_flights():
    """Truth = the prior; the residual adds a constant 0.3 m/s² to the vertical acceleration the model settles on
    (its output bias on ȧ_z is 0.3 / tau_s): every flight's gap score is worse than the prior's, less so at a
    smaller scale, and no scale is better anywhere, so the rule keeps the prior."""
    system = make_system("crazyflie")
    flights = [simulate_crazyflie(SimulatedFlight(truth=dict(cf.IDENTIFIED), duration_s=20.0), seed=s)
               for s in (0, 1)]
    bias = np.zeros(9)
    bias[8] = 0.3 / system.prior_params["tau_s"]
    constant = Residual([(np.zeros((4, 18)), np.zeros(4)), (np.zeros((9, 4)), bias)])
    knode = HybridModel(system, "knode", constant, training_meta(system))
    gains = gap_gains_by_scale(knode, flights, (1.0, 0.5, 0.25))
    assert [len(rows) for rows in gains.values()] == [2, 2, 2]
    for i in range(2):
        g = [gains[s][i]["gain_pct"] for s in (1.0, 0.5, 0.25)]
        assert g[0] < g[1] < g[2] < 0.0
    assert gains[1.0][0]["interval_pct"][1] < 0.0   # worse beyond its interval at full scale
    table = {s: [group_summary(rows)] for s, rows in gains.items()}
    assert table[1.0][0]["worse_beyond"] >= 1
    assert choose_scale(table) == 0.0
