"""Identify the Crazyflie's input-driven physics from real flights: body-frame specific force predicted
from motor PWM, battery voltage, mocap attitude and velocity, scored against the accelerometer.

Protocol (the held-out specific-force target's): the accelerometer's body-frame z specific force and the model's
prediction are both low-passed at 5 Hz (2nd-order Butterworth, zero phase) and compared by RMSE (m/s²).
Samples the recorder interpolated across radio gaps are not measurements and are left out of every fit
and score, as are the first and last 0.5 s of each flight (the zero-phase filter's edges).  Fitting is
scipy's bounded least squares over all kept samples of the training flights; the model is
`models.crazyflie` (the same function the `crazyflie` system integrates), followed by the motor lag as
a first-order filter with time constant `tau_s`.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.ingest.frames import quat_to_matrix

from ..filters import LOWPASS_HZ, lowpass  # noqa: F401  (LOWPASS_HZ: the identification's, re-exported)
from .motor_heating import HISTORY_KEY, thermal_state
from .prior import BOUNDS, GRAVITY, PUBLIC, specific_force_body, thrust_acceleration

EDGE_S = 0.5
GAP_DILATION = 5          # samples either side of an interpolated row that are also left out


@dataclass
class FlightArrays:
    """What the fit needs from one flight, on its uniform grid (T rows)."""

    name: str
    dt: float
    acc_body: np.ndarray   # (T, 3) accelerometer, body frame, m/s², low-passed
    v_world: np.ndarray    # (T, 3) mocap velocity, m/s, low-passed
    z: np.ndarray          # (T,) height, m
    u: np.ndarray          # (T, 9) quaternion, 4 PWM, vbat
    keep: np.ndarray       # (T,) bool: samples that are measurements and away from the filter edges
    extra: dict = field(default_factory=dict)


def interpolated_rows(values: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Rows lying exactly on the straight line between their neighbours in every column: what linear
    resampling writes into a gap of a stream (a measured accelerometer sample never does)."""
    flags = np.zeros(len(values), dtype=bool)
    if len(values) >= 3:
        flags[1:-1] = np.all(np.abs(np.diff(values, 2, axis=0)) < tol, axis=1)
    return flags


def flight_arrays(flight: Flight, source: str = "pwm") -> FlightArrays:
    """Arrays for identification, the thrust columns from ``source`` (`models.crazyflie.THRUST_SOURCES`);
    raises ValueError naming the missing inputs."""
    from ..inputs import SOURCE_CHANNELS, thrust_columns  # inputs imports this module's neighbours

    missing = [name for name in (*SOURCE_CHANNELS[source], "acc_body") if name not in flight.channels]
    if missing:
        raise InvalidInput(f"{flight.name}: identification needs channel(s) {', '.join(missing)}")
    dt = flight.dt
    acc = np.asarray(flight.channels["acc_body"], float)
    gaps = interpolated_rows(acc)
    if gaps.mean() < 0.5:
        gaps = np.convolve(gaps.astype(float), np.ones(2 * GAP_DILATION + 1), "same") > 0
    # else the accelerometer was logged slower than the grid (a radio log at 10-50 Hz): most rows are
    # interpolated, and what is left out is only them, not their neighbours (the measured samples)
    keep = ~gaps
    edge = int(round(EDGE_S / dt))
    keep[:edge] = False
    keep[len(keep) - edge:] = False
    v = lowpass(np.gradient(flight.p, dt, axis=0), dt)
    # the mocap attitude as logged, not `models.inputs.system_inputs`' thrust-axis calibration: the body-z
    # specific force fitted here moves by cos(3°) - 1 < 0.2 % with it (only k_xy's v_b would see it), and
    # `models.crazyflie.IDENTIFIED` was fitted this way
    u = np.column_stack([flight.quat, thrust_columns(flight, source)])
    return FlightArrays(flight.name, dt, lowpass(acc, dt), v, flight.p[:, 2].copy(), u, keep,
                        {HISTORY_KEY: flight.meta[HISTORY_KEY]} if flight.meta.get(HISTORY_KEY) else {})


