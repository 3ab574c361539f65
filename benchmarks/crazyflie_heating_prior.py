"""Motor heating in the Crazyflie prior, identified and scored on the real NanoBench flights.

`models/crazyflie/motor_heating.py` scales the prior's thrust by (1 − κ h), h a cold-start thermal state from the motor
PWM and battery voltage (τ_th h' = P − h).  This script

1. identifies (τ_th, κ) from the mocap's body-z specific force against the prior's (`models.crazyflie`, the
   identified map, the flight's thrust axis), with a free thrust gain per flight (what `models.crazyflie.thrust_gain`
   calibrates), on a grid; pooled, per family, and held out by family (fit on the circles, score on the
   figure-eights, and the reverse); a bootstrap over flights gives intervals of κ/τ_th (the drift rate);
2. scores the prior-only UKF and MHE (the service's evaluation: thrust axis, thrust gain, SG references) on
   every flight with the heating off and on (the package's pooled values, `models.crazyflie.IDENTIFIED`).

Same flights as the other Crazyflie benchmarks (B2_circle_medium_rep3 left out: its accelerometer stops
for 6.9 s).  The specific force compares airborne samples 1 s from the window's ends, both sides low-passed
at 2 Hz (`models.crazyflie.thrust_gain`'s rule).

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/crazyflie_heating_prior.py [--bootstrap 200] \
        [--out benchmarks/results/crazyflie_heating]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from learnest.estimators.prepared import system_for
from learnest.ingest import read_flights
from learnest.ingest.align import FLYING_HEIGHT_M
from learnest.ingest.frames import GRAVITY
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.identify import lowpass
from learnest.models.crazyflie.motor_heating import thermal_state
from learnest.models.crazyflie.thrust_axis import EDGE_S, LOWPASS_HZ
from learnest.models.inputs import system_inputs
from learnest.models.knode import HybridModel
from learnest.workflows.flights import evaluate_flight

DATA = Path("../shared/data/nanobench")
HEATING = {name: cf.IDENTIFIED[name] for name in ("tau_th_s", "kappa_th")}   # the package's values
LEFT_OUT = {"B2_circle_medium_rep3"}
TAUS_S = (10.0, 20.0, 30.0, 45.0, 60.0, 75.0, 90.0, 120.0, 150.0, 180.0, 300.0)
KAPPAS = tuple(np.round(np.arange(0.0, 0.2001, 0.005), 3))


def specific_force(flight) -> dict:
    """Per flight: the mocap's and the prior's body-z specific force (m/s²), the airborne mask, the inputs."""
    system = system_for(flight, "crazyflie")
    u = system_inputs(flight, system, motor_heating=False)   # attitude on the thrust axis, nothing on the thrust
    dt = flight.dt
    velocity = np.gradient(flight.p, dt, axis=0)
    acceleration = lowpass(np.gradient(velocity, dt, axis=0), dt, LOWPASS_HZ)
    R = np.array(cf.rotation_columns(*u[:, :4].T))
    measured = np.einsum("it,ti->t", R[:, 2, :], acceleration + np.array([0.0, 0.0, GRAVITY]))
    predicted = np.asarray(cf.specific_force_body(list(lowpass(velocity, dt, LOWPASS_HZ).T), flight.p[:, 2],
                                                  list(u.T), system.prior_params)[0][2], dtype=float)
    edge = int(round(EDGE_S / dt))
    airborne = np.zeros(len(u), dtype=bool)
    airborne[edge:-edge] = flight.p[edge:-edge, 2] > FLYING_HEIGHT_M
    return {"u": u, "dt": dt, "measured": measured, "predicted": predicted, "airborne": airborne,
            "params": system.prior_params, "h": {}}


def residuals(record: dict, tau: float, kappa: float) -> np.ndarray:
    """Mocap minus prior body-z specific force on the airborne samples, the flight's gain fitted (m/s²)."""
    if tau not in record["h"]:
        record["h"][tau] = thermal_state(record["u"], record["dt"], tau)
    air = record["airborne"]
    x = record["predicted"][air] * (1.0 - kappa * record["h"][tau][air])
    y = record["measured"][air]
    return y - x * (x @ y) / (x @ x)


def rmse(records: dict, names, tau: float, kappa: float) -> float:
    r = np.concatenate([residuals(records[n], tau, kappa) for n in names])
    return float(np.sqrt(np.mean(r ** 2)))


def best_fit(records: dict, names) -> tuple[float, float, float]:
    """(rmse, τ_th, κ) minimising the pooled RMSE of ``names`` over the grid."""
    return min((rmse(records, names, tau, kappa), tau, kappa) for tau in TAUS_S for kappa in KAPPAS)


