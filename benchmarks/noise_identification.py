"""Does the prior-only filter with noise identified on some flights estimate other families better in the mocap gaps?

The Crazyflie prior's noise is identified (`learnest.estimators.noise_identification`, maximum UKF innovation
likelihood) on the 17 NanoBench circles and figure-eights, then the prior-only UKF and MHE are scored on the
helices and ramps (`nanobench-more/`, never used to identify) with the system's fixed (paper) noise and with the
identified noise, side by side in one run: median mocap-gap position RMSE per family and method, per flight.

    python benchmarks/noise_identification.py [--process-blocks v a] [--measurement-blocks p a] [--out DIR]

Writes ``noise_identification.json`` and ``noise_identification.md`` under ``--out``.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import learnest as le
from learnest.estimators.noise_identification import identify_noise, noise_records
from learnest.estimators.prepared import prepare, system_for
from learnest.estimators.yardsticks import GapPlan
from learnest.models.knode import HybridModel
from learnest.models.noise import NoiseModel
from learnest.workflows.flights import evaluate_prepared

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
METHODS = ("ukf", "knode-ukf", "mhe", "knode-mhe")   # knode-* rows: the same prior, with the identified noise


def family(name: str) -> str:
    return {"B2": "circle", "B3": "figure-eight", "B5": "helix", "B6": "ramp"}[name[:2]]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--process-blocks", nargs="*", default=["v", "a"], help="Q blocks searched (default v a)")
    parser.add_argument("--measurement-blocks", nargs="*", default=[], help="R blocks searched too (default none)")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/noise_identification"))
    args = parser.parse_args()
    train = [f for f in le.read_flights(sorted((DATA / "nanobench").glob("*.csv"))) if f.quality["ok"]]
    scored = [f for f in le.read_flights(sorted((DATA / "nanobench-more").glob("*.csv"))) if f.quality["ok"]]
    system = system_for(train[0], "crazyflie")
    paper = NoiseModel.paper(system)
    prior = HybridModel(system, "prior")
    started = time.perf_counter()
    identified = identify_noise(noise_records(prior, train, "prior"), paper, process_blocks=tuple(args.process_blocks),
                                measurement_blocks=tuple(args.measurement_blocks))
    seconds = time.perf_counter() - started
    # one model, two noises: its "knode-*" rows are the prior with the identified noise, the others the paper's
    model = HybridModel(system, "prior", noise=identified, prior_noise=paper)
    rows, cache = [], {}
    for flight in scored:
        out = evaluate_prepared(prepare(model, flight), METHODS, mhe_cache=cache, gaps=GapPlan())
        rmse = out["yardsticks"].to_dict()["mocap_gaps"]["rmse_m"]
        rows.append({"flight": flight.name, "family": family(flight.name),
                     "rmse_mm": {m: round(1e3 * v, 2) for m, v in rmse.items()}})
        print(rows[-1], flush=True)
    summary = {}
    for fam in sorted({r["family"] for r in rows}):
        members = [r for r in rows if r["family"] == fam]
        summary[fam] = {"flights": len(members),
                        **{m: round(float(np.median([r["rmse_mm"][m] for r in members])), 2) for m in METHODS},
                        "ukf_better": sum(r["rmse_mm"]["knode-ukf"] < r["rmse_mm"]["ukf"] for r in members),
                        "mhe_better": sum(r["rmse_mm"]["knode-mhe"] < r["rmse_mm"]["mhe"] for r in members)}
    result = {"identified_on": [f.name for f in train], "identification_seconds": round(seconds, 1),
              "noise": identified.to_dict(), "described": identified.describe(system), "families": summary,
              "flights": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "noise_identification.json").write_text(json.dumps(result, indent=2))
    lines = ["# Prior-only filters: paper noise against noise identified on circles and figure-eights", "",
             f"Identified on {len(train)} flights in {seconds:.1f} s: "
             + ", ".join(f"{k} ×{v:g}" for k, v in identified.detail["factors"].items())
             + f" (log-likelihood per step {identified.detail['log_likelihood_per_step']['start']:.2f} -> "
             f"{identified.detail['log_likelihood_per_step']['identified']:.2f}).", "",
             "| family | flights | UKF paper | UKF identified | better | MHE paper | MHE identified | better |",
             "|---|---|---|---|---|---|---|---|"]
    for fam, s in summary.items():
        lines.append(f"| {fam} | {s['flights']} | {s['ukf']} | {s['knode-ukf']} | {s['ukf_better']} | {s['mhe']} | "
                     f"{s['knode-mhe']} | {s['mhe_better']} |")
    lines += ["", "Median mocap-gap position RMSE, mm (0.5-s gaps every 2 s).  Command: "
              "`python benchmarks/noise_identification.py`."]
    (args.out / "noise_identification.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
