"""What each yardstick says on the real NanoBench flights: mocap gaps, fast reference (with the onboard EKF) and
the paper's SG score, for UKF and MHE with a prior, and for a KNODE trained on one flight.

Per flight and method: the position RMSE inside the mocap gaps (0.5 s hidden every 2.5 s after 5 s), the
velocity RMSE against the 0.05-s derivative of the raw mocap outside the gaps (``onboard``: the vehicle's own
EKF from the log) and the paper's MSE against the 1.5-s Savitzky-Golay references; the medians; and the wall
time of an evaluation with and without the gap runs (the gap runs are one more run per method).

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/yardsticks_nanobench.py [--system crazyflie] [--train B2_circle_medium_rep2]
        [--out benchmarks/results/yardsticks]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from learnest.estimators.prepared import system_for
from learnest.ingest import read_flights
from learnest.models.knode import HybridModel
from learnest.workflows.flights import evaluate_flights, train_on_flight

DATA = Path("../shared/data/nanobench")
METHODS_PRIOR = ["ukf", "mhe", "onboard"]
METHODS_KNODE = ["ukf", "mhe", "knode-ukf", "knode-mhe", "onboard"]


def table(report: dict, methods: list[str]) -> list[dict]:
    """One row per scored flight: gap RMSE (m), fast-reference velocity RMSE (m/s), SG MSE, KNODE gains."""
    rows = []
    for entry in report["flights"]:
        if entry["excluded"]:
            continue
        y = entry["yardsticks"]
        gaps, fast = y["mocap_gaps"], y["fast_reference"]
        rows.append({"flight": entry["flight"], "gaps": gaps["gaps"],
                     "gap_rmse_m": {m: gaps["rmse_m"].get(m) for m in methods if m != "onboard"},
                     "gap_gain_pct": gaps["gain_pct"], "gap_gain_interval_pct": gaps["gain_interval_pct"],
                     "ms_per_step": entry["ms_per_step"], "gap_ms_per_step": gaps["ms_per_step"],
                     "fast_velocity_rmse_m_s": {m: fast["velocity_rmse_m_s"].get(m) for m in methods},
                     "fast_acceleration_rmse_m_s2": {m: fast["acceleration_rmse_m_s2"].get(m) for m in methods},
                     "paper_sg_mse": y["paper_sg"]["mse"]})
    return rows


def medians(rows: list[dict], key: str) -> dict:
    methods = sorted({m for r in rows for m, v in r[key].items() if v is not None})
    return {m: float(np.median([r[key][m] for r in rows if r[key].get(m) is not None])) for m in methods}


def markdown(results: dict) -> str:
    out = [f"# Yardsticks on the NanoBench flights ({results['system']} prior)", "",
           f"Command: `{results['command']}`", "",
           f"Gaps: {results['gap_s']} s hidden every {results['gap_every_s']} s after the first 5 s; fast reference: "
           "0.05-s (velocity) and 0.15-s (acceleration) Savitzky-Golay derivatives of the raw mocap, outside the "
           "gaps; RMSE of the 3-D error.  paper_sg: MSE over [p, v, a] vs the 1.5-s SG references.", ""]
    for label, section in results["runs"].items():
        rows, methods = section["rows"], section["methods"]
        est = [m for m in methods if m != "onboard"]
        out += [f"## {label}", "", f"{len(rows)} flights scored; {section['excluded']} excluded.  Evaluation wall "
                f"time {section['seconds_with_gaps']:.1f} s with the gap runs, {section['seconds_without_gaps']:.1f} s "
                "without (gap_s = 0; on a shared 2-core machine, so only roughly comparable).  Estimator wall time "
                "summed over the flights (ms per step x steps): "
                + ", ".join(f"{m} {section['run_seconds'][m]:.1f} s plain, {section['gap_run_seconds'][m]:.1f} s "
                            "with gaps" for m in section["run_seconds"]) + ".", ""]
        head = "| flight | gaps | " + " | ".join(f"gap {m} (m)" for m in est) + " | " + \
            " | ".join(f"fast v {m} (m/s)" for m in methods) + " | " + " | ".join(f"SG {m} (1e-3)" for m in est) + " |"
        out += [head, "|" + "---|" * (2 + len(est) * 2 + len(methods))]
        for r in rows:
            cells = [r["flight"], str(r["gaps"])]
            cells += [f"{r['gap_rmse_m'][m]:.4f}" if r["gap_rmse_m"].get(m) is not None else "-" for m in est]
            cells += [f"{r['fast_velocity_rmse_m_s'][m]:.4f}" if r["fast_velocity_rmse_m_s"].get(m) is not None
                      else "-" for m in methods]
            cells += [f"{1e3 * r['paper_sg_mse'][m]:.2f}" for m in est]
            out.append("| " + " | ".join(cells) + " |")
        gm, fm, sm = section["median_gap_rmse_m"], section["median_fast_velocity_rmse_m_s"], section["median_paper_sg"]
        out.append("| **median** | | " + " | ".join(f"{gm[m]:.4f}" for m in est) + " | "
                   + " | ".join(f"{fm[m]:.4f}" if m in fm else "-" for m in methods) + " | "
                   + " | ".join(f"{1e3 * sm[m]:.2f}" for m in est) + " |")
        out.append("")
        keys = sorted({k for r in rows for k in r["gap_gain_pct"]})
        if keys:
            out += ["KNODE gain on each yardstick, % (gaps: mean squared gap error, with its 95 % interval; fast: "
                    "mean squared velocity error; SG: the paper's MSE):", "",
                    "| flight | " + " | ".join(f"gaps {k} | fast {k} | SG {k}" for k in keys) + " |",
                    "|" + "---|" * (1 + 3 * len(keys))]
            for r in rows:
                cells = [r["flight"]]
                for k in keys:
                    base = k.split("_vs_")[1]
                    interval = r["gap_gain_interval_pct"].get(k)
                    cells.append(f"{r['gap_gain_pct'][k]:+.1f}" + (f" [{interval[0]:+.1f}, {interval[1]:+.1f}]"
                                                                  if interval else " [too few gaps]"))
                    fast = r["fast_velocity_rmse_m_s"]
                    cells.append(f"{100 * (1 - (fast['knode-' + base] / fast[base]) ** 2):+.1f}")
                    cells.append(f"{100 * (1 - r['paper_sg_mse']['knode-' + base] / r['paper_sg_mse'][base]):+.1f}")
                out.append("| " + " | ".join(cells) + " |")
            out.append("")
        am = section["median_fast_acceleration_rmse_m_s2"]
        out.append("Median acceleration RMSE on the fast reference (m/s²): "
                   + ", ".join(f"{m} {v:.3f}" for m, v in am.items()) + ".")
        head_line = section.get("headline")
        if head_line and head_line["median_gain_pct"]:
            for key, gain in head_line["median_gain_pct"].items():
                out.append(f"Gap headline {key}: median gain {gain:+.1f} %, better on "
                           f"{head_line['flights_better'][key]} of {head_line['flights_with_gaps']}, worse beyond the "
                           "interval on "
                           f"{head_line['flights_worse_beyond_interval'][key]}.")
        out.append("")
    return "\n".join(out)


def run(model: HybridModel, flights, methods: list[str]) -> dict:
    # a warm-up on one flight compiles (or loads) both the plain and the gap-masked functions, so neither
    # timing below holds a compilation
    evaluate_flights(model, [f for f in flights if f.quality["ok"]][:1], methods)
    started = time.perf_counter()
    evaluate_flights(model, flights, [m for m in methods if m != "onboard"], gap_s=0.0)
    without = time.perf_counter() - started
    started = time.perf_counter()
    report = evaluate_flights(model, flights, methods)
    with_gaps = time.perf_counter() - started
    rows = table(report, methods)
    print(f"{len(rows)} flights: {without:.1f} s without gaps, {with_gaps:.1f} s with", flush=True)
    return {"methods": methods, "rows": rows, "excluded": sum(f["excluded"] for f in report["flights"]),
            "seconds_with_gaps": with_gaps, "seconds_without_gaps": without,
            "median_gap_rmse_m": medians(rows, "gap_rmse_m"),
            "median_fast_velocity_rmse_m_s": medians(rows, "fast_velocity_rmse_m_s"),
            "median_fast_acceleration_rmse_m_s2": medians(rows, "fast_acceleration_rmse_m_s2"),
            "median_paper_sg": medians(rows, "paper_sg_mse"), "headline": report["headline"],
            "run_seconds": run_seconds(report, "plain"), "gap_run_seconds": run_seconds(report, "gaps")}


def run_seconds(report: dict, which: str) -> dict:
    """{method: Σ over the scored flights of ms_per_step × steps, s} of the plain or the gap-masked runs."""
    out: dict = {}
    for entry in report["flights"]:
        if entry["excluded"]:
            continue
        steps = entry["yardsticks"]["fast_reference"]["samples"] + \
            entry["yardsticks"]["mocap_gaps"]["gaps"] * round(entry["yardsticks"]["mocap_gaps"]["gap_s"] * 100)
        per_step = entry["ms_per_step"] if which == "plain" else entry["yardsticks"]["mocap_gaps"]["ms_per_step"]
        for method, ms in per_step.items():
            out[method] = out.get(method, 0.0) + ms * steps / 1e3
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", default="crazyflie", choices=["quadrotor", "crazyflie"])
    parser.add_argument("--train", default=None, help="also train a KNODE on this flight and score it")
    parser.add_argument("--data", default=str(DATA))
    parser.add_argument("--out", default="benchmarks/results/yardsticks")
    args = parser.parse_args()
    paths = sorted(Path(args.data).glob("*.csv"))
    flights = read_flights(paths)
    prior = HybridModel(system_for(flights[0], args.system), "prior")
    results = {"system": args.system, "gap_s": 0.5, "gap_every_s": 2.5,
               "command": "python benchmarks/yardsticks_nanobench.py " + " ".join(
                   f"--{k} {v}" for k, v in (("system", args.system), ("train", args.train)) if v),
               "runs": {"prior only": run(prior, flights, METHODS_PRIOR)}}
    if args.train:
        trained = next(f for f in flights if f.name == args.train)
        started = time.perf_counter()
        model = train_on_flight(trained, system=args.system).model
        results["training_seconds"] = time.perf_counter() - started
        results["runs"][f"KNODE trained on {args.train}"] = run(model, flights, METHODS_KNODE)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"nanobench_{args.system}"
    (out / f"{stem}.json").write_text(json.dumps(results, indent=1))
    (out / f"{stem}.md").write_text(markdown(results))
    print(markdown(results))


if __name__ == "__main__":
    main()
