"""Transfer across trajectory families on the real NanoBench flights: a KNODE trained on
one circle (or one figure-eight) with the paper's kinematic prior and with the Crazyflie prior (motors +
battery), each scored with UKF / MHE / KNODE-UKF / KNODE-MHE on every flight of the *other* family.

Same training flights as benchmarks/run_crazyflie.sh (medium speed, repetition 2) and the same settings
(models.presets.CRAZYFLIE_TRAINING, MHE horizon 20, Savitzky–Golay references of window 150).

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/crazyflie_transfer.py [--systems crazyflie] [--out benchmarks/results/crazyflie_transfer]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from learnest.estimators.metrics import worse_beyond_interval
from learnest.ingest import read_flights
from learnest.models.presets import METHODS
from learnest.workflows.flights import evaluate_flights, train_on_flight

DATA = Path("../shared/data/nanobench")
TRAIN = {"circle": "B2_circle_medium_rep2", "figure8": "B3_figure8_medium_rep2"}
OTHER = {"circle": "figure8", "figure8": "circle"}
SYSTEMS = ("quadrotor", "crazyflie")


def gains(report: dict) -> dict:
    """Per scored flight: the KNODE estimator's MSE gain over its own prior-only estimator (%)."""
    out = {}
    for entry in report["flights"]:
        if entry["excluded"]:
            continue
        mse = entry["mse"]
        out[entry["flight"]] = {base: 100.0 * (1.0 - mse[f"knode-{base}"] / mse[base]) for base in ("ukf", "mhe")
                                if base in mse and f"knode-{base}" in mse}
    return out


def markdown(result: dict) -> str:
    lines = ["# Transfer across trajectory families: kinematic prior vs Crazyflie prior (real NanoBench flights)",
             "", f"Command: `{result['command']}`  ({result['seconds']:.0f} s wall, 2 shared cores)", ""]
    lines += pooled(result)
    for direction, by_system in result["runs"].items():
        lines += [f"## {direction}", "", "| prior | scored | " + " | ".join(f"median {m}" for m in METHODS)
                  + " | KNODE-UKF vs UKF | KNODE-MHE vs MHE | flights KNODE-UKF better | flights KNODE-MHE better "
                    "| median per-flight gain UKF / MHE |",
                  "|---" * (7 + len(METHODS)) + "|"]
        for system, run in by_system.items():
            med = run["report"]["median"]
            imp = run["report"]["improvement_pct"]
            per = run["gains"]
            better = {b: sum(1 for g in per.values() if g.get(b, 0) > 0) for b in ("ukf", "mhe")}
            lines.append(f"| {system} | {run['report']['flights_scored']} | "
                         + " | ".join(f"{med.get(m, float('nan')):.5f}" for m in METHODS)
                         + f" | {imp.get('knode-ukf_vs_ukf', float('nan')):+.1f} % | "
                           f"{imp.get('knode-mhe_vs_mhe', float('nan')):+.1f} % | {better['ukf']}/{len(per)} | "
                           f"{better['mhe']}/{len(per)} | "
                           + " / ".join(f"{np.median([g[b] for g in per.values() if b in g]):+.1f} %"
                                        if any(b in g for g in per.values()) else "–" for b in ("ukf", "mhe"))
                           + " |")
        lines += ["", "The recommended estimate (`estimators.evaluate.recommended_model`): per flight the KNODE's, "
                      "or its prior's where its verdict in the mocap gaps is worse beyond the interval; beside it, "
                      "what the one-step check would have recommended.", "",
                  "| prior | median gap RMSE UKF / MHE (m) | the prior alone | prior's estimate used on | "
                  "median per-flight gain, one-step rule, UKF / MHE |", "|---|---|---|---|---|"]
        for system, run in by_system.items():
            rec = run["report"].get("recommended")
            if not rec:
                continue
            per = recommended_gains(run)
            prior_on = sorted({name for names in rec["prior_on"].values() for name in names})
            lines.append(f"| {system} | "
                         + " / ".join(f"{rec['median_gap_rmse_m'].get(b, float('nan')):.4f}" for b in ("ukf", "mhe"))
                         + " | " + " / ".join(f"{rec['prior_median_gap_rmse_m'].get(b, float('nan')):.4f}"
                                               for b in ("ukf", "mhe"))
                         + f" | {', '.join(prior_on) or 'none'} | "
                         + " / ".join(f"{np.median([g[b] for g in per.values() if b in g]):+.1f} %"
                                      for b in ("ukf", "mhe")) + " |")
        lines += [""]
        for system, run in by_system.items():
            lines += [f"### {system}: per flight, and the two flags (no ground truth in either)", "",
                      "| flight | KNODE-UKF gain | KNODE-MHE gain | 95 % interval UKF / MHE | position innovations "
                      "KNODE / prior | predicts worse | outside envelope |", "|---|---|---|---|---|---|---|"]
            for entry in run["report"]["flights"]:
                if entry["excluded"]:
                    continue
                g, check = run["gains"][entry["flight"]], one_step_check(entry)
                intervals = " / ".join(f"[{lo:+.1f}, {hi:+.1f}]" for lo, hi in
                                       (entry.get("gain_interval_pct") or {}).values()) or "–"
                lines.append(f"| {entry['flight']} | {g.get('ukf', float('nan')):+.1f} % | {g.get('mhe', float('nan')):+.1f} % | "
                             f"{intervals} | {check.get('innovation_ratio', float('nan')):.3f} | "
                             f"{'yes' if check.get('knode_predicts_worse') else ''} | "
                             f"{'yes' if (entry.get('envelope') or {}).get('outside_training_envelope') else ''} |")
            unflagged = unflagged_losses(run)
            lines += ["", f"Flights where the KNODE is worse than its prior and neither flag is raised: UKF "
                          f"{len(unflagged['ukf'])} ({', '.join(unflagged['ukf']) or 'none'}), MHE {len(unflagged['mhe'])} "
                          f"({', '.join(unflagged['mhe']) or 'none'}).", ""]
        for system, run in by_system.items():
            lines.append(f"- {system}: median MSE by state group (p, v, a) — "
                         + "; ".join(f"{m}: " + ", ".join(f"{g} {v:.5f}" for g, v in run["median_groups"][m].items())
                                     for m in METHODS if m in run["median_groups"]))
        lines += [""]
    return "\n".join(lines)


