"""The Crazyflie diagnosis on simulated flights with one undeclared effect each, in every thrust source the
prior takes (motor PWM + battery, rotor speed, thrust in N), plus the cases where a diagnosis can mislead:
a vehicle whose thrust per PWM is not the prior's (a brushless-like ×1.8), an accelerometer bias that a
tilt could cancel, and a tilted IMU in a Vicon + cfclient pair (two clocks, the sensor's own low-pass).

For each case: the effect reported first, its values against the truth (within 20 % is the target), the
held-out body-frame specific-force RMSE before and after (fitted on 2 flights, scored on the third), and
whether anything is claimed at a bound.

Run from the repository root:
    .venv/bin/python benchmarks/crazyflie_diagnosis_sources.py \
        > benchmarks/results/crazyflie_diagnosis_sources/results.md
(also writes results.json beside it)
"""
from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from learnest.ingest import read_flights
from learnest.ingest.sim import write_canonical_flight
from learnest.ingest.sim.export import CFCLIENT_CLOCK_OFFSET_S
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.service.experiments.diagnosis import diagnose_crazyflie

OUT = Path(__file__).parent / "results" / "crazyflie_diagnosis_sources"
PRIOR = dict(cf.IDENTIFIED)
M0 = 0.016            # light enough that a 20 % payload still flies on NanoBench's identified PWM map
DURATION_S = 20.0
TILT_RAD = np.radians(2.5)
METHODS = ("ukf",)       # the prior-only UKF with the prior before and after the repair, on the held-out flight

# effect -> (what the prior assumes, what the vehicle has, the effect expected first, its true values)
EFFECTS = {
    "payload +20 %": ({}, {"m_kg": 1.2 * M0}, None, None),            # expectation depends on the source
    "battery gamma 1.5": ({}, {"gamma": 1.5}, "battery_thrust", {"gamma": 1.5}),
    "rotor drag": ({"k_xy": 0.0, "k_z": 0.0}, {"k_xy": 0.5, "k_z": 0.3}, "rotor_drag", {"k_xy": 0.5, "k_z": 0.3}),
    "motor lag 30 ms": ({"tau_s": 0.0}, {"tau_s": 0.03}, "motor_lag", {"tau_s": 0.03}),
    "ground effect": ({"r_m": 0.0}, {"r_m": cf.BITCRAZE_ROTOR_RADIUS_M}, "ground_effect",
                      {"r_m": cf.BITCRAZE_ROTOR_RADIUS_M}),
}


def _case(source: str, effect: str, declared: float | None = None):
    """(prior, truth, controller, expected id, expected values) of one simulated case."""
    off, on, expected, values = EFFECTS[effect]
    base = {**PRIOR, "m_kg": M0}
    if source != "pwm":
        base["kappa_th"] = 0.0    # the motors' heating is not what these cases test (and rpm/thrust carry it)
    truth = {**base, **on}
    prior = {**base, **off}
    if source != "pwm":
        prior = cf.prior_for(source, M0, prior)
        if source == "rpm":     # the rotor speed is measured behind the motor's lag: the prior has none
            prior["tau_s"] = 0.0
            if effect != "motor lag 30 ms":
                # the simulator lags the body-z force (the z drag with the thrust), as the PWM prior does: a
                # vehicle with a lag would show it in its drag, which is not what these cases test
                truth["tau_s"] = 0.0
    if effect == "payload +20 %":
        if source != "thrust_n" and declared is None:
            expected, values = "thrust_gain", {"gain": 1 / 1.2}
        else:
            expected, values = "mass", {"m_kg": 1.2 * (declared or M0)}
    if effect == "battery gamma 1.5" and source == "rpm":
        expected, values = None, None       # a measured rotor speed carries the battery: nothing to find
    if effect == "battery gamma 1.5" and source == "thrust_n":
        # the firmware compensates the command with the controller's exponent: what is left is the difference
        expected, values = "battery_thrust", {"gamma": 1.5 - base["gamma"]}
    if effect == "motor lag 30 ms" and source == "rpm":
        expected, values = None, None       # a measured rotor speed lags with the motor: nothing to find
    return prior, truth, {**base}, expected, values


def _flights(truth, controller, source, n=3, **settings):
    return [simulate_crazyflie(SimulatedFlight(truth=truth, controller=controller, duration_s=DURATION_S,
                                               thrust_source=source, **settings), seed=s) for s in range(n)]


