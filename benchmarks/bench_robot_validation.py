"""Which held-out block keeps the robot's KNODE from learning the observer's artefacts?

For each seed, trains the partial-state robot KNODE (Table I settings) with the held-out 20 % of the
record as one tail block or as two spread blocks, and scores KNODE-UKF on a separate evaluation run.
Seeds 15-29 are fresh: Table I uses 0-14, so the choice is not made on the seeds it is reported on.

Run:  .venv/bin/python benchmarks/bench_robot_validation.py tail 15-29 \
          > benchmarks/results/robot_validation_layout_tail_seeds15-29.jsonl
      (and `spread`); each line: layout, seed, KNODE-UKF MSE x1e-3, residual error vs the true drag, best epoch.
"""
from __future__ import annotations

import json
import sys
import time

import numpy as np
import torch

from learnest.estimators.observers import pretraining_observer
from learnest.estimators.prepared import model_params
from learnest.estimators.ukf import run_ukf
from learnest.models.presets import PAPER_TRAINING as TRAINING
from learnest.models.systems import make_system
from learnest.models.training import TrainingConfig, train_knode


def score(layout: str, seed: int) -> dict:
    system = make_system("robot")
    train, test = system.simulate(10_000 + seed), system.simulate(20_000 + seed)
    zeta = pretraining_observer(system, train.y, train.u, system.dt)
    config = TrainingConfig(**{**TRAINING["robot"].as_dict(), "seed": seed, "validation_layout": layout})
    started = time.perf_counter()
    model = train_knode(system, zeta, train.u, system.dt, config).model
    xh = run_ukf(model_params(model, test.x_noisy[0]), test.y, test.u).means
    learned = model.residual(test.x, test.u)
    true = system.f_true(test.x, test.u) - system.f_prior(test.x, test.u)
    return {"variant": layout, "seed": seed, "knode_ukf_mse_e3": round(1e3 * float(np.mean((xh - test.x) ** 2)), 3),
            "residual_rel_err": round(float(np.linalg.norm(learned - true) / np.linalg.norm(true)), 3),
            "best_epoch": model.meta["best_epoch"], "train_s": round(time.perf_counter() - started)}


def main():
    torch.set_num_threads(1)
    layout, (first, last) = sys.argv[1], map(int, sys.argv[2].split("-"))
    for seed in range(first, last + 1):
        print(json.dumps(score(layout, seed)), flush=True)


if __name__ == "__main__":
    main()
