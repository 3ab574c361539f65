"""KNODE: exporters agree, models persist, and Algorithm 1 recovers a known residual."""
import copy
import json

import casadi as ca
import numpy as np
import pytest

from learnest.models.knode import HybridModel, Residual
from learnest.models.systems import make_system
from learnest.models.training import TrainingConfig, train_knode


def _random_mlp(n_in, n_out, hidden, seed=0):
    import torch

    from learnest.models.residual_net import ResidualNet

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    mlp = ResidualNet(n_in, n_out, hidden, rng.normal(size=n_in), rng.uniform(0.5, 2.0, size=n_in))
    torch.nn.init.normal_(mlp.output_layer.weight)
    torch.nn.init.normal_(mlp.output_layer.bias)
    return mlp


@pytest.mark.parametrize("name,hidden", [("cartpole", 8), ("robot", 8), ("quadrotor", 16)])
def test_torch_numpy_and_casadi_evaluations_agree_to_1e9(name, hidden):
    import torch  # torch is imported by the tests that use it, never at collection (it is slow)

    system = make_system(name)
    mlp = _random_mlp(system.n + system.n_inputs, system.n, hidden)
    model = HybridModel(system, "knode", mlp.export())
    rng = np.random.default_rng(1)
    x, u = rng.normal(size=(13, system.n)), rng.normal(size=(13, system.n_inputs))
    with torch.no_grad():
        xt, ut = torch.as_tensor(x), torch.as_tensor(u)
        from_torch = (system.f_prior(xt, ut) + mlp(torch.cat([xt, ut], -1))).numpy()
    from_numpy = model.f_c(x, u)  # one batched call for all 13 rows
    xs, us = ca.SX.sym("x", system.n), ca.SX.sym("u", system.n_inputs)
    f_sym = ca.Function("f", [xs, us], [model.f_c(xs, us)])
    from_casadi = np.vstack([np.asarray(f_sym(x[i], u[i])).ravel() for i in range(13)])
    np.testing.assert_allclose(from_numpy, from_torch, rtol=0, atol=1e-9)
    np.testing.assert_allclose(from_casadi, from_torch, rtol=0, atol=1e-9)
    # the exported CasADi graph is pure symbols: no callback, so it can be differentiated
    assert ca.Function("J", [xs, us], [ca.jacobian(model.step(xs, us, 0.01), xs)]).n_out() == 1


def test_model_saves_and_loads_exactly(tmp_path):
    system = make_system("cartpole")
    model = HybridModel(system, "knode", _random_mlp(5, 4, 8).export(), meta={"note": "x"})
    model.save(tmp_path / "m.json")
    loaded = HybridModel.load(tmp_path / "m.json")
    x, u = np.random.default_rng(2).normal(size=(5, 4)), np.ones((5, 1))
    np.testing.assert_array_equal(loaded.step(x, u, 0.01), model.step(x, u, 0.01))
    assert loaded.meta == {"note": "x"} and loaded.system.prior_params == system.prior_params


def test_loading_garbage_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_bytes(b"\x00\x01 not json")
    with pytest.raises(ValueError, match="bad.json"):
        HybridModel.load(bad)


def test_training_recovers_the_cart_mass_error_from_clean_states():
    """The residual a KNODE learns from one trajectory is f_true - f_prior (a 0.5 kg mass error)."""
    system = make_system("cartpole")
    run = system.simulate(10_000, n_samples=2500)
    result = train_knode(system, run.x, run.u, system.dt, TrainingConfig(epochs=250, lr=2e-2))
    truth = system.f_true(run.x, run.u) - system.f_prior(run.x, run.u)
    learned = result.model.residual(run.x, run.u)
    rel_error = np.sqrt(np.mean((learned - truth)[:, [1, 3]] ** 2) / np.mean(truth[:, [1, 3]] ** 2))
    assert rel_error < 0.15
    assert result.losses[-1] < 0.5 * result.losses[0]


@pytest.mark.parametrize("bad,match", [
    (np.full((10, 4), np.nan), "NaN"),
    (np.zeros((10, 3)), "columns"),
    (np.zeros(10), "2-D"),
])
def test_training_rejects_bad_arrays(bad, match):
    system = make_system("cartpole")
    with pytest.raises(ValueError, match=match):
        train_knode(system, bad, np.zeros((10, 1)), 0.01)


def test_training_rejects_zero_epochs():
    system = make_system("cartpole")
    with pytest.raises(ValueError, match="epochs"):
        train_knode(system, np.zeros((10, 4)), np.zeros((10, 1)), 0.01, TrainingConfig(epochs=0))


