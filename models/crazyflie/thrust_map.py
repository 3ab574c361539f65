"""The Crazyflie's thrust map identified from flights: body-frame z specific force from the inputs alone,
linear in its coefficients (a least-squares fit: no local minima, every smaller term set exactly nested).

    f_z = b + c1 Σp + c2 Σp² + cs (p1 − p2 + p3 − p4) + d1 V + d2 V Σp + d3 V² + e1 (1 − R₃₃) + e2 v_z⁺ + e3 v_z⁻

with p_i = PWM_i / 65535, V the battery voltage (V) through a first-order filter of time constant
``vbat_tau_s``, R₃₃ the cosine of the tilt and v_z± the climb and descent speeds (m/s, world frame).  Every
column then goes through the motor lag (first order, ``tau_s``) and the protocol's 5 Hz low-pass
(`models.crazyflie.identify`), as the physics prior's prediction does.  Both time constants are picked from grids on
the training flights only.

Why these terms (held-out evidence in `docs/results/thrust-maps.md`): the summed duty's
quadratic map and the battery polynomial are the physics prior's thrust map made linear; the CW/CCW split
carries thrust the collective does not (most likely the transients of the yaw loop); tilt and climb/descent
are the airframe's inflow.  Why the battery filter: the logged voltage carries centivolts of fast
fluctuation (the 10-Hz power stream resampled to 100 Hz, ADC noise, load sag) that the thrust does not follow;
fed raw, it is noise in a regressor.  Filtered over about a second it is the battery's state, and the held-out
error on real flights falls.  The voltage filter and the motor lag are causal; the 5 Hz low-pass is the
evaluation protocol's (zero phase, applied alike to every column and to the measured force), so the fitted
coefficients also hold for the unfiltered, causal map.

Physical parameters (mass, voltage exponent) are not read off this map: it is the identified *predictor* of
the thrust; `models.crazyflie` is the physical model with named, bounded parameters.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.frames import GRAVITY, quat_to_matrix

from . import prior as cf
from .identify import FlightArrays, first_order_lag, lowpass, rmse_constant

__all__ = ["TERMS", "BenchMap", "ThrustMap", "columns", "design", "fit_bench_map", "fit_thrust_map", "r2", "readings",
           "rmse_constant", "stacked"]

TERMS = ("1", "Σp", "Σp^2", "split", "V", "V·Σp", "V^2", "tilt", "vz+", "vz-")
# Motor lags a 7-mm brushed motor can have (tens of ms).  A longer grid lets the training fit absorb slow drift
# into the lag on some flights, and the held-out error grows: the lag stays a motor lag.
MOTOR_TAUS_S = (0.0, 0.02, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08, 0.10)
# 0 keeps the voltage as logged; the grid spans the fast part (0.25 s) to the battery's slow state (5 s)
VBAT_TAUS_S = (0.0, 0.25, 0.5, 1.0, 2.0, 5.0)


def columns(arrays: FlightArrays, vbat_tau_s: float = 0.0) -> dict[str, np.ndarray]:
    """Every candidate regressor of one flight on its grid, (T,) each, before motor lag and low-pass.

    Terms: ``1``, ``Σp``, ``Σp^2``, ``split`` (p1 − p2 + p3 − p4), ``V``, ``V·Σp``, ``V^2``, ``tilt``
    (1 − R₃₃), ``vz+``/``vz-`` (m/s), and per motor ``p1``..``p4``, ``p1^2``..``p4^2``; p is PWM / 65535,
    V the battery voltage (V) filtered with time constant ``vbat_tau_s`` (s; 0: as logged)."""
    p = arrays.u[:, 4:8] / 65535.0
    volts = first_order_lag(arrays.u[:, 8], vbat_tau_s, arrays.dt)
    R33 = quat_to_matrix(arrays.u[:, :4])[:, 2, 2]
    vz = arrays.v_world[:, 2]
    total = p.sum(1)
    out = {"1": np.ones(len(volts)), "Σp": total, "Σp^2": (p**2).sum(1), "split": p[:, 0] - p[:, 1] + p[:, 2] - p[:, 3],
           "V": volts, "V·Σp": volts * total, "V^2": volts**2, "tilt": 1.0 - R33,
           "vz+": np.maximum(vz, 0.0), "vz-": np.minimum(vz, 0.0)}
    for i in range(4):
        out[f"p{i + 1}"] = p[:, i]
        out[f"p{i + 1}^2"] = p[:, i] ** 2
    return out


def design(arrays: FlightArrays, terms: tuple, tau_s: float, vbat_tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(kept rows, len(terms)) design matrix (lagged, low-passed) and the measured body-z specific force
    (m/s²) on those rows."""
    cols = columns(arrays, vbat_tau_s)
    X = np.column_stack([cols[name] for name in terms])
    X = lowpass(first_order_lag(X, tau_s, arrays.dt), arrays.dt)
    return X[arrays.keep], arrays.acc_body[arrays.keep, 2]


