"""Training speed: the pre-training observer plus 150 epochs on one real 33-s flight, each run
in a fresh process (so one-time imports count, as they do for a job), side by side:

  baseline   torch.optim.Adam and torch's default intra-op threads (the training loop before this change)
  current    `models.training` as shipped: its bit-identical Adam (no torch._dynamo import on the first
             step) and one intra-op thread

Runs alternate (baseline, current, baseline, ...) so machine load hits both alike; medians are reported.

    .venv/bin/python benchmarks/bench_training.py [--runs 5] [--flight ../shared/data/nanobench/B2_circle_fast_rep2.csv]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

CHILD = r"""
import json, sys, time
started = time.perf_counter()
import torch
import learnest.models.residual_net as residual_net
import learnest.models.training as training
if sys.argv[2] == "baseline":
    residual_net.Adam = torch.optim.Adam
    residual_net.TRAINING_THREADS = torch.get_num_threads()
from learnest.estimators.observers import pretraining_observer
from learnest.ingest import read_flights
from learnest.models.inputs import system_inputs
from learnest.models.presets import CRAZYFLIE_TRAINING
from learnest.estimators.prepared import system_for
flight = read_flights([sys.argv[1]])[0]
imported = time.perf_counter()
system = system_for(flight, "quadrotor")
y, u = flight.measurements(), system_inputs(flight, system)
zeta = pretraining_observer(system, y, u, system.dt)
result = training.train_knode(system, zeta, u, system.dt, CRAZYFLIE_TRAINING)
done = time.perf_counter()
print(json.dumps({"train_s": done - imported, "total_s": done - started, "final_loss": result.losses[-1],
                  "epochs": len(result.losses), "threads_default": torch.get_num_threads()}))
"""

DEFAULT_FLIGHT = Path("../shared/data/nanobench/B2_circle_fast_rep2.csv")


def run(flight: Path, variant: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, str(flight), variant], capture_output=True, text=True,
                         check=True, cwd="/")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--flight", type=Path, default=DEFAULT_FLIGHT)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/training_speed.json"))
    args = parser.parse_args(argv)
    flight = args.flight.resolve()
    runs: dict[str, list[dict]] = {"baseline": [], "current": []}
    for i in range(args.runs):
        for variant in ("baseline", "current"):
            runs[variant].append(run(flight, variant))
            print(f"run {i + 1}/{args.runs} {variant}: {runs[variant][-1]}", flush=True)
    summary = {variant: {key: statistics.median(r[key] for r in rows) for key in ("train_s", "total_s")}
               for variant, rows in runs.items()}
    ratio = summary["baseline"]["train_s"] / summary["current"]["train_s"]
    loss_gap = max(abs(a["final_loss"] - b["final_loss"]) / abs(a["final_loss"])
                   for a, b in zip(runs["baseline"], runs["current"]))
    result = {"flight": flight.name, "runs": runs, "median": summary, "speedup_train": ratio,
              "max_relative_final_loss_difference": loss_gap, "cpu_count": os.cpu_count(),
              "load_average_at_end": os.getloadavg()}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    lines = [f"# Training speed: observer + {runs['current'][0]['epochs']} epochs on {flight.name}", "",
             f"Command: `.venv/bin/python benchmarks/bench_training.py --runs {args.runs}`; each run a fresh "
             f"process, alternating; medians. Machine: {os.cpu_count()} cores, load average at the end "
             f"{os.getloadavg()[0]:.1f}.", "",
             "| variant | training (observer + epochs), s | whole process incl. imports and ingest, s |",
             "|---|---|---|"]
    for variant in ("baseline", "current"):
        lines.append(f"| {variant} | {summary[variant]['train_s']:.2f} | {summary[variant]['total_s']:.2f} |")
    lines += ["", f"Speed-up of training: {ratio:.2f}×. Largest relative difference of the final training loss "
              f"between the two: {loss_gap:.1e} (0 = the same weights).", ""]
    args.out.with_suffix(".md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
