"""A motor-temperature proxy for the NanoBench flights, from the inputs only (the thrust drift).

Brushed motors lose thrust per (duty, volt) as they warm: the copper's resistance rises (+0.39 %/K) and the
magnets weaken.  The logs carry no temperature, so this builds a first-order thermal state driven by the
electrical power the motors draw at a fixed winding resistance,

    τ_th h' = P − h,    P = Σ_i (p_i V)² / P_hover,

with p_i = PWM_i / 65535 and V the battery voltage: p_i V is the voltage the motor sees, and (p_i V)² / R
the power it turns into heat.  P is scaled by its median over every log's motors-on samples (P_hover), so
h = 1 is the steady state of hovering, whatever τ_th.  The alternative Σ_i p_i V (∝ the power at a fixed
current-to-voltage ratio) is kept for comparison (`POWER_PROXIES`).

The state runs over the *whole* recording, the time on the ground included (motors at 0 there), not just
the flying window the benchmarks score.  Two initial states:

- ``cold``: h = 0 at the start of each log (each flight on its own; τ_th shared);
- ``carried``: every log of the session in flying order (by the absolute time stamps ``t``), each starting
  from the state the previous one ended with, decayed by exp(−gap/τ_th) over the time between the logs
  (motors assumed off between recordings).  All 17 logs heat the motors, B2_circle_medium_rep3 included
  (excluded from scoring, but it was flown).  This uses *earlier flights' inputs* (PWM and battery
  voltage), which a logger on the vehicle would have; never an accelerometer or a mocap force.

The motor and battery columns are cleaned with the NanoBench reader's own rule (`clean_stream`): the
recorder extrapolated streams which ended early (B2_circle_medium_rep3's motors end at 31.3 s and run
linearly to 1.9 million PWM by 42 s), and such rows are not measurements.  Where a log has no motor sample
(that one tail) the motors are taken at the log's mean airborne duty while the mocap says it still flies
(6.9 s) and at 0 after.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from learnest.ingest.align import FLYING_HEIGHT_M
from learnest.ingest.formats.nanobench.reader import clean_stream

MOTOR_COLUMNS = tuple(f"motor_motor_m{i}" for i in range(1, 5))
GRID_S = 0.01                 # the recordings' own 10 ms grid
MOTORS_ON = 0.2               # Σp above this: the motors run (take-off for "time since the motors started")
POWER_PROXIES = {
    "Σ(p·V)²": lambda p, v: ((p * v[:, None]) ** 2).sum(1),
    "Σ p·V": lambda p, v: (p * v[:, None]).sum(1),
}


@dataclass
class Log:
    """One NanoBench recording on a uniform grid: absolute time (Unix s), duty (T, 4), battery volts (T,)."""

    name: str
    t: np.ndarray
    duty: np.ndarray
    volts: np.ndarray
    motor_tail_filled_s: float

    @property
    def motors_start(self) -> float:
        """Unix time at which the motors first ran (s)."""
        return float(self.t[np.argmax(self.duty.sum(1) > MOTORS_ON)])


def read_log(path: Path) -> Log:
    """The inputs of one NanoBench CSV over the whole recording, cleaned as the reader cleans them."""
    table = pd.read_csv(path, usecols=["t", "pz", *MOTOR_COLUMNS, "pwr_pm_vbat"])
    t = table["t"].to_numpy(float)
    grid = np.arange(t[0], t[-1], GRID_S)
    t_m, motors, _ = clean_stream("motors", t, table[list(MOTOR_COLUMNS)].to_numpy(float))
    t_v, volts, _ = clean_stream("vbat", t, table[["pwr_pm_vbat"]].to_numpy(float))
    duty = np.column_stack([np.interp(grid, t_m, motors[:, i]) for i in range(4)]) / 65535.0
    volts = np.interp(grid, t_v, volts[:, 0])          # a battery tail the logger missed: held
    z = np.interp(grid, t, table["pz"].to_numpy(float))
    airborne = z > np.median(z[grid <= grid[0] + 0.5]) + FLYING_HEIGHT_M
    unknown = (grid < t_m[0]) | (grid > t_m[-1])
    if unknown.any():
        duty[unknown] = np.where(airborne[unknown, None], duty[airborne & ~unknown].mean(0), 0.0)
    return Log(path.stem, grid, duty, volts, float((unknown & airborne).sum() * GRID_S))


def read_logs(data_dir: Path) -> list[Log]:
    """Every NanoBench log under data_dir/nanobench, in flying order (by absolute start time)."""
    logs = [read_log(path) for path in sorted((data_dir / "nanobench").glob("B*.csv"))]
    return sorted(logs, key=lambda log: log.t[0])


def hover_power(logs: list[Log], proxy: str) -> float:
    """Median of the power proxy over every log's motors-on samples (the scale that makes h = 1 hover)."""
    power = POWER_PROXIES[proxy]
    return float(np.median(np.concatenate([power(g.duty, g.volts)[g.duty.sum(1) > 2.0] for g in logs])))


def thermal_states(logs: list[Log], tau_th: float, proxy: str = "Σ(p·V)²", carried: bool = True,
                   scale: float | None = None) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """name -> (Unix time (T,), h (T,)): the thermal state of each log, h = 1 at steady hover.

    Exact discretisation of τ_th h' = P − h with P held over each 10 ms step.  ``carried``: each log starts
    from the previous log's last state decayed over the gap between them; else from 0."""
    from scipy.signal import lfilter

    scale = hover_power(logs, proxy) if scale is None else scale
    a = np.exp(-GRID_S / tau_th)
    out, h_end, t_end = {}, 0.0, None
    for log in logs:
        h0 = h_end * np.exp(-(log.t[0] - t_end) / tau_th) if carried and t_end is not None else 0.0
        drive = POWER_PROXIES[proxy](log.duty, log.volts) / scale
        h, _ = lfilter([0.0, 1.0 - a], [1.0, -a], drive, zi=[h0])    # h[0] = h0, h[k+1] = a h[k] + (1-a) P[k]
        out[log.name] = (log.t, h)
        h_end, t_end = float(h[-1]), float(log.t[-1])
    return out