def stacked(flights: list[FlightArrays], terms: tuple, tau_s: float,
            vbat_tau_s: float) -> tuple[np.ndarray, np.ndarray]:
    """`design` of several flights, rows stacked."""
    parts = [design(a, terms, tau_s, vbat_tau_s) for a in flights]
    return np.vstack([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


@dataclass
class ThrustMap:
    """An identified thrust map: coefficients of ``terms`` (m/s² per unit of each term), the motor lag
    ``tau_s`` (s), the battery-voltage filter ``vbat_tau_s`` (s) and the training RMSE (m/s²)."""

    terms: tuple
    coef: np.ndarray
    tau_s: float
    vbat_tau_s: float
    rmse_train: float

    def rmse(self, flights: list[FlightArrays]) -> float:
        """RMSE (m/s²) of the predicted body-z specific force on the kept samples of ``flights``."""
        X, y = stacked(flights, self.terms, self.tau_s, self.vbat_tau_s)
        return float(np.sqrt(np.mean((X @ self.coef - y) ** 2)))

    def predict(self, arrays: FlightArrays) -> np.ndarray:
        """Predicted body-z specific force (m/s²) on every sample of one flight, (T,)."""
        cols = columns(arrays, self.vbat_tau_s)
        X = np.column_stack([cols[name] for name in self.terms])
        return lowpass(first_order_lag(X, self.tau_s, arrays.dt), arrays.dt) @ self.coef


def fit_thrust_map(flights: list[FlightArrays], terms: tuple = TERMS, motor_taus_s: tuple = MOTOR_TAUS_S,
                   vbat_taus_s: tuple = VBAT_TAUS_S,
                   progress: Callable[[int, int], object] | None = None) -> ThrustMap:
    """Least squares of ``terms`` on the training ``flights``; the two time constants are the grid pair with
    the lowest training RMSE (the training flights only: a held-out score stays held out).  ``progress`` is
    called as ``progress(grid points done, grid points)`` after each pair.

    Raises
    ------
    ValueError
        If no flight has a kept sample.
    """
    if not sum(int(a.keep.sum()) for a in flights):
        raise InvalidInput("thrust map: the flights have no usable samples")
    best = None
    grid = [(vbat_tau, tau) for vbat_tau in vbat_taus_s for tau in motor_taus_s]
    for done, (vbat_tau, tau) in enumerate(grid, start=1):
        X, y = stacked(flights, terms, tau, vbat_tau)
        coef, *_ = np.linalg.lstsq(X, y, rcond=None)
        rmse = float(np.sqrt(np.mean((X @ coef - y) ** 2)))
        if best is None or rmse < best.rmse_train:
            best = ThrustMap(tuple(terms), coef, tau, vbat_tau, rmse)
        if progress:
            progress(done, len(grid))
    assert best is not None
    return best


def readings(thrust_map: ThrustMap, flights: list[FlightArrays]) -> dict[str, float]:
    """The map's slopes at the mean PWM and voltage of ``flights`` (kept samples), for a map with the full
    `TERMS`:

    - ``dfz_dV``: m/s² per volt of battery at constant PWM (``percent_g_per_V``: the same in % of g);
    - ``dfz_dsplit``: m/s² per unit of the CW/CCW duty split p1 − p2 + p3 − p4 (the yaw command);
    - ``dfz_dsum``: m/s² per unit of the summed duty Σp (the collective map's slope)."""
    c = dict(zip(thrust_map.terms, thrust_map.coef))
    p = np.concatenate([a.u[a.keep, 4:8] for a in flights]) / 65535.0
    volts = float(np.mean(np.concatenate([a.u[a.keep, 8] for a in flights])))
    total = float(p.sum(1).mean())
    dV = c["V"] + c["V·Σp"] * total + 2 * c["V^2"] * volts
    # Σp² ≈ (Σp)²/4 near equal motors: d(Σp²)/d(Σp) = 2 p_i = Σp / 2
    dsum = c["Σp"] + c["Σp^2"] * total / 2 + c["V·Σp"] * volts
    return {"dfz_dV": float(dV), "percent_g_per_V": float(100 * dV / GRAVITY), "dfz_dsplit": float(c["split"]),
            "dfz_dsum": float(dsum)}


def r2(thrust_map: ThrustMap, flights: list[FlightArrays]) -> float:
    """Coefficient of determination of the prediction on the kept samples of ``flights`` (pooled)."""
    X, y = stacked(flights, thrust_map.terms, thrust_map.tau_s, thrust_map.vbat_tau_s)
    return float(1.0 - np.sum((X @ thrust_map.coef - y) ** 2) / np.sum((y - y.mean()) ** 2))


# -- a bench calibration: thrust measured on a load cell against PWM or rotor speed -------------------------
@dataclass
class BenchMap:
    """One motor's static thrust map from a bench calibration, T = (c2 x² + c1 x + c0)·(V / V_ref)^gamma.

    ``kind`` "pwm" (x = PWM, 0..65535) or "rpm" (x = rotor speed in rad/s); ``coef`` (c2, c1, c0) in N per
    unit of x², x, 1; ``gamma`` the voltage exponent (None: no voltage column, or too little spread);
    ``rmse_n`` the fit's RMSE, N; ``gain_vs_prior`` the measured thrust over the prior's map (Förster's) at
    the measured points, summed; ``n`` the rows used."""

    kind: str
    coef: tuple
    gamma: float | None
    rmse_n: float
    gain_vs_prior: float
    n: int

    def thrust(self, x: np.ndarray, vbat: np.ndarray | None = None) -> np.ndarray:
        """Thrust of one motor, N, at x (PWM or rad/s) and battery voltage (V; None: V_ref)."""
        c2, c1, c0 = self.coef
        out = c2 * np.asarray(x, float) ** 2 + c1 * np.asarray(x, float) + c0
        if self.gamma is not None and vbat is not None:
            out = out * (np.asarray(vbat, float) / cf.V_REF) ** self.gamma
        return out


# a voltage column with less spread than this cannot tell an exponent from the map's own scale
MIN_BENCH_VOLTAGE_SPREAD_V = 0.2


def fit_bench_map(kind: str, x: np.ndarray, thrust_n: np.ndarray, vbat: np.ndarray | None = None) -> BenchMap:
    """Least squares of a bench calibration of one motor (see `BenchMap`).

    Parameters
    ----------
    kind : {"pwm", "rpm"}
    x : ndarray, shape (n,)
        PWM (0..65535) or rotor speed, rad/s.
    thrust_n : ndarray, shape (n,)
        Measured thrust of that motor, N.
    vbat : ndarray, shape (n,), optional
        Battery voltage, V; an exponent is fitted when it spreads over `MIN_BENCH_VOLTAGE_SPREAD_V`.

    Raises
    ------
    ValueError
        Fewer than 4 rows, or x that does not vary.
    """
    from scipy.optimize import least_squares  # scipy.optimize costs ~1 s to import: loaded on first use

    x, thrust_n = np.asarray(x, float), np.asarray(thrust_n, float)
    if len(x) < 4 or np.ptp(x) <= 0:
        raise InvalidInput(f"a bench calibration needs at least 4 rows over several {kind} values, got {len(x)}")
    fit_gamma = vbat is not None and np.ptp(vbat) >= MIN_BENCH_VOLTAGE_SPREAD_V
    ratio = np.asarray(vbat, float) / cf.V_REF if fit_gamma else np.ones_like(x)
    scale = float(np.max(np.abs(x)))

    def residual(theta):
        c2, c1, c0, gamma = theta
        xs = x / scale
        return (c2 * xs**2 + c1 * xs + c0) * ratio ** gamma - thrust_n

    start = np.r_[np.polyfit(x / scale, thrust_n, 2), 1.0 if fit_gamma else 0.0]
    theta = least_squares(residual, start).x if fit_gamma else start
    c2, c1, c0 = theta[0] / scale**2, theta[1] / scale, theta[2]
    pwm = x if kind == "pwm" else (x - cf.FOERSTER_OMEGA_OFFSET) / cf.FOERSTER_OMEGA_SLOPE
    prior = cf.FOERSTER_A2 * pwm**2 + cf.FOERSTER_A1 * pwm + cf.FOERSTER_A0
    if fit_gamma:
        prior = prior * ratio ** cf.PUBLIC["gamma"]
    return BenchMap(kind, (float(c2), float(c1), float(c0)), float(theta[3]) if fit_gamma else None,
                    float(np.sqrt(np.mean(residual(theta) ** 2))), float(np.sum(thrust_n) / np.sum(prior)), len(x))
