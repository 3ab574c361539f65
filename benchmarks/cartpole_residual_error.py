"""What the cartpole's learned residual gets wrong, row by row, with the paper's masks and with the cartpole's own.

Usage (from the repository root, with the package installed; ~3 min on two idle cores):

    .venv/bin/python benchmarks/cartpole_residual_error.py --seeds 4 14 --workers 2

For each seed the Table I protocol trains the partial-state KNODE (joint fit from the filter's estimates of the
simulated run 10000 + s) twice: with Δθ seeing every state and correcting every derivative (the paper's), and with
`Cartpole`'s masks (accelerations only, blind to the cart's position).  The error is Δθ minus the true residual
f_true − f_prior, RMS per row, along the true states of the training run and of the evaluation run (20000 + s).
The true residual of the p and α rows is 0: whatever Δθ puts there is learned from the estimated states' errors.
Writes `results/cartpole_residual_error.md`.
"""
from __future__ import annotations

import argparse
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np

from learnest.estimators.joint_training import train_jointly
from learnest.estimators.observers import pretraining_observer
from learnest.models.presets import PAPER_TRAINING, TrainingConfig
from learnest.models.systems import make_system

RESULTS = Path(__file__).parent / "results"
MASKS = {"paper (every state, every row)": dict(residual_states=None, residual_blind=()),
         "cartpole (accelerations, blind to p)": {}}


def residual_errors(seed: int) -> list[dict]:
    """RMS of Δθ − (f_true − f_prior) per state row, on the training and evaluation runs, for each mask."""
    rows = []
    for label, masks in MASKS.items():
        system = replace(make_system("cartpole"), **masks)
        train, test = system.simulate(10_000 + seed), system.simulate(20_000 + seed)
        zeta = pretraining_observer(system, train.y, train.u, system.dt)
        config = TrainingConfig(**{**PAPER_TRAINING["cartpole"].as_dict(), "seed": seed})
        residual = train_jointly(system, train.y, train.u, system.dt, zeta, config).model.residual
        for run_name, run in (("training", train), ("evaluation", test)):
            error = residual(run.x, run.u) - (system.f_true(run.x, run.u) - system.f_prior(run.x, run.u))
            rows.append({"seed": seed, "masks": label, "run": run_name,
                         "rms": np.sqrt(np.mean(error**2, axis=0)).tolist()})
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[4, 14])
    parser.add_argument("--workers", type=int, default=1, help="seeds run in this many processes")
    args = parser.parse_args()
    with ProcessPoolExecutor(max(1, args.workers)) as pool:
        results = [row for per_seed in pool.map(residual_errors, args.seeds) for row in per_seed]
    names = make_system("cartpole").state_names
    lines = ["# The cartpole's learned residual, error per row (`benchmarks/cartpole_residual_error.py`)", "",
             "RMS of Δθ − (f_true − f_prior) along the true states; rows p and α are definitions (true residual 0), "
             "rows ṗ and α̇ the accelerations (m/s², rad/s²).", "",
             "| seed | masks | run | " + " | ".join(names) + " |", "|---" * (3 + len(names)) + "|"]
    for r in results:
        lines.append(f"| {r['seed']} | {r['masks']} | {r['run']} | " + " | ".join(f"{v:.3f}" for v in r["rms"]) + " |")
    (RESULTS / "cartpole_residual_error.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