def one_step_check(entry: dict) -> dict:
    """The one-step prediction check of a report's flight entry (`estimators.evaluate.prediction_check`'s keys),
    {} for a flight without the ratio."""
    ratio = entry.get("one_step_innovation_ratio")
    return {} if ratio is None else {"innovation_ratio": ratio, "knode_predicts_worse": bool(ratio > 1.0 + 1e-9)}


def recommended_gains(run: dict) -> dict:
    """Per scored flight: the gain over the prior-only estimator (%) of the estimate the one-step check would
    recommend: the KNODE's gain, or 0 where its ratio is above 1."""
    out = {}
    for entry in run["report"]["flights"]:
        if entry["excluded"]:
            continue
        use_prior = (one_step_check(entry)).get("knode_predicts_worse")
        out[entry["flight"]] = {b: 0.0 if use_prior else g for b, g in run["gains"][entry["flight"]].items()}
    return out


def pooled(result: dict) -> list[str]:
    """Both directions together, per prior: the issue's criterion (not worse than the prior on any flight of
    the other family, median gain across families positive), for the KNODE and for the recommended estimate."""
    lines = ["## Both directions pooled (16 flights per prior)", "",
             "Worse beyond its interval: the flight's 95 % interval of the KNODE's gain (paired circular block bootstrap, blocks of at least 2 s and 3 correlation lengths, "
             "`estimators.metrics.gain_interval`) lies below 0.", "",
             "| prior | estimate | flights worse than prior UKF / MHE | of them worse beyond the interval | "
             "median per-flight gain UKF / MHE |", "|---|---|---|---|---|"]
    systems = sorted({system for by_system in result["runs"].values() for system in by_system})
    for system in systems:
        runs = [by_system[system] for by_system in result["runs"].values() if system in by_system]
        for label, per_run in (("KNODE", lambda run: run["gains"]), ("recommended", recommended_gains)):
            per = [g for run in runs for g in per_run(run).values()]
            worse = " / ".join(str(sum(1 for g in per if g.get(b, 0) < 0)) for b in ("ukf", "mhe"))
            median = " / ".join(f"{np.median([g[b] for g in per if b in g]):+.1f} %" for b in ("ukf", "mhe"))
            clearly = " / ".join(str(sum(sum(worse_beyond_interval((e.get("gain_interval_pct") or {}).get(f"knode-{b}_vs_{b}"))
                                                     for e in run["report"]["flights"] if not e["excluded"]) for run in runs))
                                 for b in ("ukf", "mhe")) if label == "KNODE" else "–"
            lines.append(f"| {system} | {label} | {worse} | {clearly} | {median} |")
    return lines + [""]


