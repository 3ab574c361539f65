"""What is left of the body-z specific force after the best thrust map, and what does not explain it
(the held-out specific-force target on real NanoBench flights).

`crazyflie_thrust_map.py` ends at 0.128 m/s² held out (60-61 % of the constant 1 g, target ≤ 60 %) in
the in-flight window.  This benchmark asks three questions about the rest:

1. *Floor*: how well does the true specific force, R(q)ᵀ(p̈ + g e₃) from the mocap position, match the
   accelerometer after the same 5 Hz low-pass?  That is the score of a perfect model of the force, and
   it bounds what any thrust map can reach with this accelerometer.
2. *Shape*: the map's residual against that mocap force, per flight: mean offset, linear trend over the
   flight, and its spectrum in three bands (< 0.3 Hz, 0.3-1.5 Hz, > 1.5 Hz).
3. *Screen*: one candidate regressor at a time added to the best rung of the map's ladder (same motor
   lag τ as that rung's pooled fit, same low-pass), fitted on one family and scored on the other, both
   directions.  A candidate that helps both directions is a physical effect worth modelling; one that
   helps one direction only is fitting the family.

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/crazyflie_residual_screen.py
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

from learnest.ingest.frames import GRAVITY, quat_to_matrix
from learnest.models.crazyflie.identify import first_order_lag, flight_arrays, lowpass

sys.path.insert(0, str(Path(__file__).parent))
import crazyflie_thrust_map as thrust_map  # noqa: E402
from crazyflie_physics import DATA, family, load  # noqa: E402

OUT = Path(__file__).parent / "results" / "crazyflie_residual_screen"
FAMILIES = ("circle", "figure8")


def mocap_force_z(arrays) -> np.ndarray:
    """(T,) body-z specific force from the mocap velocity (already 5 Hz low-passed), m/s²."""
    acc_world = lowpass(np.gradient(arrays.v_world, arrays.dt, axis=0), arrays.dt)
    R = quat_to_matrix(arrays.u[:, :4])
    return np.einsum("tj,tj->t", R[:, :, 2], acc_world + np.array([0.0, 0.0, GRAVITY]))


def candidates(arrays, gyro: np.ndarray) -> dict[str, tuple[np.ndarray, str]]:
    """Candidate regressors of one flight (before lag and low-pass), each with its physical reading."""
    R = quat_to_matrix(arrays.u[:, :4])
    v_body = np.einsum("tji,tj->ti", R, arrays.v_world)
    p = arrays.u[:, 4:8] / 65535.0
    volts = arrays.u[:, 8]
    speed_xy = np.hypot(arrays.v_world[:, 0], arrays.v_world[:, 1])
    t = np.arange(len(volts)) * arrays.dt
    return {
        "|v_xy|": (speed_xy, "translational lift (horizontal airspeed)"),
        "|v_xy|²": (speed_xy**2, "translational lift, quadratic"),
        "v_bx² + v_by²": (v_body[:, 0] ** 2 + v_body[:, 1] ** 2, "body-frame in-plane airspeed squared"),
        "ω_x² + ω_y²": (gyro[:, 0] ** 2 + gyro[:, 1] ** 2, "roll/pitch rate (lever arm, blade flapping)"),
        "ω_z": (gyro[:, 2], "yaw rate, signed"),
        "|ω_z|": (np.abs(gyro[:, 2]), "yaw rate, unsigned"),
        "roll torque cmd": (p[:, 0] - p[:, 1] - p[:, 2] + p[:, 3], "differential thrust for roll"),
        "pitch torque cmd": (-p[:, 0] - p[:, 1] + p[:, 2] + p[:, 3], "differential thrust for pitch"),
        "d(Σp)/dt": (np.gradient(lowpass(p.sum(1), arrays.dt), arrays.dt), "motor transient beyond the lag"),
        "Σ(p·V)²": (((p * volts[:, None]) ** 2).sum(1), "thrust ∝ (duty·V)²"),
        "Σp³": ((p**3).sum(1), "cubic map"),
        "height z": (arrays.z, "height (ground/ceiling, mocap volume)"),
        "time in flight": (t, "motor heating or battery state beyond its voltage"),
        "V_start − V": (volts[arrays.keep].max() - volts, "battery sag since take-off"),
    }


def held_out(base, extra_index):
    """Held-out RMSE both directions with the base columns plus the chosen candidate columns."""
    scores = {}
    for train, test in (FAMILIES, FAMILIES[::-1]):
        def stack(fam):
            parts = [(np.column_stack([X] + [E[:, i] for i in extra_index]), y) for name, (X, y, E) in base.items()
                     if family(name) == fam]
            return np.vstack([p[0] for p in parts]), np.concatenate([p[1] for p in parts])
        X, y = stack(train)
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        Xs, ys = stack(test)
        scores[f"fit_{train}_score_{test}"] = float(np.sqrt(np.mean((Xs @ coef - ys) ** 2)))
    return scores


def main() -> int:
    start = time.perf_counter()
    flights, excluded = load(DATA)
    arrays = {f.name: flight_arrays(f) for f in flights}
    gyros = {}
    for f in flights:
        gyro = np.asarray(f.channels["gyro"], float)
        gyros[f.name] = np.deg2rad(gyro) if np.nanmax(np.abs(gyro)) > 20 else gyro   # deg/s logs
    names = thrust_map.BEST[1]
    coef, tau, pooled_rmse = thrust_map.fit(list(arrays.values()), names)

    floor, shape, base = {}, {}, {}
    for name, a in arrays.items():
        k = a.keep
        truth = mocap_force_z(a)
        floor[name] = float(np.sqrt(np.mean((truth - a.acc_body[:, 2])[k] ** 2)))
        cols = thrust_map.columns(a)
        X = lowpass(first_order_lag(np.column_stack([cols[n] for n in names]), tau, a.dt), a.dt)
        r = X @ coef - truth
        slow = lowpass(r, a.dt, 0.3)
        mid = lowpass(r, a.dt, 1.5) - slow
        t = np.arange(len(r)) * a.dt
        shape[name] = {"rms": float(np.sqrt(np.mean(r[k] ** 2))), "mean": float(r[k].mean()),
                       "trend_per_30s": float(30 * np.polyfit(t[k], r[k], 1)[0]),
                       "below_0.3Hz": float(np.sqrt(np.mean(slow[k] ** 2))),
                       "0.3_to_1.5Hz": float(np.sqrt(np.mean(mid[k] ** 2))),
                       "above_1.5Hz": float(np.sqrt(np.mean((r - slow - mid)[k] ** 2)))}
        extra = candidates(a, gyros[name])
        E = lowpass(first_order_lag(np.column_stack([v for v, _ in extra.values()]), tau, a.dt), a.dt)
        base[name] = (X[k], a.acc_body[k, 2], E[k])
    labels = list(candidates(next(iter(arrays.values())), next(iter(gyros.values()))).items())
    screen = [{"candidate": "(none: the map alone)", "reading": "", **held_out(base, [])}]
    for i, (label, (_, reading)) in enumerate(labels):
        screen.append({"candidate": label, "reading": reading, **held_out(base, [i])})
    constants = {}
    for fam in FAMILIES:
        y = np.concatenate([a.acc_body[a.keep, 2] for n, a in arrays.items() if family(n) == fam])
        constants[fam] = float(np.sqrt(np.mean((GRAVITY - y) ** 2)))
    result = {"command": "python benchmarks/crazyflie_residual_screen.py", "excluded": excluded,
              "map": {"terms": list(names), "tau_s": tau, "pooled_rmse": pooled_rmse}, "floor": floor,
              "shape": shape, "screen": screen, "constant_rmse": constants,
              "wall_s": time.perf_counter() - start}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "screen.json").write_text(json.dumps(result, indent=1))
    (OUT / "screen.md").write_text(markdown(result))
    print(markdown(result))
    return 0


def markdown(result: dict) -> str:
    lines = ["# What is left of body-z specific force after the best thrust map (NanoBench, in-flight window)", "",
             f"Command: `{result['command']}`  ({result['wall_s']:.0f} s wall)", "",
             f"Map: {', '.join(result['map']['terms'])}; τ = {result['map']['tau_s']:.2f} s; pooled RMSE "
             f"{result['map']['pooled_rmse']:.3f} m/s² (all flights).  Excluded: "
             + ("; ".join(f"{k} ({v})" for k, v in result["excluded"].items()) or "none"), "",
             "## Floor and residual shape, per flight (m/s², 5 Hz low-pass)", "",
             "Floor: mocap-derived specific force vs accelerometer (a perfect force model's score). Residual: "
             "the pooled map minus the mocap-derived force.", "",
             "| flight | floor | residual RMS | mean | trend / 30 s | < 0.3 Hz | 0.3-1.5 Hz | > 1.5 Hz |",
             "|---|---|---|---|---|---|---|---|"]
    for name in sorted(result["shape"]):
        s = result["shape"][name]
        lines.append(f"| {name} | {result['floor'][name]:.3f} | {s['rms']:.3f} | {s['mean']:+.3f} | "
                     f"{s['trend_per_30s']:+.3f} | {s['below_0.3Hz']:.3f} | {s['0.3_to_1.5Hz']:.3f} | "
                     f"{s['above_1.5Hz']:.3f} |")
    c = result["constant_rmse"]
    lines += ["", "## Screen: one candidate added to the map, held out by family (RMSE m/s²)", "",
              f"60 % of the constant: {0.6 * c['figure8']:.4f} on the figure-eights, {0.6 * c['circle']:.4f} on "
              "the circles.", "",
              "| candidate | reading | fit circle → figure8 | fit figure8 → circle |", "|---|---|---|---|"]
    for row in result["screen"]:
        lines.append(f"| {row['candidate']} | {row['reading']} | {row['fit_circle_score_figure8']:.4f} | "
                     f"{row['fit_figure8_score_circle']:.4f} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