def _ukf_against_truth(report, flight, truth, controller, source, seed) -> tuple[float, float]:
    """The prior-only UKF's mean squared error against the simulated truth (p m, v m/s, a m/s², 9 states) on
    the held-out ``flight``, with the prior before and after the repair.  The service scores against SG
    references of the noisy mocap, whose own error (~0.06 here, mostly in v and a) is ~70× the estimate's:
    it cannot see a 30-ms lag.  The truth is the same flight flown without sensor noise (the noise is drawn
    after the flight, so the path is the same)."""
    from dataclasses import replace

    from learnest.estimators.prepared import system_for
    from learnest.models.knode import HybridModel
    from learnest.service.experiments.flights import evaluate_flight

    twin = simulate_crazyflie(SimulatedFlight(truth=truth, controller=controller, duration_s=DURATION_S,
                                              thrust_source=source, accel_noise=0.0, mocap_noise=0.0,
                                              vbat_noise=0.0), seed=seed)
    states = np.column_stack([twin.p, np.gradient(twin.p, twin.dt, axis=0), twin.a_meas])
    scores = []
    for params in (report["prior"]["params"], report["prior_after"]["params"]):
        system = replace(system_for(flight, "crazyflie"), prior_params=dict(params))
        run = evaluate_flight(HybridModel(system, "prior"), flight, ("ukf",), thrust_gain=False, keep_estimates=True)
        scores.append(float(np.mean((np.asarray(run["results"]["ukf"]["estimates"]) - states) ** 2)))
    return scores[0], scores[1]


def _claimed_at_bound(report) -> list[str]:
    return [f"{e['id']}.{k}" for e in report["effects"] for k, ok in e.get("identified", {}).items()
            if ok and e.get("at_bound", {}).get(k)]


def _summary(report, expected, values, truth_scores=(None, None)) -> dict:
    top = report["effects"][0] if report["effects"] else None
    claimed = [e["id"] for e in report["effects"] if any(e.get("identified", {}).values())]
    row = {"first": top["id"] if top else None, "claimed": claimed,
           "params": top["params"] if top else {}, "ci95": top["ci95"] if top else {},
           "before": report["before"]["specific_force_rmse"], "after": report["after"]["specific_force_rmse"],
           "ukf_before": report["before"].get("ukf"), "ukf_after": report["after"].get("ukf"),
           "ukf_truth_before": truth_scores[0], "ukf_truth_after": truth_scores[1],
           "repair": report.get("repair"),
           "vehicle_fits_prior": report.get("vehicle_fits_prior"), "thrust_source": report.get("thrust_source"),
           "claimed_at_bound": _claimed_at_bound(report), "confounded": [c["effects"] for c in report["confounded"]]}
    if expected is None:
        row["met"] = not claimed
    else:
        within = bool(top and top["id"] == expected and all(
            abs(top["params"][k] - v) <= 0.2 * abs(v) for k, v in values.items()))
        row["error_pct"] = {k: round(100 * (top["params"][k] - v) / v, 1) for k, v in values.items()} \
            if top and top["id"] == expected else None
        # held out: the specific force from the inputs, and the UKF against the simulated truth
        row["met"] = (within and row["after"] < row["before"] and not row["claimed_at_bound"]
                      and (row["ukf_truth_after"] is None or row["ukf_truth_after"] < row["ukf_truth_before"]))
    row["expected"] = expected
    row["truth"] = values
    return row


def source_matrix() -> list[dict]:
    rows = []
    for source in cf.THRUST_SOURCES:
        for effect in EFFECTS:
            # a declared mass: with PWM any (the payload is scaled onto it), with rotor speed the unloaded mass
            declared_masses = {"pwm": (None, 0.025), "rpm": (None, M0)}.get(source, (None,))
            for declared in (declared_masses if effect == "payload +20 %" else (None,)):
                prior, truth, controller, expected, values = _case(source, effect, declared)
                started = time.perf_counter()
                flights = _flights(truth, controller, source)
                report = diagnose_crazyflie(flights, methods=METHODS, prior=prior, mass_kg=declared)
                truth_scores = _ukf_against_truth(report, flights[-1], truth, controller, source, len(flights) - 1)
                row = _summary(report, expected, values, truth_scores)
                row.update(source=source, effect=effect + (f", declared {declared * 1e3:g} g" if declared else ""),
                           seconds=round(time.perf_counter() - started, 1))
                rows.append(row)
                print(json.dumps(row, default=float), file=sys.stderr)
    return rows


