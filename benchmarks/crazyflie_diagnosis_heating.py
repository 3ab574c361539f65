"""Close the loop on real flights with an effect the prior lacks: the Crazyflie diagnosis run with a prior that
has no motor heating (`kappa_th` = 0), beside the same diagnosis with the package's prior (heating at its
identified value), on the NanoBench flights of `nanobench_circles_to_figure8s.md` (fit on 3 circles, scored on
3 figure-eights).  Does the diagnosis trace the within-flight thrust drift to motor heating, with a value that
agrees with the independent identification (`benchmarks/crazyflie_heating_prior.py`: 0.055)?

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/crazyflie_diagnosis_heating.py [--out benchmarks/results/crazyflie_diagnosis]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from learnest.ingest import read_flights
from learnest.models import crazyflie as cf
from learnest.workflows.diagnosis import diagnose_crazyflie

DATA = Path("../shared/data/nanobench")
FLIGHTS = ("B2_circle_slow_rep1", "B2_circle_medium_rep1", "B2_circle_fast_rep1",
           "B3_figure8_slow_rep1", "B3_figure8_medium_rep1", "B3_figure8_fast_rep1")
PRIORS = {"without heating (kappa_th = 0)": {**cf.IDENTIFIED, "kappa_th": 0.0},
          "with the identified heating (the package's prior)": dict(cf.IDENTIFIED)}


def summary(report: dict) -> dict:
    """The claimed effects with intervals, confounded pairs, the motor-heating candidate, per-flight scores."""
    heating = [c for c in report["candidates"] if c["id"] == "motor_heating"]
    return {"effects": [{"id": e["id"], "params": e["params"], "ci95": e.get("ci95"), "nominal": e.get("nominal")}
                        for e in report["effects"]],
            "confounded": [{"effects": c["effects"], "delta_bic": c["delta_bic"]} for c in report["confounded"]],
            "motor_heating_alone": heating[0] if heating else None,
            "per_flight": report["per_flight"], "improved_flights": report["improved_flights"]}


def markdown(result: dict) -> str:
    lines = ["# Crazyflie diagnosis with and without motor heating in the prior (real NanoBench flights)", "",
             f"Command: `{result['command'].strip()}` ({result['seconds']:.0f} s). Fit on "
             f"{', '.join(FLIGHTS[:3])}; scored on {', '.join(FLIGHTS[3:])}.", ""]
    for label, run in result["runs"].items():
        lines += [f"## Prior {label}", "", "| claimed effect | parameters (95 % interval) |", "|---|---|"]
        for e in run["effects"] or [{"id": "none", "params": {}, "ci95": None}]:
            params = "; ".join(f"{k} {v:.4g}" + (f" [{e['ci95'][k][0]:.4g}, {e['ci95'][k][1]:.4g}]"
                                                  if e.get("ci95") and k in e["ci95"] else "")
                               for k, v in e["params"].items())
            lines.append(f"| {e['id']} | {params} |")
        pairs = ", ".join(f"{' vs '.join(c['effects'])} (ΔBIC_eff {c['delta_bic']:.1f})" for c in run["confounded"])
        alone = run["motor_heating_alone"]
        lines += ["", f"Confounded: {pairs or 'none'}. Motor heating fitted alone: kappa_th "
                      f"{alone['params']['kappa_th']:.4f} (prior {alone['nominal']['kappa_th']:.3f})." if alone else "",
                  "", "| held-out flight | specific-force RMSE (m/s², 5 Hz) | UKF MSE |", "|---|---|---|"]
        for r in run["per_flight"]:
            before, after = r["before"], r["after"]
            lines.append(f"| {r['flight']} | {before['specific_force_rmse']:.4f} → {after['specific_force_rmse']:.4f} "
                         f"| {before['ukf']:.5f} → {after['ukf']:.5f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/crazyflie_diagnosis"))
    args = parser.parse_args(argv)
    started = time.time()
    flights = read_flights([DATA / f"{name}.csv" for name in FLIGHTS])
    runs = {label: summary(diagnose_crazyflie(flights, methods=("ukf",), prior=prior))
            for label, prior in PRIORS.items()}
    result = {"command": "python benchmarks/crazyflie_diagnosis_heating.py " + " ".join(argv or sys.argv[1:]),
              "runs": runs, "seconds": time.time() - started}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "heating_free_prior.json").write_text(json.dumps(result, indent=1, default=float))
    (args.out / "heating_free_prior.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