def unflagged_losses(run: dict) -> dict:
    """Per base estimator: the flights where the KNODE variant is worse than it and the report raises neither
    the prediction check nor the envelope flag (a loss the user would not be warned about)."""
    out = {"ukf": [], "mhe": []}
    for entry in run["report"]["flights"]:
        if entry["excluded"]:
            continue
        flagged = (one_step_check(entry)).get("knode_predicts_worse") or \
            (entry.get("envelope") or {}).get("outside_training_envelope")
        for base, gain in run["gains"][entry["flight"]].items():
            if gain < 0 and not flagged:
                out[base].append(entry["flight"])
    return out


def median_groups(report: dict) -> dict:
    scored = [f for f in report["flights"] if not f["excluded"]]
    return {m: {g: float(np.median([f["groups"][m][g] for f in scored])) for g in ("p", "v", "a")}
            for m in METHODS if scored and m in scored[0]["groups"]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/crazyflie_transfer"))
    parser.add_argument("--directions", default="circle,figure8", help="families to train on")
    parser.add_argument("--methods", default=",".join(METHODS), help="estimators to score (MHE dominates the time)")
    parser.add_argument("--flights", default="", help="comma-separated names: score only these flights of the "
                                                           "other family (default: all of them)")
    parser.add_argument("--systems", default=",".join(SYSTEMS), help="priors to train and score")
    parser.add_argument("--tag", default="", help="suffix of the result files (transfer<tag>.json/.md)")
    args = parser.parse_args(argv)
    started = time.perf_counter()
    paths = sorted(args.data.glob("B*.csv"))
    if not paths:
        sys.exit(f"no NanoBench flights under {args.data}")
    flights = read_flights(paths)
    by_name = {f.name: f for f in flights}
    runs = {}
    methods = [m for m in args.methods.split(",") if m]
    args.out.mkdir(parents=True, exist_ok=True)
    stem = f"transfer{args.tag}"
    for family in args.directions.split(","):
        test = [f for f in flights if OTHER[family] in f.name]   # quality-failed flights are excluded by evaluate
        if args.flights:
            test = [f for f in test if f.name in args.flights.split(",")]
        direction = f"trained on {TRAIN[family]}, scored on the {OTHER[family]}s"
        runs[direction] = {}
        for system in args.systems.split(","):
            t0 = time.perf_counter()
            trained = train_on_flight(by_name[TRAIN[family]], system=system)
            report = evaluate_flights(trained.model, test, methods)
            runs[direction][system] = {"report": report, "gains": gains(report), "median_groups": median_groups(report),
                                       "train_seconds": trained.seconds, "seconds": time.perf_counter() - t0}
            print(f"{direction} / {system}: medians {report['median']} improvement {report['improvement_pct']}",
                  file=sys.stderr, flush=True)
            partial = {"command": "python benchmarks/crazyflie_transfer.py " + " ".join(argv or sys.argv[1:]),
                       "runs": runs, "seconds": time.perf_counter() - started}
            (args.out / f"{stem}.json").write_text(json.dumps(partial, indent=1))
    result = {"command": "python benchmarks/crazyflie_transfer.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              "runs": runs, "seconds": time.perf_counter() - started}
    (args.out / f"{stem}.json").write_text(json.dumps(result, indent=1))
    (args.out / f"{stem}.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
