"""Pooled training speed: one Crazyflie-prior KNODE on the 16 shared NanoBench circles and figure-eights that pass
the quality checks (`../shared/data/nanobench`; the 17th fails and is left out), 150 epochs, one in five flights
held out whole, the residual's scale chosen by holding out each trajectory family in turn (the default of every
training surface, `estimators.group_training`: two inner pooled trainings, the UKF in the held-out family's mocap
gaps at each candidate scale, then the final training).  The target is under 2 minutes on a 2-core machine.

Two measurements, each in a fresh process so one-time imports count:

  library   `learnest.read_flights` of the folder, then `workflows.flights.train_on_flights` (the
            pre-training observer on each flight, the thrust gains, the vehicle check, the epochs, the scale
            choice)
  cli       `learnest train ../shared/data/nanobench --system crazyflie --name bench --json` into an empty
            LEARNEST_HOME: the whole command, storing the 17 flights and the model included

Each measurement also records a hash of the model's weights and of its scale choice's table (the inner trainings'
validation flights and kept epochs, every inner gap gain): ``same_model`` says whether both surfaces trained the
same model from the same flights and settings.

The epochs are one batched RK4 over every training flight's one-step pairs (`train_knode_pooled`), not a loop
over flights.  The machine's load average is recorded next to the times: other work shares its two cores.

    .venv/bin/python benchmarks/bench_pooled_training.py [--folder ../shared/data/nanobench] [--runs 1]
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

LIBRARY = r"""
import json, sys, time
started = time.perf_counter()
from learnest.ingest import read_flights
from learnest.models.presets import CRAZYFLIE_TRAINING
from learnest.workflows.flights import train_on_flights
from pathlib import Path
flights = [f for f in read_flights(sorted(Path(sys.argv[1]).glob("*.csv"))) if f.quality["ok"]]
read = time.perf_counter()
result = train_on_flights(flights, CRAZYFLIE_TRAINING, system="crazyflie")
done = time.perf_counter()
meta = result.model.meta
print(json.dumps({"flights": len(flights), "read_s": read - started, "train_s": done - read,
                  "epochs_s": result.seconds, "total_s": done - started,
                  "pairs": sum(f["samples"] - 1 for f in meta["training_flights"]),
                  "training_flights": [f["name"] for f in meta["training_flights"]],
                  "validation_flights": [f["name"] for f in meta["validation_flights"]],
                  "best_epoch": meta["best_epoch"], "learned": meta["learned"],
                  "prior_validation_loss": meta["prior_validation_loss"],
                  "best_validation_loss": meta["best_validation_loss"],
                  "first_validation_loss": result.validation_losses[0], "final_loss": result.losses[-1],
                  "residual_scale": meta["residual_scale"], "residual_scale_groups": meta["residual_scale_groups"],
                  "residual_scale_note": meta["residual_scale_note"],
                  "choice_s": (meta.get("residual_scale_choice") or {}).get("seconds"),
                  **fingerprint(result.model)}))
"""

# What identifies a trained model beside its scale: a hash of its weights and of the scale choice's table (the
# inner trainings' validation flights and kept epochs, every inner gap gain).  Run in each measured process
# after the clock stops; the CLI's model is read back from its registry.
FINGERPRINT = r"""
import hashlib, json
def fingerprint(model):
    weights = hashlib.sha256()
    for weight, bias in model.residual.layers:
        weights.update(weight.tobytes()); weights.update(bias.tobytes())
    choice = model.meta.get("residual_scale_choice") or {}
    table = {k: choice.get(k) for k in ("inner_trainings", "scales")}
    return {"weights_sha256": weights.hexdigest()[:16], "inner_trainings": choice.get("inner_trainings"),
            "choice_sha256": hashlib.sha256(json.dumps(table, sort_keys=True).encode()).hexdigest()[:16]}
"""
LIBRARY = FINGERPRINT + LIBRARY
STORED = FINGERPRINT + r"""
from learnest.service.storage.registry import load_model_ref
print(json.dumps(fingerprint(load_model_ref("bench:1"))))
"""


def library_run(folder: Path) -> dict:
    load = os.getloadavg()[0]
    out = subprocess.run([sys.executable, "-c", LIBRARY, str(folder.resolve())], capture_output=True, text=True,
                         check=True, cwd="/")
    return {**json.loads(out.stdout.strip().splitlines()[-1]), "load_before": load, "load_after": os.getloadavg()[0]}


def cli_run(folder: Path) -> dict:
    learnest = Path(sys.executable).with_name("learnest")
    with tempfile.TemporaryDirectory() as home:
        env = {**os.environ, "LEARNEST_HOME": home}
        for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK"):
            env.pop(name, None)
        load = os.getloadavg()[0]
        started = time.perf_counter()
        out = subprocess.run([str(learnest), "train", str(folder.resolve()), "--system", "crazyflie", "--name",
                              "bench", "--json"], capture_output=True, text=True, check=True, env=env)
        wall = time.perf_counter() - started
        stored = subprocess.run([sys.executable, "-c", STORED], capture_output=True, text=True, check=True, env=env)
    report = json.loads(out.stdout)
    return {"wall_s": wall, "epochs_s": report["seconds"], "job_s": report["total_seconds"],
            "training_flights": len(report["training_flights"]), "validation_flights": report["validation_flights"],
            "skipped_flights": report["skipped_flights"], "learned": report["learned"],
            "best_epoch": report["best_epoch"], "residual_scale": report["residual_scale"],
            "residual_scale_groups": report["residual_scale_groups"],
            "residual_scale_note": report["residual_scale_note"], "load_before": load,
            "load_after": os.getloadavg()[0], **json.loads(stored.stdout.strip().splitlines()[-1])}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--folder", type=Path, default=Path("../shared/data/nanobench"))
    parser.add_argument("--runs", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/pooled_training.json"))
    args = parser.parse_args(argv)
    library = [library_run(args.folder) for _ in range(args.runs)]
    cli = [cli_run(args.folder) for _ in range(args.runs)]
    summary = {"command": "benchmarks/bench_pooled_training.py " + " ".join(argv or sys.argv[1:]),
               "machine": {"cpus": os.cpu_count(), "python": platform.python_version()},
               "library": library, "cli": cli,
               "library_total_s_median": statistics.median(r["total_s"] for r in library),
               "cli_wall_s_median": statistics.median(r["wall_s"] for r in cli), "target_s": 120.0,
               # the same flights and settings give the same model on both surfaces (weights and choice table)
               "same_model": len({(r["weights_sha256"], r["choice_sha256"]) for r in library + cli}) == 1}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
