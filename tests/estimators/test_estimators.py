"""KF, UKF and MHE against known answers on linear-Gaussian systems, and their input checks."""
import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.kf import linearize, run_kf
from learnest.estimators.mhe import MHE
from learnest.estimators.params import EstimatorParams
from learnest.estimators.ukf import make_ukf, run_ukf, spd_factor
from learnest.models.knode import HybridModel, Residual
from learnest.models.systems import make_system


@pytest.fixture(scope="module")
def linear_case():
    """The quadrotor prior (a linear kinematic chain) with linear measurements y = [p, a]."""
    system = make_system("quadrotor")
    model = HybridModel(system, "prior")
    run = system.simulate(5, n_samples=300)
    return system, model, run


def test_ukf_equals_kf_on_a_linear_gaussian_system(linear_case):
    system, model, run = linear_case
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
    kf = run_kf(params, run.y, run.u).means
    ukf = run_ukf(params, run.y, run.u).means
    # alpha = 1e-3 puts weights of order 1e6 on the sigma points: ~1e-7 relative is the floor there
    np.testing.assert_allclose(ukf, kf, rtol=0, atol=1e-7)
    wide = run_ukf(params, run.y, run.u, alpha=1.0).means
    np.testing.assert_allclose(wide, kf, rtol=0, atol=1e-10)


def test_mhe_with_a_long_horizon_is_the_full_information_estimate(linear_case):
    """With the window covering the whole record, MHE solves the batch least-squares problem, whose
    last node is the KF estimate (linear-Gaussian), at every step."""
    system, model, run = linear_case
    T = 40
    y, u, x0 = run.y[:T], run.u[:T], run.x_noisy[0]
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, x0)
    kf = run_kf(params, y, u).means
    mhe = MHE(params, horizon=T + 5).run(y, u).means
    np.testing.assert_allclose(mhe, kf, rtol=0, atol=1e-6 * np.abs(kf).max())
    # and the last node equals an independent dense batch least-squares solution
    F, H = linearize(model, system.dt)
    n = model.n
    rows, rhs, weights = [], [], []
    for k in range(T):                                       # measurement rows
        row = np.zeros((6, n * T)); row[:, k * n:(k + 1) * n] = H
        rows.append(row); rhs.append(y[k]); weights.append(np.linalg.inv(system.R))
    for k in range(T - 1):                                   # dynamics rows x_{k+1} - F x_k = w_k
        row = np.zeros((n, n * T)); row[:, (k + 1) * n:(k + 2) * n] = np.eye(n); row[:, k * n:(k + 1) * n] = -F
        rows.append(row); rhs.append(np.zeros(n)); weights.append(np.linalg.inv(system.Q))
    row = np.zeros((n, n * T)); row[:, :n] = np.eye(n)       # arrival cost
    rows.append(row); rhs.append(x0); weights.append(np.linalg.inv(system.P0))
    A, b = np.vstack(rows), np.concatenate(rhs)
    from scipy.linalg import block_diag
    W = block_diag(*weights)
    batch = np.linalg.solve(A.T @ W @ A, A.T @ W @ b).reshape(T, n)
    np.testing.assert_allclose(mhe[-1], batch[-1], rtol=0, atol=1e-6 * np.abs(batch).max())


def test_mhe_warm_start_and_arrival_options_give_the_same_estimates_on_a_linear_system(linear_case):
    system, model, run = linear_case
    y, u = run.y[:60], run.u[:60]
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
    # warm starting is an IPOPT option (the Gauss-Newton solver always starts from the shifted window)
    ipopt = dict(horizon=10, solver="ipopt")
    warm = MHE(params, **ipopt).run(y, u).means
    cold = MHE(params, warm_start=False, **ipopt).run(y, u).means
    np.testing.assert_allclose(warm, cold, atol=1e-7)
    fixed = MHE(params, horizon=10, arrival="fixed").run(y, u).means
    # the EKF-propagated arrival (the Kalman filter's own recursion here) makes the MHE the KF, optimal on a
    # linear system; a constant P0 summarises the data that left the window worse
    mse = {name: np.mean((est - run.x[:60]) ** 2) for name, est in
           [("ekf", warm), ("fixed", fixed),
            ("kf", run_kf(params, y, u).means)]}
    assert mse["ekf"] == pytest.approx(mse["kf"], rel=1e-9) and mse["kf"] < mse["fixed"]


