"""The Gauss–Newton MHE (the default solver) against IPOPT, the reference, on known cases."""
import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.kf import run_kf
from learnest.estimators.mhe import MHE
from learnest.estimators.native.codegen import compiled
from learnest.estimators.params import EstimatorParams
from learnest.models.knode import HybridModel, Residual
from learnest.models.systems import make_system


def both(model, system, run, T, **options):
    y, u = run.y[:T], run.u[:T]
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
    gn = MHE(params, solver="gauss-newton", **options)
    ipopt = MHE(params, solver="ipopt", **options)
    return gn, gn.run(y, u).means, ipopt.run(y, u).means


def test_gauss_newton_equals_ipopt_and_the_kalman_filter_on_a_linear_system():
    """Quadrotor prior (linear): one exact step per window.  Sliding (horizon 10 on 80 samples), the arrival
    cost is the Kalman filter's prediction at the window's start, so every window's last node is the KF's
    estimate; with a window longer than the record, the full-information estimate's last node is too."""
    system = make_system("quadrotor")
    run = system.simulate(5, n_samples=80)
    model = HybridModel(system, "prior")
    gn, ours, ipopt = both(model, system, run, 80, horizon=10)
    np.testing.assert_allclose(ours, ipopt, rtol=0, atol=1e-6)
    assert gn.stats["iterations"] == gn.stats["solves"] == 80  # linear: one step each
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
    sliding_kf = run_kf(params, run.y[:80], run.u[:80]).means
    np.testing.assert_allclose(ours, sliding_kf, rtol=0, atol=1e-6 * np.abs(sliding_kf).max())
    np.testing.assert_allclose(ipopt, sliding_kf, rtol=0, atol=1e-6 * np.abs(sliding_kf).max())
    long = MHE(params, horizon=50).run(run.y[:40], run.u[:40]).means
    kf = run_kf(params, run.y[:40], run.u[:40]).means
    np.testing.assert_allclose(long, kf, rtol=0, atol=1e-6 * np.abs(kf).max())


@pytest.mark.parametrize("name,kind", [("cartpole", "true"), ("robot", "true"), ("cartpole", "knode")])
def test_gauss_newton_equals_ipopt_on_nonlinear_systems(name, kind):
    """Cartpole (sin/cos dynamics), robot (range measurements: nonlinear h) and a cartpole KNODE with a
    random residual network: the converged windows are IPOPT's within 1e-6, sliding and growing."""
    system = make_system(name)
    run = system.simulate(3, n_samples=160)
    residual = None
    if kind == "knode":
        rng = np.random.default_rng(0)
        n_in = system.n + system.n_inputs
        residual = Residual([(rng.normal(0, 0.5, (8, n_in)), rng.normal(0, 0.1, 8)),
                             (rng.normal(0, 0.2, (system.n, 8)), np.zeros(system.n))])
    model = HybridModel(system, kind, residual)
    gn, ours, ipopt = both(model, system, run, 160, horizon=20)
    np.testing.assert_allclose(ours, ipopt, rtol=0, atol=1e-6)
    assert gn.stats["failures"] == 0 and gn.stats["ipopt_fallbacks"] == 0


def test_fixed_arrival_and_the_interpreter_fallback_give_the_same_estimates():
    system = make_system("cartpole")
    run = system.simulate(4, n_samples=60)
    model = HybridModel(system, "true")
    gn, ours, ipopt = both(model, system, run, 60, horizon=8, arrival="fixed")
    np.testing.assert_allclose(ours, ipopt, rtol=0, atol=1e-6)
    interpreted = MHE(gn.params, horizon=8, arrival="fixed", compiler=None)
    assert interpreted._gn.backend == "casadi" and gn._gn.backend in ("c", "casadi")
    np.testing.assert_allclose(interpreted.run(run.y[:60], run.u[:60]).means, ours, rtol=0, atol=1e-9)


