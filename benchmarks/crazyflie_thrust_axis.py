"""The thrust axis against the mocap body frame on the real NanoBench flights (the Crazyflie prior
vs the kinematic one).

Per flight: the calibrated offset (`models.crazyflie.thrust_axis`, from mocap position and attitude only), and the
prior-only UKF and MHE scored against the Savitzky–Golay references (as `learnest evaluate` scores them)
with three priors: the paper's kinematic chain, the Crazyflie prior fed the mocap attitude as logged, and
the Crazyflie prior fed the attitude calibrated onto the thrust axis (what `models.inputs.system_inputs`
gives it now).

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/crazyflie_thrust_axis.py [--out benchmarks/results/crazyflie_thrust_axis]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from learnest.estimators.evaluate import evaluate_sequence
from learnest.estimators.prepared import initial_state, model_params, system_for
from learnest.ingest import read_flights
from learnest.ingest.baseline import references
from learnest.models.inputs import flight_thrust_axis, system_inputs
from learnest.models.knode import HybridModel
from learnest.models.presets import SG_WINDOW

DATA = Path("../shared/data/nanobench")
METHODS = ("ukf", "mhe")
PRIORS = ("kinematic", "crazyflie, attitude as logged", "crazyflie, calibrated")


def score_flight(flight, cache: dict) -> dict:
    reference = references(flight, window=SG_WINDOW)
    y, x0 = flight.measurements(), initial_state(flight)
    out = {"offset_deg": [float(v) for v in np.degrees(flight_thrust_axis(flight))], "mse": {}}
    for prior in PRIORS:
        system = system_for(flight, "quadrotor" if prior == "kinematic" else "crazyflie")
        u = system_inputs(flight, system)
        if prior == "crazyflie, attitude as logged":
            u = u.copy()
            u[:, :4] = flight.quat
        params = model_params(HybridModel(system, "prior"), x0, flight.dt)
        results = evaluate_sequence(METHODS, params, params, y, u, reference, mhe_cache=cache.setdefault(prior, {}))
        out["mse"][prior] = {m: results[m]["mse"] for m in METHODS}
    return out


def markdown(result: dict) -> str:
    rows = result["flights"]
    lines = ["# Thrust axis vs the mocap body frame, NanoBench (prior-only UKF and MHE, MSE over p, v, a)", "",
             f"Command: `{result['command']}`  ({result['seconds']:.0f} s wall)", "",
             "Offset: the mean direction of the specific force Rᵀ(p̈ + g e₃) in the mocap body frame "
             "(p̈ from the mocap position, 2 Hz low-pass), as angles towards body x and y.", "",
             "| flight | offset x (°) | offset y (°) | " + " | ".join(f"{p} {m.upper()}" for p in PRIORS for m in METHODS)
             + " |", "|---" * (3 + len(PRIORS) * len(METHODS)) + "|"]
    for name, r in rows.items():
        lines.append(f"| {name} | {r['offset_deg'][0]:+.2f} | {r['offset_deg'][1]:+.2f} | "
                     + " | ".join(f"{r['mse'][p][m]:.5f}" for p in PRIORS for m in METHODS) + " |")
    lines += ["", "| prior | median UKF | median MHE | flights better than the kinematic prior (UKF / MHE) |", "|---|---|---|---|"]
    for p in PRIORS:
        med = {m: float(np.median([r["mse"][p][m] for r in rows.values()])) for m in METHODS}
        better = {m: sum(r["mse"][p][m] < r["mse"]["kinematic"][m] for r in rows.values()) for m in METHODS}
        lines.append(f"| {p} | {med['ukf']:.5f} | {med['mhe']:.5f} | {better['ukf']}/{len(rows)} / "
                     f"{better['mhe']}/{len(rows)} |")
    gained = {m: sum(r["mse"][PRIORS[2]][m] < r["mse"][PRIORS[1]][m] for r in rows.values()) for m in METHODS}
    tilt = np.array([np.hypot(*r["offset_deg"]) for r in rows.values()])
    loss = np.array([r["mse"][PRIORS[1]]["ukf"] - r["mse"]["kinematic"]["ukf"] for r in rows.values()])
    lines += ["", f"Calibration lowers the Crazyflie prior's MSE on {gained['ukf']}/{len(rows)} flights (UKF) and "
              f"{gained['mhe']}/{len(rows)} (MHE).  Offset magnitude {tilt.min():.2f}-{tilt.max():.2f}°; its "
              f"correlation with the uncalibrated Crazyflie prior's UKF loss to the kinematic prior: "
              f"{np.corrcoef(tilt, loss)[0, 1]:.2f}.", ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/crazyflie_thrust_axis"))
    args = parser.parse_args(argv)
    started = time.perf_counter()
    paths = sorted(args.data.glob("B*.csv"))
    if not paths:
        sys.exit(f"no NanoBench flights under {args.data}")
    cache: dict = {}
    flights = {}
    for flight in read_flights(paths):
        if not flight.quality["ok"]:
            continue
        flights[flight.name] = score_flight(flight, cache)
        print(flight.name, flights[flight.name], file=sys.stderr, flush=True)
    result = {"command": "python benchmarks/crazyflie_thrust_axis.py " + " ".join(argv or sys.argv[1:]),
              "flights": flights, "seconds": time.perf_counter() - started}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "thrust_axis.json").write_text(json.dumps(result, indent=1))
    (args.out / "thrust_axis.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