def first_order_lag(x: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """Exact discretisation of τ ẏ = x − y with x held over each step (y[k+1] from x[k], as the system
    integrates it), started at y = x[0]."""
    from scipy.signal import lfilter  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    if tau <= 1e-6:
        return x
    a = np.exp(-dt / tau)
    return lfilter([0.0, 1.0 - a], [1.0, -a], x - x[0], axis=0) + x[0]


def predict_body_force(arrays: FlightArrays, params: dict) -> np.ndarray:
    """(T, 3) body-frame specific force predicted from the inputs (the motors' heating applied when ``params``
    has ``kappa_th``, `models.crazyflie.motor_heating`), lagged by tau_s, low-passed."""
    f_b, _ = specific_force_body(list(arrays.v_world.T), arrays.z, list(arrays.u.T), params)
    f_b = np.column_stack([np.broadcast_to(c, arrays.z.shape) for c in f_b])
    if params.get("kappa_th"):
        # the thrust term × (1 − κ h), directly: smooth in every parameter a fit moves, gamma included (the
        # voltage route of `with_motor_heating` cannot carry it near gamma = 0)
        thrust = thrust_acceleration(arrays.z, list(arrays.u.T), params)
        h = thermal_state(arrays.u, arrays.dt, params["tau_th_s"], arrays.extra.get(HISTORY_KEY))
        f_b[:, 2] -= params["kappa_th"] * h * thrust
    return lowpass(first_order_lag(f_b, params.get("tau_s", 0.0), arrays.dt), arrays.dt)


@dataclass
class Variant:
    """Which parameters a fit frees (the rest stay at `base`), and whether ground effect is on."""

    name: str
    free: tuple
    base: dict = field(default_factory=lambda: {**PUBLIC, "r_m": 0.0, "tau_s": 0.0, "k_z": 0.0})


def _params(variant: Variant, theta) -> dict:
    return {**variant.base, **dict(zip(variant.free, theta))}


def z_residuals(theta, variant: Variant, flights: list[FlightArrays]) -> np.ndarray:
    params = _params(variant, theta)
    return np.concatenate([(predict_body_force(a, params)[:, 2] - a.acc_body[:, 2])[a.keep] for a in flights])


def fit_z(variant: Variant, flights: list[FlightArrays], start: dict | None = None) -> dict:
    """Bounded least squares of the free parameters on body-z specific force; returns all params."""
    from scipy.optimize import least_squares  # scipy.optimize costs ~1 s to import: loaded on first use

    start = {**variant.base, "m_kg": 0.03, "gamma": 1.0, "tau_s": 0.05, **(start or {})}
    x0 = [start[k] for k in variant.free]
    lower = [BOUNDS[k][0] for k in variant.free]
    upper = [BOUNDS[k][1] for k in variant.free]
    x0 = np.clip(x0, np.add(lower, 1e-9), np.subtract(upper, 1e-9))
    solution = least_squares(z_residuals, x0, bounds=(lower, upper), args=(variant, flights), x_scale="jac")
    return _params(variant, solution.x)


def fit_k_xy(params: dict, flights: list[FlightArrays]) -> dict:
    """k_xy from the body x/y specific force, which rotor drag alone predicts: f = −k_xy v_b + bias.

    A per-axis bias is fitted with it (an accelerometer offset or tilt would otherwise be read as drag)
    and reported, not used by the prediction."""
    rows, target = [], []
    for axis in (0, 1):
        for arrays in flights:
            R = quat_to_matrix(arrays.u[:, :4])
            vb = np.einsum("tji,tj->ti", R, arrays.v_world)
            keep = arrays.keep
            design = np.zeros((keep.sum(), 3))
            design[:, 0] = -first_order_lag(vb[:, axis], params.get("tau_s", 0.0), arrays.dt)[keep]
            design[:, 1 + axis] = 1.0
            rows.append(design)
            target.append(arrays.acc_body[keep, axis])
    coef, *_ = np.linalg.lstsq(np.vstack(rows), np.concatenate(target), rcond=None)
    return {"k_xy": float(coef[0]), "bias_x": float(coef[1]), "bias_y": float(coef[2])}


def rmse_z(params: dict, flights: list[FlightArrays]) -> float:
    err = np.concatenate([(predict_body_force(a, params)[:, 2] - a.acc_body[:, 2])[a.keep] for a in flights])
    return float(np.sqrt(np.mean(err**2)))


def rmse_constant(flights: list[FlightArrays]) -> float:
    """RMSE of predicting the body z specific force as a constant 1 g (hover, level)."""
    err = np.concatenate([(GRAVITY - a.acc_body[:, 2])[a.keep] for a in flights])
    return float(np.sqrt(np.mean(err**2)))


def r2_z(params: dict, flights: list[FlightArrays]) -> float:
    pred = np.concatenate([predict_body_force(a, params)[:, 2][a.keep] for a in flights])
    meas = np.concatenate([a.acc_body[:, 2][a.keep] for a in flights])
    return float(1.0 - np.sum((pred - meas) ** 2) / np.sum((meas - meas.mean()) ** 2))


# The ablation ladder: each rung frees one more physical effect.
VARIANTS = (
    Variant("pwm map + mass", ("m_kg",)),
    Variant("+ battery voltage (gamma)", ("m_kg", "gamma")),
    Variant("+ quadratic PWM term (q_pwm2)", ("m_kg", "gamma", "q_pwm2")),
    Variant("+ motor lag (tau_s)", ("m_kg", "gamma", "q_pwm2", "tau_s")),
    Variant("+ rotor drag z (k_z)", ("m_kg", "gamma", "q_pwm2", "tau_s", "k_z")),
    Variant("+ ground effect (r_m fitted)", ("m_kg", "gamma", "q_pwm2", "tau_s", "k_z", "r_m")),
)
FULL = VARIANTS[4]