def test_the_papers_smoothing_update_is_one_mhe_in_c_python_and_ipopt_and_counts_the_window_again():
    """The paper's eq. (2) arrival mean (the last window's estimate of the new first step): the compiled
    Gauss–Newton loop, its Python twin and IPOPT agree; on a linear system it differs from the Kalman filter that
    the filtering update equals, because each shift counts the window's measurements again."""
    system = make_system("cartpole")
    run = system.simulate(4, n_samples=80)
    gn, ours, ipopt = both(HybridModel(system, "true"), system, run, 80, horizon=10, arrival_update="smoothing")
    np.testing.assert_allclose(ours, ipopt, rtol=0, atol=1e-6)
    interpreted = MHE(gn.params, horizon=10, arrival_update="smoothing", compiler=None)
    assert interpreted._gn.backend == "casadi"
    np.testing.assert_allclose(interpreted.run(run.y[:80], run.u[:80]).means, ours, rtol=0, atol=1e-9)
    linear = make_system("quadrotor")
    run = linear.simulate(5, n_samples=80)
    params = EstimatorParams(HybridModel(linear, "prior"), linear.dt, linear.Q, linear.R, linear.P0, run.x_noisy[0])
    kf = run_kf(params, run.y[:80], run.u[:80]).means
    smoothed = MHE(params, horizon=10, arrival_update="smoothing").run(run.y[:80], run.u[:80]).means
    filtered = MHE(params, horizon=10).run(run.y[:80], run.u[:80]).means
    np.testing.assert_allclose(filtered, kf, rtol=0, atol=1e-6 * np.abs(kf).max())
    assert np.abs(smoothed - kf)[11:].max() > 1e-3 * np.abs(kf).max()   # from the first shift on
    np.testing.assert_allclose(smoothed[:11], kf[:11], rtol=0, atol=1e-6 * np.abs(kf).max())   # growing window
    with pytest.raises(InvalidInput, match="arrival_update"):
        MHE(params, arrival_update="smoothed")


def test_a_real_time_iteration_is_close_but_not_equal():
    """max_iter=1 (one Gauss–Newton step per window) trades accuracy for time: measurable, small."""
    system = make_system("cartpole")
    run = system.simulate(3, n_samples=150)
    model = HybridModel(system, "true")
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
    rti = MHE(params, max_iter=1).run(run.y[:150], run.u[:150]).means
    exact = MHE(params).run(run.y[:150], run.u[:150]).means
    gap = np.abs(rti - exact).max()
    assert 0 < gap < 0.05 * np.abs(exact).max()


def test_compiled_functions_are_cached_by_content(tmp_path):
    import casadi as ca
    x = ca.SX.sym("x", 3)
    fn = ca.Function("lrn_test_square", [x], [x * x])
    first = compiled([fn], cache_dir=tmp_path)[0]
    if first.backend != "c":
        pytest.skip("no C compiler here")
    libraries = sorted(tmp_path.glob("*.so"))
    assert len(libraries) == 1
    stamp = libraries[0].stat().st_mtime_ns
    again = compiled([fn], cache_dir=tmp_path)[0]
    assert libraries[0].stat().st_mtime_ns == stamp and len(list(tmp_path.glob("*.so"))) == 1
    again.inputs[0][...] = [1.0, -2.0, 3.0]
    np.testing.assert_array_equal(again()[0].ravel(), [1.0, 4.0, 9.0])


def _masked_cartpole_knode(seed):
    """A cartpole KNODE whose residual corrects only the accelerations and does not see the cart position
    (masks folded into the weights as `ResidualNet.export` does), random weights of one architecture."""
    from dataclasses import replace
    system = replace(make_system("cartpole"), residual_states=("p_dot", "alpha_dot"), residual_blind=("p",))
    inputs, outputs = system.residual_masks()
    rng = np.random.default_rng(seed)
    residual = Residual([(rng.normal(0, 0.5, (6, 5)) * inputs, rng.normal(0, 0.1, 6)),
                         (rng.normal(0, 0.3, (4, 6)) * outputs[:, None], rng.normal(0, 0.1, 4) * outputs)])
    return system, HybridModel(system, "knode", residual)


