"""Joint estimation of the training record's states and the residual (`estimators.joint_training`): on a simulated
cartpole whose true dynamics are known, the learned model is closer to them than the prior and than the paper's
Adam fit on the same observer's states."""
from __future__ import annotations

import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.algorithm1 import Algorithm1, first_observation
from learnest.estimators.joint_training import ITERATIONS, WEIGHT_PRIOR, solve_bordered_tridiagonal, train_jointly
from learnest.models.knode import HybridModel
from learnest.models.presets import PAPER_TRAINING
from learnest.models.systems import make_system
from learnest.models.training import train_knode


def _derivative_error(model, system, x, u):
    """RMS of ẋ_model − ẋ_true over the true states, per state."""
    model_rates = np.array([np.asarray(model.f_c(xx, uu), float) for xx, uu in zip(x, u)])
    true_rates = np.array([np.asarray(system.f_true(xx, uu), float) for xx, uu in zip(x, u)])
    return np.sqrt(np.mean((model_rates - true_rates) ** 2, axis=0))


def test_the_joint_fit_learns_the_true_dynamics_better_than_the_observer_fit():
    system = make_system("cartpole")             # the prior's cart is 1.0 kg, the true one 1.5 kg
    record = system.simulate(10_000, 1500)
    zeta = first_observation(system, record.y, record.u, system.dt, "filter")
    config = PAPER_TRAINING["cartpole"]
    joint = train_jointly(system, record.y, record.u, system.dt, zeta, config)
    adam = train_knode(system, zeta, record.u, system.dt, config).model
    x, u = record.x[::10], record.u[::10]
    rates = [1, 3]                               # the cart's and the pole's accelerations
    prior_err = _derivative_error(HybridModel(system, "prior"), system, x, u)[rates]
    joint_err = _derivative_error(joint.model, system, x, u)[rates]
    adam_err = _derivative_error(adam, system, x, u)[rates]
    assert np.all(joint_err < 0.3 * prior_err), (joint_err, prior_err)
    assert np.all(joint_err < adam_err), (joint_err, adam_err)


def test_the_joint_observer_of_algorithm_1_records_what_it_ran():
    system = make_system("cartpole")
    record = system.simulate(10_000, 300)
    result = Algorithm1("joint", PAPER_TRAINING["cartpole"], 2).fit(system, record.y, record.u, system.dt)
    meta = result.model.meta
    assert meta["observer"] == {"kind": "joint", "rounds": 2, "kept_round": 0, "misfit": []}
    assert meta["training"]["hidden"] == 8 and meta["training"]["seed"] == 0
    assert meta["training"]["weight_prior"] == WEIGHT_PRIOR
    assert len(result.losses) == meta["training"]["joint_iterations"] <= ITERATIONS
    assert np.all(np.diff(result.losses) < 0), "every Levenberg-Marquardt step taken lowers the objective"


def test_the_joint_fit_refuses_mismatched_or_non_finite_records():
    system = make_system("cartpole")
    record = system.simulate(10_000, 50)
    with pytest.raises(InvalidInput, match="one length"):
        train_jointly(system, record.y[:-1], record.u, system.dt, record.x, PAPER_TRAINING["cartpole"], 5)
    bad = record.y.copy()
    bad[3, 0] = np.nan
    with pytest.raises(InvalidInput, match="finite"):
        train_jointly(system, bad, record.u, system.dt, record.x, PAPER_TRAINING["cartpole"], 5)
    with pytest.raises(InvalidInput, match="weight_prior"):
        train_jointly(system, record.y, record.u, system.dt, record.x, PAPER_TRAINING["cartpole"], 5, -1.0)