def special_cases() -> list[dict]:
    rows = []
    # a brushless-like vehicle: 1.8× the thrust per PWM of the prior's map (≡ 1/1.8 the mass against it)
    base = {**PRIOR, "m_kg": M0}
    report = diagnose_crazyflie(_flights({**base, "m_kg": M0 / 1.8}, base, "pwm"), methods=(), prior=base)
    fits = report["vehicle_fits_prior"]
    rows.append({"case": "brushless-like, thrust per PWM ×1.8", "vehicle_fits_prior": fits,
                 "met": (not fits["ok"]) and abs(fits["thrust_gain"] - 1.8) < 0.2 * 1.8,
                 "claimed_at_bound": _claimed_at_bound(report)})
    print(json.dumps(rows[-1], default=float), file=sys.stderr)
    # an accelerometer bias that a tilt could cancel (body x/y offsets)
    report = diagnose_crazyflie(_flights(base, base, "pwm", accel_bias=(0.25, -0.15, 0.0)), methods=(), prior=base)
    claimed = {e["id"]: e["params"] for e in report["effects"] if any(e.get("identified", {}).values())}
    rows.append({"case": "accelerometer bias (0.25, -0.15, 0) m/s²", "claimed": claimed,
                 "confounded": [c["effects"] for c in report["confounded"]],
                 "met": not ({"accel_bias", "accel_misalignment"} <= set(claimed)),
                 "claimed_at_bound": _claimed_at_bound(report)})
    print(json.dumps(rows[-1], default=float), file=sys.stderr)
    # a tilted IMU in a Vicon + cfclient pair, with the sensor's own 2-pole low-pass (30 Hz)
    with tempfile.TemporaryDirectory() as tmp:
        flights, offsets = [], []
        for i, flight in enumerate(_flights(base, base, "pwm", accel_tilt_rad=(TILT_RAD, 0.0), accel_lpf_hz=30.0)):
            read = read_flights(write_canonical_flight(flight, "vicon+cfclient", tmp, f"flight{i}"))[0]
            offsets.append(read.meta["clock_offset_s"] - CFCLIENT_CLOCK_OFFSET_S)
            flights.append(read)
        report = diagnose_crazyflie(flights, methods=(), prior=base)
    claimed = {e["id"]: e["params"] for e in report["effects"] if any(e.get("identified", {}).values())}
    tilt = (claimed.get("accel_misalignment") or {}).get("roll_rad")
    mocap_sample = flights[0].dt
    rows.append({"case": "IMU tilted 2.5° (roll), Vicon + cfclient, 30 Hz 2-pole low-pass",
                 "claimed": claimed, "first": report["effects"][0]["id"] if report["effects"] else None,
                 "roll_deg": None if tilt is None else float(np.degrees(tilt)),
                 "clock_offset_error_s": offsets, "mocap_sample_s": mocap_sample,
                 "tilt_met": tilt is not None and abs(tilt - TILT_RAD) <= 0.2 * TILT_RAD,
                 "clock_met": all(abs(o) <= mocap_sample for o in offsets),
                 "claimed_at_bound": _claimed_at_bound(report)})
    print(json.dumps(rows[-1], default=float), file=sys.stderr)
    return rows


def _markdown(matrix, special) -> str:
    lines = ["# Crazyflie diagnosis by thrust source, simulated flights",
             "", "Command: `.venv/bin/python benchmarks/crazyflie_diagnosis_sources.py > "
             "benchmarks/results/crazyflie_diagnosis_sources/results.md` (results.json beside it).",
             f"Three {DURATION_S:g}-s closed-loop flights per case (`models.crazyflie.simulate_crazyflie`, seeds 0-2), "
             "fitted on "
             "the first two, scored on the third (body-frame specific force from the inputs, RMSE m/s², 5 Hz).",
             "Target: the right effect first, within 20 %, after < before, nothing claimed at a bound; where the "
             "source already carries the effect (battery or lag behind a measured rotor speed, battery behind a "
             "thrust command), nothing claimed.", "",
             "Held-out (the third flight): specific-force RMSE (m/s²) from the inputs; the prior-only UKF's MSE "
             "over p, v, a against the simulated truth (the same flight flown without sensor noise), which "
             "`met` uses; and the service's own score, the UKF's MSE against SG references of the noisy mocap, "
             "whose own error (~0.06) is ~70× the estimate's and hides a 30-ms lag (the true parameters score "
             "worse on it than a lag-free prior), shown for reference.", "",
             "| source | effect | expected | first | values | error % | force before | force after "
             "| UKF vs truth before | UKF vs truth after | UKF vs SG ref. before | UKF vs SG ref. after "
             "| claimed | met |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in matrix:
        values = ", ".join(f"{k} {v:.4g}" for k, v in r["params"].items())
        lines.append(f"| {r['source']} | {r['effect']} | {r['expected'] or 'nothing'} | {r['first'] or '-'} | {values} "
                     f"| {r.get('error_pct') or '-'} | {r['before']:.4f} | {r['after']:.4f} | "
                     f"{r['ukf_truth_before']:.4g} | {r['ukf_truth_after']:.4g} | "
                     f"{r['ukf_before']:.4g} | {r['ukf_after']:.4g} | "
                     f"{', '.join(r['claimed']) or '-'} | {'MET' if r['met'] else 'NOT MET'} |")
    lines += ["", "## Cases a diagnosis can get wrong", ""]
    for r in special:
        met = r.get("met", r.get("tilt_met") and r.get("clock_met"))
        lines.append(f"- **{r['case']}**: {'MET' if met else 'NOT MET'} — "
                     + json.dumps({k: v for k, v in r.items() if k not in ("case",)}, default=float))
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    matrix = source_matrix()
    special = special_cases()
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "results.json").write_text(json.dumps({"matrix": matrix, "special": special}, indent=1, default=float))
    print(_markdown(matrix, special))