def test_knode_model_needs_a_residual():
    with pytest.raises(ValueError, match="residual"):
        HybridModel(make_system("cartpole"), "knode")
    # a residual survives its JSON round trip exactly: same layers, same outputs
    residual = _random_mlp(5, 4, 8).export()
    restored = Residual.from_dict(json.loads(json.dumps(residual.to_dict())))
    for (w, b), (w2, b2) in zip(residual.layers, restored.layers, strict=True):
        np.testing.assert_array_equal(w, w2)
        np.testing.assert_array_equal(b, b2)
    x, u = np.random.default_rng(0).normal(size=(7, 4)), np.random.default_rng(1).normal(size=(7, 1))
    np.testing.assert_array_equal(restored(x, u), residual(x, u))


def test_adam_matches_torch_optim_adam_bit_for_bit():
    """The training loop's Adam (written out to skip torch.optim's 3-4 s first-step import of
    torch._dynamo) takes exactly torch.optim.Adam's steps: same weights after 50 steps of a real loss."""
    import torch

    from learnest.models.residual_net import Adam

    torch.manual_seed(3)
    data, target = torch.randn(200, 9, dtype=torch.float64), torch.randn(200, 9, dtype=torch.float64)
    ours = torch.nn.Sequential(torch.nn.Linear(9, 16, dtype=torch.float64), torch.nn.Tanh(),
                               torch.nn.Linear(16, 9, dtype=torch.float64))
    reference, initial = copy.deepcopy(ours), copy.deepcopy(ours)
    optimizers = (Adam(ours.parameters(), lr=3e-3), torch.optim.Adam(reference.parameters(), lr=3e-3))
    for _ in range(50):
        for net, optimizer in zip((ours, reference), optimizers):
            loss = ((net(data) - target) ** 2).mean()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    for mine, theirs in zip(ours.parameters(), reference.parameters()):
        assert torch.equal(mine, theirs)
    assert not torch.equal(ours[0].weight, initial[0].weight)  # they moved: equal because both trained


def test_training_leaves_the_callers_torch_threads_alone():
    import torch

    system = make_system("quadrotor", n_samples=50)
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        zeta = np.cumsum(np.random.default_rng(0).normal(size=(50, 9)) * 0.01, axis=0)
        train_knode(system, zeta, np.zeros((50, 0)), 0.01, TrainingConfig(epochs=2, hidden=4))
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


def test_a_trained_robot_residual_does_not_depend_on_where_the_robot_is_or_which_way_it_points():
    """The robot's Δθ is blind to its invariant states (x, y, ψ): the range-only observer's errors depend on them,
    the physics does not.  A KNODE trained on a simulated lap gives the same residual anywhere, any heading."""
    from learnest.estimators.observers import pretraining_observer

    system = make_system("robot")
    assert set(system.residual_blind) == set(system.invariant_states) == {"x", "y", "psi"}
    run = system.simulate(3, 500)
    zeta = pretraining_observer(system, run.y, run.u, system.dt)
    residual = train_knode(system, zeta, run.u, system.dt, TrainingConfig(hidden=8, epochs=30)).model.residual
    moved = run.x + np.array([7.0, -3.0, 0.0, 2.0])           # elsewhere, turned by 2 rad, same speed
    here, there = residual(run.x, run.u), residual(moved, run.u)
    assert np.abs(here).max() > 1e-3                          # it learned something
    np.testing.assert_allclose(there, here, rtol=0, atol=1e-12)
    faster = run.x + np.array([0.0, 0.0, 0.5, 0.0])           # the speed it does see
    assert np.abs(residual(faster, run.u) - here).max() > 1e-6


def test_a_trained_cartpole_residual_corrects_only_the_accelerations_and_does_not_see_the_cart_position():
    """The derivatives of p and α are ṗ and α̇ by definition, and a level track is the same everywhere: Δθ's p and α
    rows are exactly 0, and it gives the same accelerations wherever the cart is."""
    system = make_system("cartpole")
    assert system.residual_states == ("p_dot", "alpha_dot") and system.residual_blind == system.invariant_states
    run = system.simulate(5, 600)
    residual = train_knode(system, run.x_noisy, run.u, system.dt, TrainingConfig(hidden=8, epochs=40)).model.residual
    here = residual(run.x, run.u)
    assert np.abs(here[:, [1, 3]]).max() > 1e-2                # it learned the accelerations' error
    assert np.all(here[:, [0, 2]] == 0.0)
    moved = run.x + np.array([0.8, 0.0, 0.0, 0.0])             # the cart elsewhere on the track
    np.testing.assert_allclose(residual(moved, run.u), here, rtol=0, atol=1e-12)
    faster = run.x + np.array([0.0, 0.5, 0.0, 0.0])            # the cart's speed it does see
    assert np.abs(residual(faster, run.u) - here).max() > 1e-6
