"""What the Crazyflie KNODE's residual may read across trajectory families: Δθ with and without the acceleration
state among its inputs, trained on one circle (or one figure-eight) of the real NanoBench flights with seeds
0-4, scored with UKF / KNODE-UKF on every flight of the other family; and the five seeds' networks averaged
into one (a wider network whose output is their mean), to tell a seed's luck from what the inputs allow; then,
on seed 0, the screen that located the cause (longer training; blind to other inputs instead).

Same training flights and settings as benchmarks/crazyflie_transfer.py (workflows.flights.
train_on_flight with the Crazyflie prior, CRAZYFLIE_TRAINING); only the residual's blind inputs differ.

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/crazyflie_residual_inputs.py [--seeds 5] [--out benchmarks/results/crazyflie_transfer]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from learnest.ingest import read_flights
from learnest.models import systems
from learnest.models.knode import HybridModel, Residual
from learnest.models.presets import CRAZYFLIE_TRAINING
from learnest.workflows.flights import evaluate_flights, train_on_flight

DATA = Path("../shared/data/nanobench")
TRAIN = {"circle": "B2_circle_medium_rep2", "figure8": "B3_figure8_medium_rep2"}
OTHER = {"circle": "figure8", "figure8": "circle"}
BLIND_TO_XY = ("px", "py")
BLIND_TO_A = ("px", "py", "ax", "ay", "az")
# (label, blind inputs, seeds, epochs): the two residuals compared over seeds, then the screen that located
# the cause on seed 0 (longer training of the residual that reads a; blind to other inputs instead of a)
RUNS = [("sees a (blind to x, y)", BLIND_TO_XY, None, None),
        ("blind to a (package default)", BLIND_TO_A, None, None),
        ("sees a, 500 epochs", BLIND_TO_XY, 1, 500),
        ("sees a, 1500 epochs", BLIND_TO_XY, 1, 1500),
        ("blind to v instead", ("px", "py", "vx", "vy", "vz"), 1, None),
        ("blind to the attitude instead", ("px", "py", "qx", "qy", "qz", "qw"), 1, None),
        ("blind to the height instead", ("px", "py", "pz"), 1, None),
        ("blind to a, 500 epochs", BLIND_TO_A, 1, 500)]


def with_blind(blind: tuple):
    """`System.residual_masks` for the Crazyflie prior with ``blind`` as its blind inputs."""
    original = systems.System.residual_masks

    def masks(self):
        return original(replace(self, residual_blind=blind) if self.name == "crazyflie" else self)
    return masks


def averaged(models: list[HybridModel]) -> HybridModel:
    """One network whose output is the mean of ``models``' residuals: hidden layers stacked, output /K."""
    k = len(models)
    layers = [m.residual.layers for m in models]
    hidden = (np.vstack([lay[0][0] for lay in layers]), np.concatenate([lay[0][1] for lay in layers]))
    output = (np.hstack([lay[1][0] for lay in layers]) / k, np.mean([lay[1][1] for lay in layers], axis=0))
    return HybridModel(models[0].system, "knode", Residual([hidden, output]), dict(models[0].meta))


def gains(model: HybridModel, flights: list) -> dict:
    """Per scored flight, KNODE-UKF's MSE gain over the UKF with the same prior (%)."""
    report = evaluate_flights(model, flights, ["ukf", "knode-ukf"])
    return {e["flight"]: 100.0 * (1.0 - e["mse"]["knode-ukf"] / e["mse"]["ukf"])
            for e in report["flights"] if not e["excluded"]}


def markdown(result: dict) -> str:
    lines = ["# What the Crazyflie residual reads: with and without the acceleration state (real NanoBench flights)",
             "", f"Command: `{result['command']}`  ({result['seconds']:.0f} s wall, 2 shared cores)", "",
             "KNODE-UKF's MSE gain over the UKF with the same (Crazyflie) prior, per flight of the other family. "
             "`avg` is the seeds' networks averaged into one.", ""]
    for direction, by_mask in result["runs"].items():
        names = list(next(iter(next(iter(by_mask.values())).values())))
        lines += [f"## {direction}", "", "| residual | seed | flights worse | median gain | "
                  + " | ".join(n.replace("B2_", "").replace("B3_", "") for n in names) + " |",
                  "|---" * (4 + len(names)) + "|"]
        for mask, by_seed in by_mask.items():
            for seed, per in by_seed.items():
                values = [per[n] for n in names]
                lines.append(f"| {mask} | {seed} | {sum(v < 0 for v in values)}/{len(values)} | "
                             f"{np.median(values):+.2f} % | " + " | ".join(f"{v:+.1f}" for v in values) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/crazyflie_transfer"))
    parser.add_argument("--seeds", type=int, default=5)
    args = parser.parse_args(argv)
    started = time.perf_counter()
    flights = read_flights(sorted(args.data.glob("B*.csv")))
    if not flights:
        sys.exit(f"no NanoBench flights under {args.data}")
    by_name = {f.name: f for f in flights}
    original = systems.System.residual_masks
    runs: dict = {}
    for family, train in TRAIN.items():
        direction = f"trained on {train}, scored on the {OTHER[family]}s"
        test = [f for f in flights if OTHER[family] in f.name]
        runs[direction] = {}
        for mask, blind, seeds, epochs in RUNS:
            config = replace(CRAZYFLIE_TRAINING, epochs=epochs or CRAZYFLIE_TRAINING.epochs)
            systems.System.residual_masks = with_blind(blind)
            try:
                models = [train_on_flight(by_name[train], replace(config, seed=s), system="crazyflie").model
                          for s in range(seeds or args.seeds)]
                per_seed = {str(s): gains(m, test) for s, m in enumerate(models)}
                if len(models) > 1:
                    per_seed["avg"] = gains(averaged(models), test)
            finally:
                systems.System.residual_masks = original
            runs[direction][mask] = per_seed
            print(f"{direction} / {mask}: worse per seed "
                  f"{[sum(v < 0 for v in g.values()) for g in per_seed.values()]}", file=sys.stderr, flush=True)
    result = {"command": "python benchmarks/crazyflie_residual_inputs.py " + " ".join(argv or sys.argv[1:]),
              "runs": runs, "seconds": time.perf_counter() - started}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "residual_inputs.json").write_text(json.dumps(result, indent=1))
    (args.out / "residual_inputs.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