def test_a_second_model_of_an_architecture_skips_code_generation_in_this_process(tmp_path, monkeypatch):
    """`compiled(key=...)`: the UKF functions of a second model of the same architecture (other weights)
    reuse the library loaded for the first without generating C; a model whose residual masks differ
    (same layer sizes) is another key, gets its own code, and each filter equals the numpy one."""
    import casadi as ca

    from learnest.estimators.ukf import compiled_sigma_functions, run_ukf
    generated = []

    class CountingGenerator(ca.CodeGenerator):
        def add(self, fn, *args):
            generated.append(fn.name())
            return super().add(fn, *args)

    monkeypatch.setattr(ca, "CodeGenerator", CountingGenerator)
    system, first = _masked_cartpole_knode(1)
    (w1, b1), second_layer = _masked_cartpole_knode(3)[1].residual.layers
    w1 = w1.copy()
    w1[:, 1] = 0.0   # one more blind input: the zero pattern is part of the architecture (Residual.parametric)
    run = system.simulate(3, n_samples=40)
    models = [first, _masked_cartpole_knode(2)[1], HybridModel(system, "knode", Residual([(w1, b1), second_layer]))]
    counts = []
    for model in models:
        before = len(generated)
        functions = compiled_sigma_functions(model, system.dt, tmp_path)
        if functions is None:
            pytest.skip("no C compiler here")
        counts.append(len(generated) - before)
        params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
        np.testing.assert_allclose(run_ukf(params, run.y, run.u, sigma_functions=functions).means,
                                   run_ukf(params, run.y, run.u).means, rtol=0, atol=1e-7)
    assert counts == [2, 0, 2]


def test_models_of_one_architecture_share_one_compiled_library(tmp_path):
    """Weights, physical parameters and dt are inputs of the compiled code, not constants in it: a second
    model of the same architecture (other weights, another prior mass, another dt) compiles nothing new,
    and each model's MHE still equals IPOPT and its compiled UKF the numpy filter; masked residual rows are
    structural zeros, so exactly zero."""
    from dataclasses import replace

    import casadi as ca

    from learnest.estimators.ukf import run_ukf
    models = [_masked_cartpole_knode(1)[1], _masked_cartpole_knode(2)[1]]
    second = models[1]
    models[1] = HybridModel(replace(second.system, prior_params={**second.system.prior_params, "m_c": 1.2}),
                            "knode", second.residual)
    run = models[0].system.simulate(3, n_samples=40)
    libraries, estimates = [], []
    for model, dt in zip(models, (0.002, 0.0025)):
        system = model.system
        y, u = run.y, run.u
        params = EstimatorParams(model, dt, system.Q, system.R, system.P0, run.x_noisy[0])
        gn = MHE(params, horizon=8, codegen_dir=tmp_path)
        if gn._gn.backend != "c":
            pytest.skip("no C compiler here")
        ours = gn.run(y, u).means
        ipopt = MHE(params, horizon=8, solver="ipopt").run(y, u).means
        np.testing.assert_allclose(ours, ipopt, rtol=0, atol=1e-6)
        fast = run_ukf(params, y, u, compiled=True, codegen_dir=tmp_path).means
        np.testing.assert_allclose(fast, run_ukf(params, y, u).means, rtol=0, atol=1e-7)
        libraries.append(sorted(path.name for path in tmp_path.glob("*.so")))
        estimates.append(ours)
    # the MHE's model functions, its linear algebra (btd.c/gn.c), the UKF's and its loop (ukf.c): built
    # once, then loaded
    assert len(libraries[0]) == 4 and libraries[1] == libraries[0]
    assert np.abs(estimates[0] - estimates[1]).max() > 1e-3      # the second model's weights were used
    symbolic, theta, values = models[0].parametric()
    x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 1)
    residual = ca.Function("residual", [x, u, theta], [symbolic.residual(x, u)])
    assert residual.sparsity_out(0).row() == [1, 3]                  # p and alpha rows: structural zeros
    assert not ca.depends_on(symbolic.residual(x, u), x[0])          # the blind input is never read
    out = np.asarray(residual(run.x[5], run.u[5], values)).ravel()   # zeros as numbers, masked rows exact
    np.testing.assert_allclose(out, models[0].residual(run.x[5:6], run.u[5:6])[0], rtol=0, atol=1e-14)
    assert out[0] == 0.0 and out[2] == 0.0


def test_mhe_rejects_an_unknown_solver():
    system = make_system("quadrotor")
    model = HybridModel(system, "prior")
    params = EstimatorParams(model, 0.01, system.Q, system.R, system.P0, np.zeros(9))
    with pytest.raises(ValueError, match="solver must be one of gauss-newton, ipopt"):
        MHE(params, solver="newton")
    with pytest.raises(ValueError, match="max_iter"):
        MHE(params, max_iter=0)