def test_batched_ukf_matches_filterpy_step_for_step_on_a_nonlinear_system():
    """Same filter as filterpy's own predict/update calling fx once per point: states, covariances and
    likelihoods agree on the cartpole (sin/cos dynamics), with the factor reuse and batching in place."""
    system = make_system("cartpole")
    model, run = HybridModel(system, "prior"), system.simulate(2, n_samples=200)
    ours = make_ukf(EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0]))
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter  # slow import: only here

    points = MerweScaledSigmaPoints(4, alpha=1e-3, beta=2.0, kappa=0.0)
    plain = UnscentedKalmanFilter(4, 2, system.dt, points=points,
                                  fx=lambda x, dt, u: model.step(x[None], u[None], dt)[0],
                                  hx=lambda x, u: model.h(x[None], u[None])[0])
    plain.x, plain.P, plain.Q, plain.R = run.x_noisy[0].copy(), system.P0.copy(), system.Q, system.R
    for k in range(len(run.y)):
        if k:
            ours.predict(u=run.u[k - 1])
            plain.predict(u=run.u[k - 1])
        ours.update(run.y[k], u=run.u[k])
        plain.update(run.y[k], u=run.u[k])
    np.testing.assert_allclose(ours.x, plain.x, rtol=0, atol=1e-7)  # α = 1e-3 weights amplify rounding
    np.testing.assert_allclose(ours.P, plain.P, rtol=1e-6, atol=1e-14)
    assert ours.log_likelihood == pytest.approx(plain.log_likelihood, rel=1e-6)


def test_the_compiled_sigma_point_model_gives_the_numpy_filter_s_estimates():
    """run_ukf(compiled=True) on a cartpole KNODE with inputs: the same filter to rounding (amplified by the
    α = 1e-3 weights, as against filterpy above)."""
    system = make_system("cartpole")
    rng = np.random.default_rng(0)
    residual = Residual([(rng.normal(0, 0.5, (8, 5)), rng.normal(0, 0.1, 8)),
                         (rng.normal(0, 0.2, (4, 8)), np.zeros(4))])
    model, run = HybridModel(system, "knode", residual), system.simulate(2, n_samples=200)
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
    plain = run_ukf(params, run.y, run.u).means
    fast = run_ukf(params, run.y, run.u, compiled=True).means
    np.testing.assert_allclose(fast, plain, rtol=0, atol=1e-7)


def test_the_c_filter_loop_equals_the_python_filter_step_for_step():
    """run_ukf's C loop (ukf.c) against BatchedUKF driven from Python over the same compiled sigma-point
    functions, on a cartpole KNODE with inputs: means, covariances and innovations agree to rounding.  With
    an indefinite Q every predicted covariance fails Cholesky, so each step goes through the repair that
    the C loop hands back to spd_factor: it must agree there too."""
    from learnest.estimators.ukf import compiled_sigma_functions

    system = make_system("cartpole")
    rng = np.random.default_rng(0)
    residual = Residual([(rng.normal(0, 0.5, (8, 5)), rng.normal(0, 0.1, 8)),
                         (rng.normal(0, 0.2, (4, 8)), np.zeros(4))])
    model, run = HybridModel(system, "knode", residual), system.simulate(2, n_samples=150)
    functions = compiled_sigma_functions(model, system.dt)
    if functions is None or functions.native is None:
        pytest.skip("no C compiler here")
    x0, P0 = run.x_noisy[0], system.P0
    for Q, repaired in ((system.Q, False), (system.Q - np.diag([0, 0, 0, 1e-2]), True)):
        ours = functions.native.run(run.y, run.u, system.dt, Q, system.R, x0, P0, alpha=1e-3)
        ukf = make_ukf(EstimatorParams(model, system.dt, Q, system.R, P0, x0),
                       sigma_functions=tuple(functions))  # Python loop
        ukf.sigmas_f = ukf._sigmas()
        for k in range(len(run.y)):
            if k:
                ukf.predict(u=run.u[k - 1])
            ukf.update(run.y[k], u=run.u[k])
            np.testing.assert_allclose(ours.means[k], ukf.x, rtol=0, atol=1e-7)   # α = 1e-3 amplifies rounding
            np.testing.assert_allclose(ours.covariances[k], ukf.P, rtol=0, atol=1e-9)
            np.testing.assert_allclose(ours.innovations[k], ukf.y, rtol=0, atol=1e-7)
        # the eigenvalue lift leaves the smallest eigenvalue at spd_factor's floor (~1e-15)
        assert (np.linalg.eigvalsh(ours.covariances[-1]).min() < 1e-12) == repaired
    # functions compiled for this model refuse another model's sizes (C would write past the arrays)
    robot = make_system("robot")
    T = len(run.y)
    with pytest.raises(InvalidInput, match=r"built for a model with n=4, m=2, p=1: got y \(150, 5\) \(expected"):
        run_ukf(EstimatorParams(HybridModel(robot, "prior"), system.dt, robot.Q, robot.R, robot.P0, np.zeros(4)),
                np.zeros((T, 5)), np.zeros((T, 2)), sigma_functions=functions)


