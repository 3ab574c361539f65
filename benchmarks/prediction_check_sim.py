"""The prediction check against simulated truth (`estimators.evaluate.prediction_check`).

A Crazyflie KNODE is trained on one simulated flight of each regime (nominal; a payload of +20 % mass; rotor
drag ×3) and scored with UKF / KNODE-UKF on three fresh flights of every regime.  Where the KNODE loses to its
prior, does the check (KNODE / prior one-step position innovations > 1) flag the flight, and how often does it
flag a flight where the KNODE still gains?  The ground truth (the MSE against the simulated states' SG
references) is never shown to the check.

Run from the repository root:
    .venv/bin/python benchmarks/prediction_check_sim.py [--out benchmarks/results/prediction_check]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.workflows.flights import evaluate_flights, train_on_flight

NOMINAL = cf.IDENTIFIED
REGIMES = {"nominal": NOMINAL, "payload +20 %": {**NOMINAL, "m_kg": 1.2 * NOMINAL["m_kg"]},
           "rotor drag x3": {**NOMINAL, "k_xy": 3 * NOMINAL["k_xy"], "k_z": 3 * NOMINAL["k_z"]}}
TRAIN_SEED, TEST_SEEDS = 0, (11, 12, 13)


def flights(regime: str, seeds) -> list:
    out = []
    for seed in seeds:
        flight = simulate_crazyflie(SimulatedFlight(truth=REGIMES[regime], controller=NOMINAL, duration_s=20), seed=seed)
        flight.meta["name"] = f"{regime} #{seed}"
        out.append(flight)
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/prediction_check"))
    args = parser.parse_args(argv)
    started = time.perf_counter()
    rows = []
    for train in REGIMES:
        model = train_on_flight(flights(train, [TRAIN_SEED])[0], system="crazyflie").model
        for test in REGIMES:
            for entry in evaluate_flights(model, flights(test, TEST_SEEDS), ["ukf", "knode-ukf"])["flights"]:
                mse, ratio = entry["mse"], entry["one_step_innovation_ratio"]
                rows.append({"trained_on": train, "scored_on": entry["flight"], "same_regime": train == test,
                             "gain_pct": 100 * (1 - mse["knode-ukf"] / mse["ukf"]),
                             "innovation_ratio": ratio, "flagged": bool(ratio > 1.0 + 1e-9)})
                print(rows[-1], file=sys.stderr, flush=True)
    losses = [r for r in rows if r["gain_pct"] < 0]
    summary = {"evaluations": len(rows), "losses": len(losses), "losses_flagged": sum(r["flagged"] for r in losses),
               "gains_flagged": sum(r["flagged"] for r in rows if r["gain_pct"] >= 0),
               "same_regime_flagged": sum(r["flagged"] for r in rows if r["same_regime"])}
    result = {"command": "python benchmarks/prediction_check_sim.py", "rows": rows, "summary": summary,
              "seconds": time.perf_counter() - started}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "sim.json").write_text(json.dumps(result, indent=1))
    lines = ["# Prediction check against simulated truth", "", f"Command: `{result['command']}` "
             f"({result['seconds']:.0f} s wall)", "", "| trained on | scored on | KNODE-UKF gain | ratio | flagged |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['trained_on']} | {r['scored_on']} | {r['gain_pct']:+.1f} % | {r['innovation_ratio']:.3f} | "
              f"{'yes' if r['flagged'] else ''} |" for r in rows]
    lines += ["", f"{summary['evaluations']} evaluations: {summary['losses']} losses, {summary['losses_flagged']} of "
              f"them flagged; {summary['gains_flagged']} flags where the KNODE gains; "
              f"{summary['same_regime_flagged']} flags in the training regime."]
    (args.out / "sim.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
