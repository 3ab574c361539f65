"""How strong a weight prior should the cartpole's joint fit have?  λ chosen on seeds that Table I does not use.

Usage (from the repository root, with the package installed; ~10 min on two idle cores):

    .venv/bin/python benchmarks/joint_weight_prior.py --seeds 15 16 17 18 19 --priors 0 1 3 10 30 --workers 2

For each seed the Table I protocol runs (train on the simulated run 10000 + s, score on 20000 + s) with the joint
fit of `estimators.joint_training` at each λ, and the evaluation run's KNODE-MHE and KNODE-UKF MSE are printed beside
MHE (true dynamics) and UKF (prior).  Writes `results/joint_weight_prior.json` and `.md`.
"""
from __future__ import annotations

import argparse
import json
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

from learnest.estimators.joint_training import train_jointly
from learnest.estimators.mhe import MHE
from learnest.estimators.observers import pretraining_observer
from learnest.estimators.params import EstimatorParams
from learnest.estimators.ukf import run_ukf
from learnest.models.knode import HybridModel
from learnest.models.presets import MHE_HORIZON, PAPER_TRAINING, TrainingConfig
from learnest.models.systems import make_system

RESULTS = Path(__file__).parent / "results"


def _mse(system, model, test, estimator: str) -> float:
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, test.x_noisy[0])
    if estimator == "UKF":
        xh = run_ukf(params, test.y, test.u).means
    else:
        xh = MHE(params, horizon=MHE_HORIZON).run(test.y, test.u).means
    return float(np.mean((xh - test.x) ** 2))


def run_seed(seed: int, priors: list[float]) -> list[dict]:
    """One row per λ for one seed: the evaluation run's MSEs, the LM iterations taken and the training time."""
    system = make_system("cartpole")
    train, test = system.simulate(10_000 + seed), system.simulate(20_000 + seed)
    zeta = pretraining_observer(system, train.y, train.u, system.dt)
    config = TrainingConfig(**{**PAPER_TRAINING["cartpole"].as_dict(), "seed": seed})
    reference = {"MHE (true dynamics)": _mse(system, HybridModel(system, "true"), test, "MHE"),
                 "UKF": _mse(system, HybridModel(system, "prior"), test, "UKF")}
    rows = []
    for prior in priors:
        started = time.perf_counter()
        model = train_jointly(system, train.y, train.u, system.dt, zeta, config, weight_prior=prior).model
        row = {"seed": seed, "weight_prior": prior, "training_s": time.perf_counter() - started,
               "iterations": model.meta["training"]["joint_iterations"],
               "KNODE-MHE": _mse(system, model, test, "MHE"), "KNODE-UKF": _mse(system, model, test, "UKF"),
               **reference}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[15, 16, 17, 18, 19])
    parser.add_argument("--priors", type=float, nargs="+", default=[0.0, 1.0, 3.0, 10.0, 30.0])
    parser.add_argument("--workers", type=int, default=1, help="seeds run in this many processes")
    args = parser.parse_args()
    with ProcessPoolExecutor(max(1, args.workers)) as pool:
        rows = [row for per_seed in pool.map(run_seed, args.seeds, [args.priors] * len(args.seeds))
                for row in per_seed]
    lines = ["# Weight prior of the cartpole's joint fit (`benchmarks/joint_weight_prior.py`)", "",
             "MSE × 1e-3 on each seed's evaluation run; seeds outside Table I's 0-14.", "",
             "| seed | λ | KNODE-MHE | MHE (true) | KNODE-MHE / MHE (true) | KNODE-UKF | UKF | UKF / KNODE-UKF "
             "| LM iterations | training s |", "|---" * 10 + "|"]
    for r in rows:
        lines.append(f"| {r['seed']} | {r['weight_prior']:g} | {r['KNODE-MHE'] * 1e3:.3f} | "
                     f"{r['MHE (true dynamics)'] * 1e3:.3f} | {r['KNODE-MHE'] / r['MHE (true dynamics)']:.2f} | "
                     f"{r['KNODE-UKF'] * 1e3:.3f} | {r['UKF'] * 1e3:.1f} | {r['UKF'] / r['KNODE-UKF']:.1f} | "
                     f"{r['iterations']} | {r['training_s']:.0f} |")
    lines += ["", "Means over the seeds:", "", "| λ | KNODE-MHE | KNODE-UKF | KNODE-MHE / MHE (true), ratio of means "
              "| UKF / KNODE-UKF, ratio of means |", "|---|---|---|---|---|"]
    for prior in args.priors:
        mine = [r for r in rows if r["weight_prior"] == prior]
        mean = {k: np.mean([r[k] for r in mine]) for k in ("KNODE-MHE", "KNODE-UKF", "MHE (true dynamics)", "UKF")}
        lines.append(f"| {prior:g} | {mean['KNODE-MHE'] * 1e3:.3f} | {mean['KNODE-UKF'] * 1e3:.3f} | "
                     f"{mean['KNODE-MHE'] / mean['MHE (true dynamics)']:.2f} | {mean['UKF'] / mean['KNODE-UKF']:.1f} |")
    (RESULTS / "joint_weight_prior.json").write_text(json.dumps(rows, indent=1))
    (RESULTS / "joint_weight_prior.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