def estimator_scores(flights, heating: bool) -> dict:
    """Prior-only UKF and MHE MSE per flight, with the thrust gain; heating on or off."""
    out = {}
    for flight in flights:
        system = system_for(flight, "crazyflie")
        if not heating:
            system = replace(system, prior_params={**system.prior_params, "kappa_th": 0.0})
        results = evaluate_flight(HybridModel(system, "prior"), flight, ["ukf", "mhe"])["results"]
        out[flight.name] = {"ukf": results["ukf"]["mse"], "mhe": results["mhe"]["mse"]}
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bootstrap", type=int, default=200)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/crazyflie_heating"))
    args = parser.parse_args(argv)
    started = time.time()
    paths = sorted(p for p in DATA.glob("B*.csv") if p.stem not in LEFT_OUT)
    flights = read_flights(paths)
    records = {f.name: specific_force(f) for f in flights}
    names = list(records)
    family = {"circles": [n for n in names if "circle" in n], "figure-eights": [n for n in names if "figure8" in n]}

    fits = {label: best_fit(records, sel) for label, sel in [("pooled", names), *family.items()]}
    held_out = {}
    for fit_on, score_on in (("circles", "figure-eights"), ("figure-eights", "circles")):
        _, tau, kappa = fits[fit_on]
        held_out[f"{fit_on} -> {score_on}"] = {
            "tau_th_s": tau, "kappa_th": kappa, "rmse_without": rmse(records, family[score_on], TAUS_S[0], 0.0),
            "rmse_with": rmse(records, family[score_on], tau, kappa),
            "rmse_with_package_values": rmse(records, family[score_on], HEATING["tau_th_s"], HEATING["kappa_th"])}
    rng = np.random.default_rng(0)
    rates = []
    for _ in range(args.bootstrap):   # resample flights; the drift rate κ/τ_th is what 20-40 s flights determine
        _, tau, kappa = best_fit(records, list(rng.choice(names, size=len(names))))
        rates.append(100.0 * kappa / tau * 60.0)
    per_flight = {n: {"rmse_without": float(np.sqrt(np.mean(residuals(records[n], TAUS_S[0], 0.0) ** 2))),
                      "rmse_with": float(np.sqrt(np.mean(residuals(records[n], HEATING["tau_th_s"],
                                                                    HEATING["kappa_th"]) ** 2)))} for n in names}
    without, with_heating = estimator_scores(flights, False), estimator_scores(flights, True)
    result = {"command": "python benchmarks/crazyflie_heating_prior.py " + " ".join(argv or sys.argv[1:]),
              "package_values": HEATING,
              "fits": {k: {"rmse_without": rmse(records, sel, TAUS_S[0], 0.0), "rmse": fits[k][0],
                           "tau_th_s": fits[k][1], "kappa_th": fits[k][2]}
                       for k, sel in [("pooled", names), *family.items()]},
              "held_out": held_out, "drift_pct_per_hover_minute_ci95": [float(np.percentile(rates, 2.5)),
                                                                       float(np.percentile(rates, 97.5))],
              "drift_pct_per_hover_minute_pooled": 100.0 * fits["pooled"][2] / fits["pooled"][1] * 60.0,
              "per_flight": per_flight, "estimators": {"without": without, "with": with_heating},
              "seconds": time.time() - started}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "heating.json").write_text(json.dumps(result, indent=1))
    (args.out / "heating.md").write_text(markdown(result, family))
    print((args.out / "heating.md").read_text())
    return 0


def markdown(result: dict, family: dict) -> str:
    fits, held = result["fits"], result["held_out"]
    lines = ["# Motor heating in the Crazyflie prior (real NanoBench flights)", "",
             f"Command: `{result['command'].strip()}` ({result['seconds']:.0f} s)", "",
             "## Identification: body-z specific force, mocap vs prior, a free thrust gain per flight (m/s²)", "",
             "| fitted on | RMSE without heating | RMSE with | τ_th (s) | κ |", "|---|---|---|---|---|"]
    for label, fit in fits.items():
        lines.append(f"| {label} | {fit['rmse_without']:.4f} | {fit['rmse']:.4f} | {fit['tau_th_s']:.0f} | "
                     f"{fit['kappa_th']:.3f} |")
    lines += ["", "Held out by family (grid fit on one family, scored on the other):", "",
              "| direction | τ_th, κ fitted | RMSE without | RMSE with | with the package's values |",
              "|---|---|---|---|---|"]
    for direction, h in held.items():
        lines.append(f"| {direction} | {h['tau_th_s']:.0f} s, {h['kappa_th']:.3f} | {h['rmse_without']:.4f} | "
                     f"{h['rmse_with']:.4f} | {h['rmse_with_package_values']:.4f} |")
    lo, hi = result["drift_pct_per_hover_minute_ci95"]
    lines += ["", f"Drift rate κ/τ_th (thrust lost per minute of hover from cold, first order): pooled "
                  f"{result['drift_pct_per_hover_minute_pooled']:.2f} %/min, 95 % bootstrap over flights "
                  f"[{lo:.2f}, {hi:.2f}] %/min.", "",
              f"## Per flight, the package's values (τ_th {result['package_values']['tau_th_s']:.0f} s, "
              f"κ {result['package_values']['kappa_th']:.3f})", "",
              "| flight | specific force RMSE without / with | prior UKF MSE without / with "
              "| prior MHE MSE without / with |",
              "|---|---|---|---|"]
    est = result["estimators"]
    for name, row in result["per_flight"].items():
        lines.append(f"| {name} | {row['rmse_without']:.4f} / {row['rmse_with']:.4f} | "
                     f"{est['without'][name]['ukf']:.5f} / {est['with'][name]['ukf']:.5f} | "
                     f"{est['without'][name]['mhe']:.5f} / {est['with'][name]['mhe']:.5f} |")
    lines += ["", "| family | median prior UKF without / with | median prior MHE without / with "
                  "| flights better UKF / MHE |",
              "|---|---|---|---|"]
    for label, names in family.items():
        med = {k: {m: np.median([est[k][n][m] for n in names]) for m in ("ukf", "mhe")} for k in est}
        better = {m: sum(est["with"][n][m] < est["without"][n][m] for n in names) for m in ("ukf", "mhe")}
        lines.append(f"| {label} | {med['without']['ukf']:.5f} / {med['with']['ukf']:.5f} | "
                     f"{med['without']['mhe']:.5f} / {med['with']['mhe']:.5f} | "
                     f"{better['ukf']}/{len(names)} / {better['mhe']}/{len(names)} |")
    sf_better = sum(r["rmse_with"] < r["rmse_without"] for r in result["per_flight"].values())
    lines += ["", f"Specific force better with heating on {sf_better} of {len(result['per_flight'])} flights."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
