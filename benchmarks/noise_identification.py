"""Is the prior's identified noise better than the paper's on a trajectory family it was not identified on?

Leave one family out on the real NanoBench flights (circles, figure-eights, helices, ramps; `../shared/data/
nanobench*`): the Crazyflie prior's process noise is identified on the other three families as training
identifies it (`learnest.estimators.noise_identification.with_identified_noise`: the UKF's innovation
likelihood plus that of the mocap hidden in the yardstick's gaps), then the prior-only UKF and MHE are scored
on every flight of the held-out family with the system's fixed (paper) noise and with the identified noise,
side by side in one run: median mocap-gap position RMSE per family and method, and on how many flights the
identified noise is better.

    python benchmarks/noise_identification.py [--families circle,figure8,helix,ramp] [--out DIR]

Writes ``noise_identification.json`` and ``noise_identification.md`` under ``--out``.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import learnest as le
from learnest.estimators.noise_identification import with_identified_noise
from learnest.estimators.prepared import prepare, system_for
from learnest.estimators.yardsticks import GapPlan
from learnest.models.knode import HybridModel
from learnest.models.noise import NoiseModel
from learnest.workflows.flights import evaluate_prepared

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FAMILIES = {"circle": "B2_circle", "figure8": "B3_figure8", "helix": "B5_helix", "ramp": "B6_linear_ramp"}
METHODS = ("ukf", "knode-ukf", "mhe", "knode-mhe")   # knode-* rows: the same prior, with the identified noise


def family_of(name: str) -> str | None:
    return next((family for family, prefix in FAMILIES.items() if name.startswith(prefix)), None)


def held_out(family: str, flights: list) -> dict:
    """The prior's noise identified without ``family``, and the family's flights scored with both noises."""
    train = [f for f in flights if family_of(f.name) != family and f.quality["ok"]]
    scored = [f for f in flights if family_of(f.name) == family and f.quality["ok"]]
    system = system_for(train[0], "crazyflie")
    started = time.perf_counter()
    identified = with_identified_noise(HybridModel(system, "prior"), train).noise
    seconds = time.perf_counter() - started
    # one model, two noises: its "knode-*" rows are the prior with the identified noise, the others the paper's
    model = HybridModel(system, "prior", noise=identified, prior_noise=NoiseModel.paper(system))
    rows, cache = [], {}
    for flight in scored:
        out = evaluate_prepared(prepare(model, flight), METHODS, mhe_cache=cache, gaps=GapPlan())
        rmse = out["yardsticks"].to_dict()["mocap_gaps"]["rmse_m"]
        rows.append({"flight": flight.name, "rmse_mm": {m: round(1e3 * v, 2) for m, v in rmse.items()}})
        print(family, rows[-1], flush=True)
    summary = {"flights": len(rows), "identified_on": len(train), "identification_seconds": round(seconds, 1),
               "factors": identified.detail["factors"],
               **{m: round(float(np.median([r["rmse_mm"][m] for r in rows])), 2) for m in METHODS},
               "ukf_better": sum(r["rmse_mm"]["knode-ukf"] < r["rmse_mm"]["ukf"] for r in rows),
               "mhe_better": sum(r["rmse_mm"]["knode-mhe"] < r["rmse_mm"]["mhe"] for r in rows)}
    return {"summary": summary, "flights": rows, "noise": identified.to_dict()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/noise_identification"))
    args = parser.parse_args()
    paths = sorted(p for folder in ("nanobench", "nanobench-more") for p in (DATA / folder).glob("B*.csv"))
    flights = [f for f in le.read_flights(paths) if family_of(f.name)]
    result = {family: held_out(family, flights) for family in args.families.split(",")}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "noise_identification.json").write_text(json.dumps(result, indent=2))
    lines = ["# The prior's noise: paper against identified on the other three families", "",
             "| held out | flights | factors (velocity, acceleration) | UKF paper | UKF identified | better | "
             "MHE paper | MHE identified | better |", "|---|---|---|---|---|---|---|---|---|"]
    for family, run in result.items():
        s = run["summary"]
        factors = f"×{s['factors']['Q:v']:.1f}, ×{s['factors']['Q:a']:.2f}"
        lines.append(f"| {family} | {s['flights']} | {factors} | {s['ukf']} | {s['knode-ukf']} | {s['ukf_better']} | "
                     f"{s['mhe']} | {s['knode-mhe']} | {s['mhe_better']} |")
    lines += ["", "Median mocap-gap position RMSE, mm (0.5-s gaps every 2.5 s after the first 5 s); the noise "
              "identified on the other three families' flights that pass the quality checks.  Command: "
              "`python benchmarks/noise_identification.py`."]
    (args.out / "noise_identification.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