def test_the_quadrotor_observer_batch_solve_equals_the_kalman_rts_smoother():
    """The pre-training observer solves the smoothing problem in one block-tridiagonal solve; the RTS
    smoother (filterpy) computes the same means recursively."""
    from learnest.estimators.observers import observe_quadrotor
    system = make_system("quadrotor")
    run = system.simulate(2, n_samples=400)
    model = HybridModel(system, "prior")
    x0 = np.concatenate([run.y[0, :3], np.zeros(3), run.y[0, 3:]])
    rts = run_kf(EstimatorParams(model, system.dt, system.Q, system.R, system.P0, x0), run.y, smooth=True).means
    ours = observe_quadrotor(system, run.y, run.u, system.dt)
    np.testing.assert_allclose(ours, rts, rtol=0, atol=1e-9 * np.abs(rts).max())
    assert np.abs(ours - run.x).mean() < np.abs(run.y[:, 3:] - run.x[:, 6:]).mean()  # it does smooth


def test_a_window_gauss_newton_cannot_solve_is_solved_by_ipopt():
    """The fallback path, in C (gn.c's recursion hands the window back to Python, one step at a time when
    progress is reported) and in the Python loop: every window reported unconverged goes to IPOPT, from the
    same warm start, arrival weight and data, so the recursion equals the IPOPT solver's."""
    system = make_system("cartpole")
    run = system.simulate(5, n_samples=40)
    model = HybridModel(system, "true")
    gn, _, ipopt = both(model, system, run, 40, horizon=6)
    args = (run.y[:40], run.u[:40], run.x_noisy[0])
    if gn._gn._native is not None:
        gn._gn._native.problem.limit = 0   # no Gauss–Newton iteration: every window unconverged
        steps = []
        np.testing.assert_allclose(gn.run(*args, progress=steps.append).means, ipopt, rtol=0, atol=1e-6)
        assert gn.stats["ipopt_fallbacks"] == 40 and steps == list(range(40))
        gn = MHE(gn.params, horizon=6)
        gn._gn._native = None               # the Python loop
    gn._gn._solve = lambda X, *args: (X, False)   # Gauss–Newton "fails" on every window
    fallback = gn.run(*args).means
    np.testing.assert_allclose(fallback, ipopt, rtol=0, atol=1e-6)
    assert gn.stats["ipopt_fallbacks"] == 40


def test_the_compiled_arrival_update_equals_the_numpy_recursion():
    """gn.c's EKF arrival update (and P⁻¹) against `_ekf_update` + inv on a nonlinear model's Jacobians."""
    from learnest.estimators.mhe_gn import _ekf_update

    system = make_system("robot")
    gn = MHE(EstimatorParams(HybridModel(system, "true"), system.dt, system.Q, system.R, system.P0,
                             np.zeros(system.n)))._gn
    if gn._native is None:
        pytest.skip("no C compiler")
    rng = np.random.default_rng(1)
    u = np.ones(system.n_inputs)
    _, F, H = gn._jac2(rng.normal(size=system.n), u, np.zeros(system.n), u)
    A = rng.normal(size=(system.n, system.n))
    P = A @ A.T + np.eye(system.n)
    expected = _ekf_update(F[0], H[0], P, system.Q, system.R)
    P_inv = np.zeros_like(P)
    gn._native.arrival(F[0], H[0], P, P_inv)
    np.testing.assert_allclose(P, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    np.testing.assert_allclose(P_inv @ P, np.eye(system.n), atol=1e-10)

    # an indefinite P (what rounding can leave after many updates): Cholesky refuses S and the new P, and the
    # C update goes on by LU, as numpy's solve and inv do, instead of ending the evaluation
    P = -(A @ A.T + np.eye(system.n))
    expected = _ekf_update(F[0], H[0], P, system.Q, system.R)
    assert np.linalg.eigvalsh(H[0] @ P @ H[0].T + system.R).min() < 0 and np.linalg.eigvalsh(expected).min() < 0
    gn._native.arrival(F[0], H[0], P, P_inv)
    np.testing.assert_allclose(P, expected, rtol=1e-10, atol=1e-10 * np.abs(expected).max())
    np.testing.assert_allclose(P_inv, np.linalg.inv(expected), rtol=1e-8, atol=1e-8 * np.abs(P_inv).max())
