"""Ingest speed and memory, and evaluation time per step for each method.

- ingest of a ~33-s real NanoBench flight (the longest in ../shared/data; 40 s of CSV rows with take-off and landing)
- ingest of a synthetic 60-s uSD log at 500 Hz (the real uSD files are 15 s at 250 Hz)
- time per step of UKF, MHE, KNODE-UKF, KNODE-MHE on one real flight
Peak memory is tracemalloc's peak (numpy allocations included).  Medians over repeats.

Run:  .venv/bin/python benchmarks/bench_ingest.py   (writes benchmarks/results/ingest_speed.{json,md})
"""
from __future__ import annotations

import json
import platform
import statistics
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np
import torch

from learnest.ingest import read_flights
from learnest.ingest.formats.crazyflie_usd.writer import write as write_usd
from learnest.models.presets import TrainingConfig
from learnest.workflows.flights import evaluate_flight, train_on_flight

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
OUT = Path(__file__).parent / "results"


def measure(fn, repeats=5):
    times, peaks = [], []
    for _ in range(repeats):
        tracemalloc.start()
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
        peaks.append(tracemalloc.get_traced_memory()[1])
        tracemalloc.stop()
    return statistics.median(times), max(peaks)


def synthetic_usd(path: Path, seconds=60.0, rate=500.0):
    """A 500 Hz fixed-frequency stream with acc (g) and locSrv sample-and-hold at 100 Hz, a 1 m circle."""
    t = np.arange(int(seconds * rate)) / rate
    held = np.floor(t * 100) / 100
    w = 1.0
    z = np.where(t < 2, 0.0, 1.0)
    acc = np.column_stack([0.01 * np.sin(t), 0.01 * np.cos(t), np.ones_like(t)])
    variables = {"acc.x": ("f", acc[:, 0]), "acc.y": ("f", acc[:, 1]), "acc.z": ("f", acc[:, 2]),
                 "locSrv.x": ("f", np.cos(w * held)), "locSrv.y": ("f", np.sin(w * held)), "locSrv.z": ("f", z),
                 "locSrv.qx": ("f", 0 * t), "locSrv.qy": ("f", 0 * t), "locSrv.qz": ("f", 0 * t),
                 "locSrv.qw": ("f", 1 + 0 * t)}
    write_usd(path, {"fixedFrequency": {"t": t, "vars": variables}})


def main():
    torch.set_num_threads(1)
    report = {"machine": {"platform": platform.platform(), "cpus": __import__("os").cpu_count()}}
    nanobench = DATA / "nanobench" / "B3_figure8_fast_rep2.csv"
    seconds, peak = measure(lambda: read_flights([nanobench]))
    report["nanobench"] = {"file": nanobench.name, "bytes": nanobench.stat().st_size, "median_s": seconds,
                           "peak_mb": peak / 2**20}
    with tempfile.TemporaryDirectory() as tmp:
        usd = Path(tmp) / "log60s"
        synthetic_usd(usd)
        seconds, peak = measure(lambda: read_flights([usd]))
        report["usd_60s_500hz"] = {"bytes": usd.stat().st_size, "median_s": seconds, "peak_mb": peak / 2**20}
    flights = read_flights([DATA / "nanobench" / "B2_circle_medium_rep2.csv", DATA / "nanobench" / "B2_circle_fast_rep2.csv"])
    model = train_on_flight(flights[0], TrainingConfig(hidden=16, epochs=50, lr=1e-3)).model
    results = evaluate_flight(model, flights[1], ["ukf", "mhe", "knode-ukf", "knode-mhe"])["results"]
    report["evaluation"] = {"flight": flights[1].name, "steps": len(flights[1].t),
                            "ms_per_step": {m: r["ms_per_step"] for m, r in results.items()}}
    OUT.mkdir(exist_ok=True)
    (OUT / "ingest_speed.json").write_text(json.dumps(report, indent=2))
    md = ["# Ingest and evaluation speed (benchmarks/bench_ingest.py)", "", f"Machine: {report['machine']}", "",
          "| input | size | median time | peak memory |", "|---|---|---|---|",
          f"| NanoBench CSV {nanobench.name} | {report['nanobench']['bytes'] / 2**20:.1f} MB | "
          f"{report['nanobench']['median_s'] * 1e3:.0f} ms | {report['nanobench']['peak_mb']:.0f} MB |",
          f"| uSD log, 60 s at 500 Hz (synthetic) | {report['usd_60s_500hz']['bytes'] / 2**20:.1f} MB | "
          f"{report['usd_60s_500hz']['median_s'] * 1e3:.0f} ms | {report['usd_60s_500hz']['peak_mb']:.0f} MB |",
          "", f"Evaluation of {report['evaluation']['flight']} ({report['evaluation']['steps']} steps), ms per step:", "",
          "| method | ms/step |", "|---|---|"]
    md += [f"| {m} | {v:.3f} |" for m, v in report["evaluation"]["ms_per_step"].items()]
    (OUT / "ingest_speed.md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