def test_the_bordered_block_tridiagonal_solve_equals_a_dense_solve():
    """The normal equations' solver against numpy's dense solve of the same matrix, with and without damping:
    J's process rows reach x_k, x_{k+1} and θ, its measurement rows one x_k."""
    from learnest.estimators.native.block_tridiagonal import BlockTridiagonal

    rng = np.random.default_rng(3)
    T, n, m, P = 7, 3, 2, 4
    transition, measurement = rng.normal(size=(T - 1, n, n)), rng.normal(size=(T, m, n))
    weight_jacobians = rng.normal(size=(T - 1, n, P))   # B_k
    q_inv = np.diag(rng.uniform(0.5, 2.0, n))
    root = np.sqrt(q_inv)
    jacobian = np.zeros((T * m + (T - 1) * n, T * n + P))
    for k in range(T):
        jacobian[k * m:(k + 1) * m, k * n:(k + 1) * n] = measurement[k]
    for k in range(T - 1):
        rows = slice(T * m + k * n, T * m + (k + 1) * n)
        jacobian[rows, k * n:(k + 1) * n] = -root @ transition[k]
        jacobian[rows, (k + 1) * n:(k + 2) * n] = root
        jacobian[rows, T * n:] = -root @ weight_jacobians[k]
    full = jacobian.T @ jacobian + 0.1 * np.diag(np.r_[np.zeros(T * n), np.ones(P)])   # θ's weight prior
    border, corner = full[: T * n, T * n:].reshape(T, n, P), full[T * n:, T * n:]
    solver = BlockTridiagonal(n, m + n, T, q_inv, np.eye(m + n))
    rhs = rng.normal(size=T * n + P)
    for damping in (0.0, 0.7):
        expected = np.linalg.solve(full + damping * np.diag(np.diag(full)), rhs)
        step_x, step_theta = solve_bordered_tridiagonal(solver, transition, measurement, border, corner,
                                                        rhs[: T * n].reshape(T, n), rhs[T * n:], damping)
        np.testing.assert_allclose(np.concatenate([step_x.ravel(), step_theta]), expected, rtol=1e-8, atol=1e-9)
    with pytest.raises(ValueError, match="shapes"):     # a solver for other sizes would be read out of bounds
        solve_bordered_tridiagonal(BlockTridiagonal(n, m + n + 1, T, q_inv, np.eye(m + n + 1)), transition,
                                   measurement, border, corner, rhs[: T * n].reshape(T, n), rhs[T * n:])
    with pytest.raises(ValueError, match="shapes"):     # ...and so would one built for fewer nodes
        solve_bordered_tridiagonal(BlockTridiagonal(n, m + n, T - 1, q_inv, np.eye(m + n)), transition,
                                   measurement, border, corner, rhs[: T * n].reshape(T, n), rhs[T * n:])


def test_the_normal_equations_are_the_autograd_jacobians():
    """J's gradient and JᵀJ's border and corner, as the fit assembles them, against torch's Jacobian of the
    stacked residuals (measurement, process and weight-prior rows) on a short cartpole record."""
    import torch

    from learnest.estimators.joint_training import _JointProblem, normal_equations
    from learnest.estimators.params import EstimatorParams
    from learnest.models.training import new_residual

    system = make_system("cartpole")
    T, prior = 6, 10.0
    rng = np.random.default_rng(0)
    states, u, y = rng.normal(size=(T, system.n)) * 0.3, rng.normal(size=(T, 1)), rng.normal(size=(T, 2)) * 0.3
    torch.manual_seed(0)
    tuning = EstimatorParams(HybridModel(system, "prior"), system.dt, system.Q, system.R, system.P0, states[0])
    problem = _JointProblem(system, y, u, tuning, new_residual(system, states, u, 4), prior)
    theta = problem.theta0() + rng.normal(size=problem.theta0().size) * 0.1
    assembled = normal_equations(problem, states, theta)

    def stacked(z):
        x, th = z[: T * system.n].reshape(T, system.n), z[T * system.n:]
        r_m = (problem.y - system.h(x, problem.u)) * problem.inv_sigma_r
        r_q = (x[1:] - problem.steps(x[:-1], problem.u[:-1], th)) * torch.as_tensor(problem.inv_sigma_q)
        return torch.cat([r_m.ravel(), r_q.ravel(), np.sqrt(prior) * th])

    z = torch.as_tensor(np.r_[states.ravel(), theta])
    jacobian, r = torch.autograd.functional.jacobian(stacked, z).numpy(), stacked(z).numpy()
    gradient, gauss_newton = jacobian.T @ r, jacobian.T @ jacobian
    split = T * system.n
    np.testing.assert_allclose(np.r_[assembled["grad_x"].ravel(), assembled["grad_theta"]], gradient,
                               rtol=1e-9, atol=1e-9 * np.abs(gradient).max())
    np.testing.assert_allclose(assembled["border"].reshape(split, -1), gauss_newton[:split, split:], rtol=1e-9,
                               atol=1e-9 * np.abs(gauss_newton).max())
    np.testing.assert_allclose(assembled["corner"], gauss_newton[split:, split:], rtol=1e-9, atol=1e-9)
    assert problem.cost(states, theta) == pytest.approx(0.5 * r @ r / T, rel=1e-12)
