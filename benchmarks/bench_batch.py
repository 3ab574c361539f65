"""Batch evaluation of the shared NanoBench flights, four methods, on one and two workers and on Dask.

One model (`bench:1`, the Crazyflie preset's 150 epochs on TRAINING_FLIGHT) is evaluated with UKF, KNODE-UKF,
MHE and KNODE-MHE on every other shared NanoBench flight through the service's job code
(`service.jobs.evaluation.start_evaluation`, results cache emptied before each run) on
- the local process pool with 1 worker and with 2 workers,
- a Dask LocalCluster with 2 worker processes (1 thread each).
Before the clock starts the workers are warm (torch, CasADi imported) and the model's compiled C is in the
code cache (one untimed evaluation of one flight), as on a server that has evaluated the model once.  The
three reports must be equal apart from `ms_per_step` (a wall time).  Flights the quality checks exclude are
counted, not scored.

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/bench_batch.py [--repeats 1]   (writes benchmarks/results/batch_speed.{json,md})
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

from bench_service import flight_samples, machine, timed_evaluations, without_timing

from learnest.service.config import Settings
from learnest.service.jobs.executors import DaskExecutor, LocalPoolExecutor
from learnest.service.jobs.training import start_training
from learnest.service.local import add_flight, local_services, wait_for_job

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "nanobench"
OUT = REPO / "benchmarks" / "results"
TRAINING_FLIGHT = "B2_circle_medium_rep2"
METHODS = ("ukf", "knode-ukf", "mhe", "knode-mhe")
COMMAND = ".venv/bin/python benchmarks/bench_batch.py"


def store_and_train(home: Path) -> list[str]:
    """Every shared flight stored under `home`, bench:1 trained on TRAINING_FLIGHT; -> the other flights' names."""
    paths = sorted(DATA.glob("B*.csv"))
    if not paths:
        sys.exit(f"no NanoBench flights under {DATA}")
    with local_services(Settings(home=home, pool_workers=1)) as services:
        rows = {path.stem: add_flight(services, [path])[0] for path in paths}
        job, _ = start_training(services, "bench", rows[TRAINING_FLIGHT].id, {})
        assert wait_for_job(services, job.id).state == "succeeded", "training failed"
    return [name for name in rows if name != TRAINING_FLIGHT]


def estimator_seconds(report: dict, steps: dict[str, int]) -> float:
    """Time the workers spent in the estimators (ms_per_step x steps), summed over the scored flights."""
    return sum(ms * steps[f["flight"]] / 1e3 for f in report["flights"] for ms in f.get("ms_per_step", {}).values())


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=1)
    args = parser.parse_args(argv)
    started = time.perf_counter()
    result = {"command": COMMAND + (f" --repeats {args.repeats}" if args.repeats != 1 else ""),
              "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "machine": machine(),
              "methods": list(METHODS), "training_flight": TRAINING_FLIGHT}
    with tempfile.TemporaryDirectory(prefix="learnest-batch-") as tmp:
        home = Path(tmp) / "home"
        names = store_and_train(home)
        steps = flight_samples(home)
        runs, reports = {}, {}
        for label, make, workers in (("local pool, 1 worker", lambda: LocalPoolExecutor(1), 1),
                                     ("local pool, 2 workers", lambda: LocalPoolExecutor(2), 2),
                                     ("Dask LocalCluster, 2 worker processes",
                                      lambda: DaskExecutor(None, processes=True, n_workers=2, threads_per_worker=1),
                                      2)):
            seconds, report = timed_evaluations(home, make(), workers, names, METHODS, args.repeats,
                                                compile_first=True)
            scored = [f for f in report["flights"] if not f["excluded"]]
            runs[label] = {"workers": workers, "seconds": [round(x, 2) for x in seconds],
                           "best_s": round(min(seconds), 2), "flights_scored": len(scored),
                           "flights_excluded": len(report["flights"]) - len(scored),
                           "flights_per_min": round(60 * len(scored) / min(seconds), 2),
                           "minutes_of_flight_per_min": round(sum(steps[f["flight"]] for f in scored) / 100.0
                                                              / min(seconds), 2),
                           "estimator_s_in_workers": round(estimator_seconds(report, steps), 1)}
            reports[label] = without_timing(report)
            print(f"{label}: {', '.join(f'{x:.1f}' for x in seconds)} s", file=sys.stderr, flush=True)
    first = next(iter(reports.values()))
    result.update(runs=runs, reports_equal=all(r == first for r in reports.values()), median_mse=first["median"],
                  load_average_at_end=[round(x, 2) for x in os.getloadavg()],
                  wall_s=round(time.perf_counter() - started, 1))
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "batch_speed.json").write_text(json.dumps(result, indent=2) + "\n")
    (OUT / "batch_speed.md").write_text(markdown(result))
    print(markdown(result))
    return 0


def markdown(result: dict) -> str:
    m, runs = result["machine"], result["runs"]
    single = runs["local pool, 1 worker"]["best_s"]
    lines = ["# Batch evaluation of the shared NanoBench flights", "",
             f"Command: `{result['command']}` ({result['wall_s']:.0f} s wall, {result['date']}). Machine: {m['cpu']}, "
             f"{m['cpus']} CPUs; load average {m['load_average_at_start']} at the start, "
             f"{result['load_average_at_end']} at the end.", "",
             f"Model: 150 epochs (Crazyflie preset) on {result['training_flight']}; methods "
             f"{', '.join(result['methods'])}; workers warm and the model's compiled code cached before timing.", "",
             "| executor | workers | wall s | flights scored (excluded) | flights/min | minutes of flight per minute "
             "| speed-up vs 1 worker | summed estimator time in the workers (s) |",
             "|---|---|---|---|---|---|---|---|"]
    for label, r in runs.items():
        lines.append(f"| {label} | {r['workers']} | {r['best_s']:.1f} | {r['flights_scored']} "
                     f"({r['flights_excluded']}) | {r['flights_per_min']:.1f} | {r['minutes_of_flight_per_min']:.2f} | "
                     f"{single / r['best_s']:.2f}x | {r['estimator_s_in_workers']:.1f} |")
    lines += ["", "Reports identical across executors (ms_per_step aside): "
              f"{'yes' if result['reports_equal'] else 'NO'}; median MSE "
              + ", ".join(f"{k} {v:.4g}" for k, v in result["median_mse"].items()) + "."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
