"""Core speed, side by side in one run (ratios of medians; the machine is noisy).

(a) our batched UKF per step vs filterpy's UKF calling the same KNODE once per sigma point;
(b) our MHE per step (built once, warm-started) at N = 20 vs a plain CasADi/IPOPT formulation rebuilt
    every step without warm start;
(c) KNODE training time for the paper's cartpole setting (5000 samples, 250 epochs).

Run:  .venv/bin/python benchmarks/bench_core.py   (writes benchmarks/results/core_speed.{json,md})
"""
from __future__ import annotations

import json
import platform
import statistics
import time
from pathlib import Path

import casadi as ca
import numpy as np
import torch
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from learnest.estimators.mhe import MHE
from learnest.estimators.observers import pretraining_observer
from learnest.estimators.params import EstimatorParams
from learnest.estimators.ukf import run_ukf
from learnest.models.systems import make_system
from learnest.models.training import TrainingConfig, train_knode

OUT = Path(__file__).parent / "results"


def ukf_means(model, y, u, dt, Q, R, x0, P0):
    return run_ukf(EstimatorParams(model, dt, Q, R, P0, x0), y, u).means


def timed(fn, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times), result


def timed_side_by_side(fn_a, fn_b, repeats):
    """Medians of a and b run alternately, so a slow spell of a shared machine hits both alike."""
    times, results = ([], []), [None, None]
    for _ in range(repeats):
        for i, fn in enumerate((fn_a, fn_b)):
            start = time.perf_counter()
            results[i] = fn()
            times[i].append(time.perf_counter() - start)
    return statistics.median(times[0]), statistics.median(times[1]), *results


def plain_filterpy_ukf(model, y, u, dt, Q, R, x0, P0):
    """Textbook filterpy usage: fx and hx called once per sigma point."""
    points = MerweScaledSigmaPoints(model.n, alpha=1e-3, beta=2.0, kappa=0.0)
    ukf = UnscentedKalmanFilter(model.n, y.shape[1], dt, hx=lambda x, u: model.h(x[None], u[None])[0],
                                fx=lambda x, dt, u: model.step(x[None], u[None], dt)[0], points=points)
    ukf.x, ukf.P, ukf.Q, ukf.R = x0.copy(), P0.copy(), Q, R
    ukf.sigmas_f = points.sigma_points(ukf.x, ukf.P)
    out = np.empty((len(y), model.n))
    for k in range(len(y)):
        if k:
            ukf.predict(u=u[k - 1])
        ukf.update(y[k], u=u[k])
        out[k] = ukf.x
    return out


def plain_mhe(model, y, u, dt, Q, R, P0, x0, horizon):
    """Eq. (2) written the direct way: a new Opti problem per step, IPOPT from a cold start."""
    estimates, x_bar = [], x0
    Q_inv, R_inv, P_inv = (np.linalg.inv(M) for M in (Q, R, P0))
    for k in range(len(y)):
        start = max(0, k - horizon)
        opti = ca.Opti()
        X = opti.variable(model.n, k - start + 1)
        cost = ca.bilin(P_inv, X[:, 0] - x_bar, X[:, 0] - x_bar)
        for i in range(k - start + 1):
            v = y[start + i] - model.h(X[:, i], u[start + i])
            cost += ca.bilin(R_inv, v, v)
            if i < k - start:
                w = X[:, i + 1] - model.step(X[:, i], u[start + i], dt)
                cost += ca.bilin(Q_inv, w, w)
        opti.minimize(cost)
        opti.solver("ipopt", {"print_time": False}, {"print_level": 0, "sb": "yes"})
        sol = opti.solve()
        X_opt = np.atleast_2d(sol.value(X)).reshape(model.n, -1)
        estimates.append(X_opt[:, -1])
        if k >= horizon:
            x_bar = X_opt[:, 1]
    return np.array(estimates)