def test_spd_factor_repairs_an_indefinite_covariance_and_the_kept_covariance_is_read_only():
    P = np.array([[1.0, 2.0], [2.0, 1.0]])  # eigenvalues 3 and -1
    repaired, L = spd_factor(P)
    np.testing.assert_allclose(L @ L.T, repaired, atol=1e-12)
    assert np.linalg.eigvalsh(repaired).min() > 0
    model = HybridModel(make_system("quadrotor"), "prior")
    ukf = make_ukf(EstimatorParams(model, 0.01, np.eye(9), np.eye(6), np.eye(9), np.zeros(9)))
    with pytest.raises(ValueError, match="read-only"):
        ukf.P *= 2  # would outdate the kept factor silently; assigning a new array is the way
    ukf.P = 4 * np.eye(9)
    ukf.predict(u=np.zeros(0))
    F = model.step(np.eye(9), np.zeros((9, 0)), 0.01).T  # the prior is linear: its step matrix
    np.testing.assert_allclose(ukf.P, F @ (4 * np.eye(9)) @ F.T + np.eye(9), atol=1e-9)  # the new P was used


def test_ukf_survives_ten_thousand_steps_with_a_singular_process_noise():
    """No process noise, very precise sensors and a nonlinear model: the covariance collapses towards
    singular, which kills a plain Cholesky; ours stays symmetric positive definite."""
    system = make_system("robot")
    run = system.simulate(1, n_samples=10_000)
    model = HybridModel(system, "true")
    params = EstimatorParams(model, system.dt, np.zeros((4, 4)), system.R * 1e-6, system.P0 * 1e-6, run.x[0])
    estimates = run_ukf(params, run.y, run.u).means
    assert np.all(np.isfinite(estimates))
    assert np.sqrt(np.mean((estimates - run.x) ** 2)) < 0.05


@pytest.mark.parametrize("estimator", ["kf", "ukf", "mhe"])
@pytest.mark.parametrize("change,match", [
    (dict(y=np.zeros((10, 5))), "columns"),
    (dict(y=np.full((10, 6), np.nan)), "NaN"),
    (dict(Q=np.full((9, 9), np.inf)), "Q contains NaN"),
    (dict(R=-np.eye(6)), "R is not positive"),
    (dict(P0=np.ones((3, 3))), "P0 must be 9x9"),
    (dict(x0=np.zeros(4)), "x0 must have 9"),
    (dict(dt=0.0), "dt must be"),
])
def test_bad_arguments_raise_clear_value_errors(linear_case, estimator, change, match):
    system, model, _ = linear_case
    args = dict(y=np.zeros((10, 6)), u=np.zeros((10, 0)), dt=0.01, Q=system.Q, R=system.R,
                x0=np.zeros(9), P0=system.P0)
    args.update(change)
    with pytest.raises(ValueError, match=match):
        params = EstimatorParams(model, args["dt"], args["Q"], args["R"], args["P0"], args["x0"])
        if estimator == "kf":
            run_kf(params, args["y"], args["u"])
        elif estimator == "ukf":
            run_ukf(params, args["y"], args["u"])
        else:
            MHE(params, horizon=5).run(args["y"], args["u"])


def test_mhe_rejects_bad_options(linear_case):
    system, model, _ = linear_case
    params = EstimatorParams(model, 0.01, system.Q, system.R, system.P0, np.zeros(9))
    with pytest.raises(ValueError, match="horizon"):
        MHE(params, horizon=0)
    with pytest.raises(ValueError, match="arrival"):
        MHE(params, arrival="magic")


def test_an_evaluation_builds_each_models_compiled_ukf_once_and_scores_like_numpy():
    """A batch shares one cache: the compiled sigma-point model of each model is built once, before the timer
    (its code generation is not in ms_per_step), and the compiled filter scores as the numpy one."""
    from learnest.estimators.evaluate import evaluate_sequence

    system = make_system("cartpole")
    prior, true = HybridModel(system, "prior"), HybridModel(system, "true")
    run = system.simulate(0, n_samples=200)
    prior, true = (EstimatorParams(m, system.dt, system.Q, system.R, system.P0, run.x[0]) for m in (prior, true))
    args = dict(y=run.y, u=run.u, reference=run.x)
    cache: dict = {}
    first = evaluate_sequence(["ukf", "knode-ukf"], prior, true, mhe_cache=cache, **args)
    built = {key: value for key, value in cache.items() if key[0] == "ukf"}
    assert len(built) == 2                          # prior and true dynamics: each model its own pair
    second = evaluate_sequence(["ukf", "knode-ukf"], prior, true, mhe_cache=cache, **args)
    assert {key: value for key, value in cache.items() if key[0] == "ukf"} == built   # the same objects
    assert second["knode-ukf"]["mse"] == first["knode-ukf"]["mse"]
    numpy_mse = np.mean((run_ukf(true, run.y, run.u).means - run.x) ** 2)
    assert first["knode-ukf"]["mse"] == pytest.approx(numpy_mse, rel=1e-6)
