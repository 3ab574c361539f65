"""The three evaluators of one model agree, and RK4 is the RK4 we think it is."""
import casadi as ca
import numpy as np
import pytest
from scipy.linalg import expm

from learnest.models.backend import rk4_step
from learnest.models.systems import make_system


def test_rk4_matches_matrix_exponential_with_fourth_order_convergence():
    A = np.array([[0.0, 1.0, 0.0], [-4.0, -0.3, 1.0], [0.0, 0.0, -2.0]])
    x0 = np.array([1.0, -0.5, 0.3])
    errors = []
    for dt in (0.1, 0.05):
        x = x0.copy()
        for _ in range(int(round(1.0 / dt))):
            x = rk4_step(lambda s, _u: s @ A.T, x, None, dt)
        errors.append(np.linalg.norm(x - expm(A) @ x0))
    assert errors[1] < 1e-5
    order = np.log2(errors[0] / errors[1])
    assert 3.7 < order < 4.3  # global error of a 4th-order method halves 16x per halved step


@pytest.mark.parametrize("name", ["cartpole", "robot", "quadrotor"])
def test_prior_true_and_h_agree_in_numpy_torch_and_casadi(name):
    import torch  # here, not at module level: collection must not import torch (it is slow)

    system = make_system(name)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(7, system.n)) + system.initial_state(rng)
    u = rng.normal(size=(7, system.n_inputs))
    xs, us = ca.SX.sym("x", system.n), ca.SX.sym("u", system.n_inputs)
    for fn in (system.f_prior, system.f_true, system.h):
        batched = fn(x, u)
        symbolic = ca.Function("f", [xs, us], [fn(xs, us)])
        from_casadi = np.vstack([np.asarray(symbolic(x[i], u[i])).ravel() for i in range(len(x))])
        from_torch = fn(torch.as_tensor(x), torch.as_tensor(u)).numpy()
        np.testing.assert_allclose(from_casadi, batched, rtol=0, atol=1e-12)
        np.testing.assert_allclose(from_torch, batched, rtol=0, atol=1e-12)


def test_cartpole_prior_and_truth_differ_only_through_cart_mass():
    system = make_system("cartpole")
    assert system.true_params["m_c"] == 1.5 and system.prior_params["m_c"] == 1.0
    same_mass = system.with_true_params(m_c=1.0)
    x, u = np.array([[0.1, 0.2, 3.0, -0.4]]), np.array([[2.0]])
    np.testing.assert_allclose(same_mass.f_true(x, u), same_mass.f_prior(x, u))
    # with F = 0 and the pole hanging still, nothing moves whatever the mass
    rest = np.array([[0.0, 0.0, np.pi, 0.0]])
    np.testing.assert_allclose(system.f_true(rest, np.zeros((1, 1))), 0.0, atol=1e-12)


def test_simulation_is_reproducible_and_matches_the_papers_sizes():
    system = make_system("cartpole")
    a, b = system.simulate(3, n_samples=50), system.simulate(3, n_samples=50)
    np.testing.assert_array_equal(a.y, b.y)
    assert system.n_samples == 5000 and system.dt * system.n_samples == pytest.approx(10.0)
    robot = make_system("robot")
    assert robot.n_samples == 2500 and robot.dt * robot.n_samples == pytest.approx(25.0)
    # measurement noise has the stated size
    residual = a.y - system.h(a.x)
    assert 0.005 < residual.std() < 0.02


def test_unknown_system_is_a_clear_error():
    with pytest.raises(ValueError, match="unknown system"):
        make_system("submarine")
