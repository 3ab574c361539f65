"""Per-motor thrust maps on the real NanoBench flights (issue 14, the held-out specific-force target).

`crazyflie_physics.py` fits the physics prior's form: one thrust map shared by the four motors (Förster's
quadratic in PWM, a voltage power law, an effective mass, a motor lag, rotor drag).  Its held-out error
stays at 73 % / 88 % of the constant's.  This benchmark asks how much of the rest the inputs can explain
when each motor has its own quadratic map, with a model that is *linear in its coefficients* (so it is
fitted by least squares, no local minima, and every rung of the ladder is exactly nested):

    f_z = b + Σ_i (c1_i p_i + c2_i p_i²) + d1 V + d2 V Σ_i p_i + d3 V² [+ airframe terms]

with p_i = PWM_i / 65535, V the battery voltage (V); every column goes through the motor lag (first
order, τ picked on the training flights only, from a grid) and the 5 Hz low-pass of the protocol
(`models.identify`), so the model is the same filter chain as the prior's.  Airframe terms: 1 − R₃₃
(tilt), max(v_z, 0) and min(v_z, 0) (climb/descent inflow).

Scored in two windows, because the issue's scale ("the constant scores ≈ 0.28 m/s²") was measured in the
second one:
- *in flight*: learnest's flying window (1 s after take-off to 1 s before landing), as every other
  identification benchmark; the constant scores ≈ 0.21 here.
- *airborne*: from the first rise 10 cm above the resting height to the last time below it (no settle
  cut), which keeps the climb-out and the descent; the constant scores ≈ 0.28 here.

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/crazyflie_thrust_map.py [--bootstrap 200]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import learnest.ingest.align as align
from learnest.ingest.frames import GRAVITY, quat_to_matrix
from learnest.models.identify import first_order_lag, flight_arrays, lowpass

sys.path.insert(0, str(Path(__file__).parent))
from crazyflie_physics import DATA, TARGET_FRACTION_OF_CONSTANT, TARGET_RMSE, family, load  # noqa: E402

TAUS_S = (0.0, 0.02, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.10)
SHARED = ("1", "Σp", "Σp^2")
PER_MOTOR = ("1", "p1", "p2", "p3", "p4", "p1^2", "p2^2", "p3^2", "p4^2")
BATTERY = ("V", "V·Σp", "V^2")
AIRFRAME = ("tilt", "vz+", "vz-")
LADDER = (
    ("shared quadratic map + V", SHARED + ("V",)),
    ("+ battery polynomial (V·Σp, V²)", SHARED + BATTERY),
    ("+ CW/CCW split (p1 − p2 + p3 − p4)", SHARED + ("split",) + BATTERY),
    ("per-motor quadratic maps instead of the split", PER_MOTOR + BATTERY),
    ("CW/CCW split + tilt, climb, descent", SHARED + ("split",) + BATTERY + AIRFRAME),
)
BEST = LADDER[4]


def columns(arrays) -> dict[str, np.ndarray]:
    """Every candidate regressor of one flight, on its grid (before lag and low-pass)."""
    p = arrays.u[:, 4:8] / 65535.0
    volts = arrays.u[:, 8]
    R = quat_to_matrix(arrays.u[:, :4])
    vz = arrays.v_world[:, 2]
    out = {"1": np.ones(len(volts)), "Σp": p.sum(1), "Σp^2": (p**2).sum(1), "V": volts, "V·Σp": volts * p.sum(1),
           "V^2": volts**2, "split": p[:, 0] - p[:, 1] + p[:, 2] - p[:, 3], "tilt": 1.0 - R[:, 2, 2], "vz+": np.maximum(vz, 0.0), "vz-": np.minimum(vz, 0.0)}
    for i in range(4):
        out[f"p{i + 1}"] = p[:, i]
        out[f"p{i + 1}^2"] = p[:, i] ** 2
    return out


def design(arrays, names, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """(kept rows, len(names)) design matrix and the measured body z specific force on those rows."""
    cols = columns(arrays)
    X = np.column_stack([cols[n] for n in names])
    X = lowpass(first_order_lag(X, tau, arrays.dt), arrays.dt)
    return X[arrays.keep], arrays.acc_body[arrays.keep, 2]


def stacked(flights, names, tau):
    parts = [design(a, names, tau) for a in flights]
    return np.vstack([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def fit(flights, names) -> tuple[np.ndarray, float, float]:
    """Coefficients, τ (s) and training RMSE; τ is the grid value with the lowest training RMSE."""
    best = None
    for tau in TAUS_S:
        X, y = stacked(flights, names, tau)
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        rmse = float(np.sqrt(np.mean((X @ coef - y) ** 2)))
        if best is None or rmse < best[2]:
            best = (coef, tau, rmse)
    return best


def score(flights, names, coef, tau) -> float:
    X, y = stacked(flights, names, tau)
    return float(np.sqrt(np.mean((X @ coef - y) ** 2)))


def constant(flights) -> float:
    y = np.concatenate([a.acc_body[a.keep, 2] for a in flights])
    return float(np.sqrt(np.mean((GRAVITY - y) ** 2)))


def readings(flights, coef, names) -> dict[str, float]:
    """The physical reading of a fit of `BEST`, at the flights' mean PWM and voltage:

    - ``dfz_dV``: m/s² per volt of battery at constant PWM (``percent_g_per_V``: the same in % of g);
    - ``dfz_dsplit``: m/s² per unit of the CW/CCW duty split p1 − p2 + p3 − p4 (the yaw command);
    - ``dfz_dsum``: m/s² per unit of the summed duty Σp (the collective map's slope)."""
    c = dict(zip(names, coef))
    p = np.concatenate([a.u[a.keep, 4:8] for a in flights]) / 65535.0
    volts = float(np.mean(np.concatenate([a.u[a.keep, 8] for a in flights])))
    total = float(p.sum(1).mean())
    dV = c["V"] + c["V·Σp"] * total + 2 * c["V^2"] * volts
    # Σp² ≈ (Σp)²/4 near equal motors: d(Σp²)/d(Σp) = 2 p_i = Σp / 2
    dsum = c["Σp"] + c["Σp^2"] * total / 2 + c["V·Σp"] * volts
    return {"dfz_dV": float(dV), "percent_g_per_V": float(100 * dV / GRAVITY), "dfz_dsplit": float(c["split"]),
            "dfz_dsum": float(dsum)}


def window(flights_by_window: dict, name: str, n_boot: int) -> dict:
    arrays = flights_by_window[name]
    fams = {f: [a for a in arrays.values() if family(a.name) == f] for f in ("circle", "figure8")}
    splits = {}
    for train, test in (("circle", "figure8"), ("figure8", "circle")):
        c0 = constant(fams[test])
        rows = []
        for label, names in LADDER:
            coef, tau, rmse_train = fit(fams[train], names)
            rmse_test = score(fams[test], names, coef, tau)
            rows.append({"model": label, "terms": list(names), "tau_s": tau, "rmse_train": rmse_train,
                         "rmse_test": rmse_test, "fraction_of_constant": rmse_test / c0,
                         "meets_target": bool(rmse_test <= TARGET_RMSE
                                              and rmse_test <= TARGET_FRACTION_OF_CONSTANT * c0)})
        splits[f"fit_{train}_score_{test}"] = {"constant_rmse_test": c0, "rows": rows}
    everything = list(arrays.values())
    coef, tau, rmse = fit(everything, BEST[1])
    rng = np.random.default_rng(0)
    draws = []
    for _ in range(n_boot):
        sample = [everything[i] for i in rng.integers(0, len(everything), len(everything))]
        c, *_ = np.linalg.lstsq(*stacked(sample, BEST[1], tau), rcond=None)
        draws.append(readings(sample, c, BEST[1]))
    intervals = {k: [float(np.percentile([d[k] for d in draws], q)) for q in (2.5, 97.5)] for k in draws[0]}
    return {"splits": splits, "pooled": {"terms": list(BEST[1]), "coef": coef.tolist(), "tau_s": tau,
                                         "rmse": rmse, "readings": readings(everything, coef, BEST[1]),
                                         "intervals": intervals},
            "constant_rmse_all": constant(everything), "flights": sorted(arrays)}


def markdown(result: dict) -> str:
    lines = ["# Per-motor thrust maps on NanoBench (body z specific force, 5 Hz low-pass, held out by family)", "",
             f"Command: `{result['command']}`  ({result['seconds']:.0f} s wall)", "",
             f"Flights: {len(result['windows']['in flight']['flights'])}; excluded: "
             + ", ".join(f"{k} ({v})" for k, v in result["flights_excluded"].items()), "",
             f"Target: held-out RMSE ≤ {TARGET_RMSE} m/s² and ≤ {100 * TARGET_FRACTION_OF_CONSTANT:.0f} % of "
             "the constant 1 g's, fit on one family and scored on the other, both directions.", ""]
    for wname, w in result["windows"].items():
        lines += [f"## Window: {wname} (constant 1 g over all flights: {w['constant_rmse_all']:.3f} m/s²)", ""]
        for key, split in w["splits"].items():
            lines += [f"### {key.replace('_', ' ')} (constant: {split['constant_rmse_test']:.3f})", "",
                      "| model | τ (s) | RMSE train | RMSE held-out | fraction of constant | target |",
                      "|---|---|---|---|---|---|"]
            for r in split["rows"]:
                lines.append(f"| {r['model']} | {r['tau_s']:.2f} | {r['rmse_train']:.3f} | {r['rmse_test']:.3f} | "
                             f"{100 * r['fraction_of_constant']:.0f} % | {'met' if r['meets_target'] else 'not met'} |")
            lines += [""]
        pooled = w["pooled"]
        lines += [f"Pooled fit of '{BEST[0]}' on all flights: RMSE {pooled['rmse']:.3f}, τ = {pooled['tau_s']:.2f} s. "
                  f"Readings at the mean PWM and voltage, 95 % bootstrap over flights (n = {result['n_boot']}):", ""]
        for key, text in (("dfz_dV", "battery: m/s² per V at constant PWM"), ("percent_g_per_V", "battery: % of g per V"),
                          ("dfz_dsplit", "CW/CCW split: m/s² per unit duty of p1 − p2 + p3 − p4"),
                          ("dfz_dsum", "collective map slope: m/s² per unit of Σp")):
            lo, hi = pooled["intervals"][key]
            lines.append(f"- {text}: {pooled['readings'][key]:.3g} [{lo:.3g}, {hi:.3g}]")
        lines += [""]
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--bootstrap", type=int, default=200)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/crazyflie_thrust_map"))
    args = parser.parse_args(argv)
    started = time.perf_counter()
    flights, excluded = load(args.data)
    by_window = {"in flight": {f.name: flight_arrays(f) for f in flights}}
    # the airborne window: the same reader with the take-off/landing settle cut set to zero
    settle = align.TAKEOFF_SETTLE_S, align.LANDING_SETTLE_S
    align.TAKEOFF_SETTLE_S = align.LANDING_SETTLE_S = 0.0
    try:
        airborne, _ = load(args.data)
    finally:
        align.TAKEOFF_SETTLE_S, align.LANDING_SETTLE_S = settle
    by_window["airborne"] = {f.name: flight_arrays(f) for f in airborne if f.name in by_window["in flight"]}
    result = {"command": "python benchmarks/crazyflie_thrust_map.py "
                         + " ".join(argv if argv is not None else sys.argv[1:]),
              "flights_excluded": excluded, "n_boot": args.bootstrap,
              "windows": {name: window(by_window, name, args.bootstrap) for name in by_window}}
    result["seconds"] = time.perf_counter() - started
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "thrust_map.json").write_text(json.dumps(result, indent=1))
    (args.out / "thrust_map.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
