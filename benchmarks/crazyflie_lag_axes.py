"""The Crazyflie prior's two lags on real flights: the motors' lag along the thrust axis (tau_s) and the
attitude lag across it (tau_att_s), scored by the prior-only estimators' position RMSE in the mocap gaps.

A motor lags the thrust's size; its direction is the attitude, an input.  So a vehicle whose logged attitude
is its own needs no lag across the thrust axis, which is how the simulator flies.  This grid asks what the
real NanoBench flights need: tau_s and tau_att_s are chosen on the circles and figure-eights (``nanobench/``)
and reported on the helices and ramps (``nanobench-more/``), families the choice never saw.  The UKF runs
the whole grid; the MHE (one compiled library per setting) runs the candidates around the prior's value.
Last, a check of what the attitude lag is not: the lag at which the attitude's prediction of the horizontal
acceleration best matches the acceleration of the mocap position (cross-correlation, per flight), and the
UKF with the attitude input advanced by 20-60 ms, which that lead suggests.

Run from the repository root (needs ../shared/data, ~3 min):
    .venv/bin/python benchmarks/crazyflie_lag_axes.py > benchmarks/results/crazyflie_lag_axes/results.md
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
from scipy.signal import savgol_filter

from learnest.ingest import read_flights
from learnest.models import crazyflie as cf
from learnest.models.knode import HybridModel
from learnest.models.systems import Crazyflie
from learnest.workflows.estimation import evaluate

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
OUT = Path(__file__).parent / "results" / "crazyflie_lag_axes"
GRID_S = (0.0, 0.015, 0.03, 0.045, 0.061, 0.08, 0.1)
MHE_ATT_S = (0.03, 0.045, 0.061, 0.07, 0.08)
MAX_SHIFT = 20        # samples either way in the cross-correlation (0.2 s at 100 Hz)
ADVANCE_SAMPLES = (0, 2, 4, 6)


def _gaps(params: dict, flights, methods) -> np.ndarray:
    """(flights, methods) mocap-gap position RMSE (m) of the prior with ``params`` over cf.IDENTIFIED."""
    model = HybridModel(Crazyflie(prior_params={**cf.IDENTIFIED, **params}), "prior")
    report = evaluate(model, flights, methods=methods)
    return np.array([[f["yardsticks"]["mocap_gaps"]["rmse_m"][m] for m in methods]
                     for f in report["flights"] if not f.get("excluded")])


def attitude_lead_s(flight) -> float:
    """The shift (s) at which the attitude's horizontal acceleration, b₃,xy · median thrust over mass, best
    matches the mocap position's second derivative (Savitzky–Golay, 0.21 s), both axes pooled; positive when
    the mocap acceleration comes after the attitude that should cause it."""
    a = savgol_filter(flight.p, 21, 3, deriv=2, delta=flight.dt, axis=0)
    R = cf.rotation_columns(*flight.quat.T)
    b3 = np.stack([R[0][2], R[1][2], R[2][2]], axis=1)
    from_attitude = b3[:, :2] * np.median((a[:, 2] + 9.81) / b3[:, 2])
    x, y = from_attitude - from_attitude.mean(0), a[:, :2] - a[:, :2].mean(0)
    n = len(x)
    score = [np.sum(x[max(0, -k):n - max(0, k)] * y[max(0, k):n - max(0, -k)])
             for k in range(-MAX_SHIFT, MAX_SHIFT + 1)]
    return (int(np.argmax(score)) - MAX_SHIFT) * flight.dt


def attitude_advanced(flight, samples: int):
    """The flight with its attitude input taken ``samples`` steps later (the last ones held)."""
    if samples == 0:
        return flight
    quat = np.concatenate([flight.quat[samples:], np.repeat(flight.quat[-1:], samples, axis=0)])
    return dataclasses.replace(flight, quat=quat)


def main() -> None:
    started = time.perf_counter()
    chosen_on = read_flights(sorted((DATA / "nanobench").glob("*.csv")))
    held_out = read_flights(sorted((DATA / "nanobench-more").glob("*.csv")))
    nominal = {"tau_s": cf.IDENTIFIED["tau_s"], "tau_att_s": cf.IDENTIFIED["tau_att_s"]}
    base = [_gaps(nominal, f, ("ukf", "mhe")) for f in (chosen_on, held_out)]
    print("# The Crazyflie prior's two lags on real flights\n")
    print(f"Chosen on {len(base[0])} NanoBench circles and figure-eights, reported on {len(base[1])} helices "
          f"and ramps (the flights that pass the quality checks).  Median mocap-gap position RMSE (mm) of the "
          f"prior-only estimator; the prior's values: "
          f"tau_s {nominal['tau_s']} s, tau_att_s {nominal['tau_att_s']} s.\n")
    rows = []
    print("## UKF, the whole grid (chosen on / held out)\n")
    print("| tau_s \\ tau_att_s | " + " | ".join(f"{a:g}" for a in GRID_S) + " |")
    print("|---" * (len(GRID_S) + 1) + "|")
    for tau_s in GRID_S:
        cells = []
        for tau_att in GRID_S:
            params = {"tau_s": tau_s, "tau_att_s": tau_att}
            chosen, held = (np.median(_gaps(params, f, ("ukf",))) for f in (chosen_on, held_out))
            rows.append({**params, "ukf_chosen_on_m": float(chosen), "ukf_held_out_m": float(held)})
            cells.append(f"{1e3 * chosen:.2f} / {1e3 * held:.2f}")
        print(f"| {tau_s:g} | " + " | ".join(cells) + " |")
    best = min(rows, key=lambda r: r["ukf_chosen_on_m"])
    print(f"\nBest on the flights chosen on: tau_s {best['tau_s']:g}, tau_att_s {best['tau_att_s']:g} "
          f"({1e3 * best['ukf_chosen_on_m']:.2f} mm; held out {1e3 * best['ukf_held_out_m']:.2f} mm).\n")
    print("## UKF and MHE near the prior's value (tau_s held), against the prior flight by flight\n")
    print("| tau_att_s | UKF chosen on | better | UKF held out | better | MHE chosen on | better | MHE held out "
          "| better |")
    print("|---|---|---|---|---|---|---|---|---|")
    for tau_att in MHE_ATT_S:
        runs = [_gaps({**nominal, "tau_att_s": tau_att}, f, ("ukf", "mhe")) for f in (chosen_on, held_out)]
        cells = []
        for m in range(2):
            for run, ref in zip(runs, base):
                cells += [f"{1e3 * np.median(run[:, m]):.2f}", f"{int((run[:, m] < ref[:, m]).sum())}/{len(run)}"]
        print(f"| {tau_att:g} | " + " | ".join(cells) + " |")
    leads = {f.name: attitude_lead_s(f) for f in (*chosen_on, *held_out)}
    print("\n## Does the mocap acceleration trail the logged attitude?\n")
    print("Shift (ms) of the best match, positive = the acceleration comes after the attitude: "
          + ", ".join(f"{name} {1e3 * s:+.0f}" for name, s in leads.items())
          + f".  Median {1e3 * np.median(list(leads.values())):+.0f} ms.")
    print("\n## The attitude input advanced\n")
    print("| advance (ms) | tau_att_s | UKF chosen on | UKF held out |")
    print("|---|---|---|---|")
    for samples in ADVANCE_SAMPLES:
        for tau_att in (0.03, nominal["tau_att_s"]):
            scores = [np.median(_gaps({**nominal, "tau_att_s": tau_att},
                                      [attitude_advanced(f, samples) for f in flights], ("ukf",)))
                      for flights in (chosen_on, held_out)]
            print(f"| {1e3 * samples * chosen_on[0].dt:.0f} | {tau_att:g} | {1e3 * scores[0]:.2f} "
                  f"| {1e3 * scores[1]:.2f} |")
    print(f"\n{time.perf_counter() - started:.0f} s.")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "grid.json").write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
