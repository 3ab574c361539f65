"""Does the training envelope flag the Table I seeds whose KNODE is worse than its prior?

Usage (from the repository root, with the package installed):

    .venv/bin/python benchmarks/envelope_check.py --task robot > benchmarks/results/envelope_check_robot.md

For each seed the envelope is built exactly as training builds it (the pre-training observer's estimates
and the inputs of the training run, seed 10000 + s) and the evaluation run (seed 20000 + s) is judged
against it; no network is trained (the envelope does not depend on it).  The committed Table I results
(benchmarks/results/table1_<task>.json) give each seed's KNODE-UKF and UKF MSE to compare with.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from learnest.estimators.observers import pretraining_observer
from learnest.models.envelope import MARGIN, THRESHOLD, envelope_report, training_envelope
from learnest.models.systems import make_system


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=("cartpole", "robot"), required=True)
    parser.add_argument("--seeds", type=int, default=15)
    args = parser.parse_args()
    table = json.loads((Path(__file__).parent / "results" / f"table1_{args.task}.json").read_text())
    mse = {s["seed"]: s["mse"] for s in table["per_seed"]}
    system = make_system(args.task)
    names = [*system.state_names, *system.input_names]
    print(f"# Training envelope vs Table I, {args.task} (margin {MARGIN:.0%} of the box, threshold {THRESHOLD:.0%})\n")
    print("| seed | KNODE-UKF (1e-3) | UKF (1e-3) | KNODE-UKF worse | flagged | outside (flagged states) | "
          + " | ".join(names) + " |")
    print("|---" * (6 + len(names)) + "|")
    missed = false_alarms = 0
    for seed in range(args.seeds):
        train, test = system.simulate(10_000 + seed), system.simulate(20_000 + seed)
        envelope = training_envelope(pretraining_observer(system, train.y, train.u, system.dt), train.u, names,
                                     system.invariant_states)
        report = envelope_report(envelope, pretraining_observer(system, test.y, test.u, system.dt), test.u)
        knode, prior = mse[seed]["KNODE-UKF"], mse[seed]["UKF"]
        worse, flagged = knode > prior, report["outside_training_envelope"]
        missed += worse and not flagged
        false_alarms += flagged and not worse
        print(f"| {seed} | {knode * 1e3:.3f} | {prior * 1e3:.3f} | {'yes' if worse else 'no'} | "
              f"{'yes' if flagged else 'no'} | {', '.join(report['states_outside']) or '-'} | "
              + " | ".join(f"{report['per_state'][n]:.3f}" for n in names) + " |", flush=True)
    print(f"\nSeeds where KNODE-UKF is worse than UKF and the envelope does not flag the run: {missed}. "
          f"Flagged seeds where KNODE-UKF still beats UKF: {false_alarms}. "
          f"Invariant (reported, never flagged): {', '.join(system.invariant_states)}.")


if __name__ == "__main__":
    main()
