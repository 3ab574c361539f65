"""How long the learning steps take on the shared real flights: noise identification, pooled training (one residual
and an ensemble of five, side by side), and one flight scored by four estimators with every yardstick.

Noise identification is timed as training runs it (`with_identified_noise`: the process noise only, the
sensors' noise held, the mocap hidden in the yardstick's gaps): the prior alone, then the prior and the KNODE
together, as `learnest train` identifies both for a KNODE; the ensemble's training is timed as `learnest train
--ensemble 5` runs it, its noise identified.

Flights: the NanoBench circles and figure-eights that pass the quality checks (`../shared/data/nanobench`, 16),
Crazyflie prior; the scored flight is a helix (`nanobench-more`).  Wall time of one run each (the steps take
minutes, so a repeat would not fit a session); the machine's load at the start and end is written beside them.

    python benchmarks/learning_speed.py [--out benchmarks/results/learning_speed]
"""
from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import replace
from pathlib import Path

import learnest as le
from learnest.estimators import noise_identification as identification
from learnest.estimators.prepared import system_for
from learnest.models.knode import HybridModel
from learnest.models.presets import CRAZYFLIE_TRAINING
from learnest.workflows.flights import evaluate_flights, train_on_flights

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
METHODS = ("ukf", "knode-ukf", "mhe", "knode-mhe")


def timed(step, results: dict, name: str):
    started = time.perf_counter()
    value = step()
    results[name] = round(time.perf_counter() - started, 1)
    print(f"{name}: {results[name]} s", flush=True)
    return value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/learning_speed"))
    args = parser.parse_args()
    flights = [f for f in le.read_flights(sorted((DATA / "nanobench").glob("*.csv"))) if f.quality["ok"]]
    helix = le.read_flights([sorted((DATA / "nanobench-more").glob("B5_helix*.csv"))[0]])[0]
    results: dict = {"flights": len(flights), "load_before": os.getloadavg()[0]}
    prior = HybridModel(system_for(flights[0], "crazyflie"), "prior")
    timed(lambda: identification.with_identified_noise(prior, flights), results, "noise identification, prior, s")
    one = timed(lambda: train_on_flights(flights, system="crazyflie", group_by="none").model, results,
                "pooled training, one, s")
    timed(lambda: identification.with_identified_noise(one, flights), results,
          "noise identification, prior and KNODE, s")
    model = timed(lambda: train_on_flights(flights, replace(CRAZYFLIE_TRAINING, ensemble=5), system="crazyflie",
                                           group_by="none", noise="identified").model, results,
                  "pooled training, ensemble of 5, noise identified, s")
    evaluate_flights(model, [helix], METHODS)     # compiles the estimators once, as a service's first job does
    timed(lambda: evaluate_flights(model, [helix], METHODS), results, "one flight, 4 methods, every yardstick, s")
    results["load_after"] = os.getloadavg()[0]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "learning_speed.json").write_text(json.dumps(results, indent=1))
    lines = ["# Learning steps on the shared flights: wall time", "",
             f"Command: `python benchmarks/learning_speed.py`; {results['flights']} flights; load average "
             f"{results['load_before']:.1f} before, {results['load_after']:.1f} after (2 cores).", "",
             "| step | seconds |", "|---|---|"]
    lines += [f"| {k[:-3]} | {v} |" for k, v in results.items() if k.endswith(", s")]
    (args.out / "learning_speed.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