def main():
    torch.set_num_threads(1)
    system = make_system("cartpole")
    train, test = system.simulate(10_000), system.simulate(20_000)
    zeta = pretraining_observer(system, train.y, train.u, system.dt)
    config = TrainingConfig(hidden=8, epochs=250, lr=2e-2)
    train_s, result = timed(lambda: train_knode(system, zeta, train.u, system.dt, config), 3)
    model = result.model
    args = (model, test.y[:1000], test.u[:1000], system.dt, system.Q, system.R, test.x_noisy[0], system.P0)

    ours_s, plain_s, ours, plain = timed_side_by_side(lambda: ukf_means(*args), lambda: plain_filterpy_ukf(*args), 5)
    ukf_max_diff = float(np.abs(ours - plain).max())
    # the Crazyflie setting: 9 states, 19 sigma points, a 16-unit KNODE
    quad = make_system("quadrotor")
    quad_run = quad.simulate(1)
    quad_zeta = pretraining_observer(quad, quad_run.y, quad_run.u, quad.dt)
    quad_model = train_knode(quad, quad_zeta, quad_run.u, quad.dt, TrainingConfig(hidden=16, epochs=50)).model
    quad_args = (quad_model, quad_run.y, quad_run.u, quad.dt, quad.Q, quad.R, quad_run.x_noisy[0], quad.P0)
    quad_ours_s, quad_plain_s, quad_ours, quad_plain = timed_side_by_side(
        lambda: ukf_means(*quad_args), lambda: plain_filterpy_ukf(*quad_args), 5)
    quad_steps = len(quad_run.y)

    steps = 200
    mhe_args = (test.y[:steps], test.u[:steps], test.x_noisy[0])
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, test.x_noisy[0])
    build_s, estimator = timed(lambda: MHE(params, horizon=20, arrival="fixed"), 1)
    estimator.run(*mhe_args)  # build every growing-horizon window once, as a long run does
    mhe_s, mhe_est = timed(lambda: estimator.run(*mhe_args).means, 3)
    plain_mhe_s, plain_est = timed(lambda: plain_mhe(model, *mhe_args[:2], system.dt, system.Q, system.R,
                                                     system.P0, mhe_args[2], 20), 1)
    report = {
        "machine": {"platform": platform.platform(), "processor": platform.processor() or platform.machine(),
                    "cpus": __import__("os").cpu_count(), "torch_threads": torch.get_num_threads()},
        "ukf": {"steps": 1000, "ours_ms_per_step": 1e3 * ours_s / 1000, "filterpy_per_point_ms_per_step":
                1e3 * plain_s / 1000, "speedup": plain_s / ours_s, "max_abs_difference": ukf_max_diff},
        "ukf_quadrotor": {"steps": quad_steps, "ours_ms_per_step": 1e3 * quad_ours_s / quad_steps,
                          "filterpy_per_point_ms_per_step": 1e3 * quad_plain_s / quad_steps,
                          "speedup": quad_plain_s / quad_ours_s,
                          "max_abs_difference": float(np.abs(quad_ours - quad_plain).max())},
        "mhe": {"horizon": 20, "steps": steps, "ours_ms_per_step": 1e3 * mhe_s / steps,
                "plain_rebuilt_cold_ms_per_step": 1e3 * plain_mhe_s / steps, "speedup": plain_mhe_s / mhe_s,
                "build_once_s": build_s, "max_abs_difference": float(np.abs(mhe_est - plain_est).max())},
        "training": {"samples": 5000, "epochs": 250, "hidden": 8, "median_s": train_s, "target_s": 3.0},
    }
    OUT.mkdir(exist_ok=True)
    (OUT / "core_speed.json").write_text(json.dumps(report, indent=2))
    md = [
        "# Core speed (benchmarks/bench_core.py)", "",
        f"Machine: {report['machine']}", "",
        "| what | ours | baseline | ratio | target |", "|---|---|---|---|---|",
        f"| UKF ms/step (KNODE cartpole) | {report['ukf']['ours_ms_per_step']:.3f} | "
        f"{report['ukf']['filterpy_per_point_ms_per_step']:.3f} (filterpy, one call per sigma point) | "
        f"{report['ukf']['speedup']:.1f}x | >= 10x |",
        f"| UKF ms/step (KNODE quadrotor, 9 states, 16 hidden) | {report['ukf_quadrotor']['ours_ms_per_step']:.3f} | "
        f"{report['ukf_quadrotor']['filterpy_per_point_ms_per_step']:.3f} (filterpy, one call per sigma point) | "
        f"{report['ukf_quadrotor']['speedup']:.1f}x | >= 10x |",
        f"| MHE ms/step, N=20 (KNODE cartpole) | {report['mhe']['ours_ms_per_step']:.2f} | "
        f"{report['mhe']['plain_rebuilt_cold_ms_per_step']:.2f} (Opti rebuilt each step, cold start) | "
        f"{report['mhe']['speedup']:.1f}x | >= 3x |",
        f"| KNODE training, 5000 samples x 250 epochs | {train_s:.2f} s | paper: 3 s (Intel i5) | | <= 3 s |",
        "", f"Same answers: UKF max |diff| {ukf_max_diff:.2e}; MHE max |diff| "
        f"{report['mhe']['max_abs_difference']:.2e} (both arrival costs from the previous solution, fixed P0).",
        "", "Batching saves at most 2n+1 model calls per step, each about as dear as the 2n+1-row call: the",
        "cartpole's 9 sigma points cap its UKF ratio near 9x, the quadrotor's 19 do not (docs/results/speed.md).",
    ]
    (OUT / "core_speed.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
