"""Can the crazyswarm2 uSD logs tell the thrust command's scale from the vehicle's mass through the rotation?

Position and accelerometer measure only thrust made over mass, so a thrust command k times the thrust made and a
vehicle 1/k as heavy look the same.  The rotation could break the tie: the logs carry the Lee controller's
torque commands (``ctrlLee.torquex/y``, N·m) and the gyro (``ctrlLee.omegax/y``, rad/s).  The motors turn the
torque commands into force through the same map as the thrust command, so their scale is the same k.  With the
published inertia the angular acceleration then gives k: J ω̇ = k·τ_cmd, after the motors' lag.  This script
fits k per log and axis: ω̇ by a Savitzky–Golay derivative, both sides low-passed (zero phase) at 2, 5 and
10 Hz, the command lagged by 0-60 ms.  It keeps the best R² per log and axis; the fit is over contiguous
stretches of the flight (the card drops records).

Run from the repository root (needs ../shared/data, a few seconds):
    .venv/bin/python benchmarks/crazyswarm2_torque_scale.py > benchmarks/results/crazyswarm2_torque_scale.md
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.signal import butter, filtfilt, savgol_filter

from learnest.ingest.formats.crazyflie_usd.decoder import decode
from learnest.models.crazyflie.identify import first_order_lag

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "crazyswarm2-tools"
# crazyflie-firmware, src/modules/src/controller/controller_lee.c: the Lee controller's inertia (kg·m²)
J_XY = (16.571710e-6, 16.655602e-6)
DT = 0.004               # the logs' 250 Hz
FLYING_N = 0.2           # a thrust command above this: in the air
CUTOFFS_HZ = (2.0, 5.0, 10.0)
LAGS_S = (0.0, 0.02, 0.04, 0.06)


def _stretches(log) -> list[np.ndarray]:
    t = np.asarray(log["t"], dtype=float)
    thrust = np.asarray(log["ctrlLee.thrustSI"], dtype=float)
    pieces = np.split(np.arange(len(t)), np.where(np.diff(t) > 1.5 * DT)[0] + 1)
    return [k for k in pieces if len(k) >= 400 and thrust[k].min() > FLYING_N]


def best_fit(log, axis: int) -> dict:
    """The scale k with the highest R² over the cutoffs and lags, for one axis (0: x, 1: y)."""
    name = "xy"[axis]
    best = {"r2": -np.inf}
    for cutoff in CUTOFFS_HZ:
        b, a = butter(2, cutoff / (0.5 / DT))
        for lag in LAGS_S:
            xs, ys = [], []
            for k in _stretches(log):
                omega = np.asarray(log[f"ctrlLee.omega{name}"], dtype=float)[k]
                torque = first_order_lag(np.asarray(log[f"ctrlLee.torque{name}"], dtype=float)[k], lag, DT)
                xs.append(filtfilt(b, a, torque)[100:-100] / J_XY[axis])
                ys.append(filtfilt(b, a, savgol_filter(omega, 11, 3, deriv=1, delta=DT))[100:-100])
            x, y = np.concatenate(xs), np.concatenate(ys)
            design = np.column_stack([x, np.ones_like(x)])
            coef, *_ = np.linalg.lstsq(design, y, rcond=None)
            r2 = 1.0 - np.var(y - design @ coef) / np.var(y)
            if r2 > best["r2"]:
                best = {"k": float(coef[0]), "r2": float(r2), "cutoff_hz": cutoff, "lag_s": lag}
    return best


def main() -> None:
    print("# crazyswarm2 log182-184: the thrust command's scale from the rotation\n")
    print("k: angular acceleration over (torque command / published inertia); 1 if the commands are the torques "
          "made, 0.625 if they over-promise as the thrust command does.  R²: the share of the angular "
          "acceleration's variance the torque command explains.\n")
    print("| log | axis | k | R² | low-pass (Hz) | lag (s) |")
    print("|---|---|---|---|---|---|")
    fits = []
    for n in (182, 183, 184):
        log = decode(DATA / f"log{n}").events["fixedFrequency"]
        for axis in (0, 1):
            fits.append(fit := best_fit(log, axis))
            print(f"| log{n} | {'xy'[axis]} | {fit['k']:.3f} | {fit['r2']:.2f} | {fit['cutoff_hz']:g} "
                  f"| {fit['lag_s']:g} |")
    ks, r2s = [f["k"] for f in fits], [f["r2"] for f in fits]
    print(f"\nk from {min(ks):.3f} to {max(ks):.3f}, negative in {sum(k < 0 for k in ks)} of {len(ks)} fits; "
          f"R² at most {max(r2s):.2f}.  A scale near 0.6-1 explaining most of the rotation would have broken the tie. "
          "What correlates here is likely the controller reacting to the rotation (its rate damping), not the rotation "
          "following the command, so these logs give no scale and no mass.")


if __name__ == "__main__":
    main()
