"""Motor heating in the Crazyflie prior: thrust per (PWM, volt) falls as the brushed motors warm over a flight.

Physics: the copper's resistance rises (+0.39 %/K) and the magnets weaken as a motor warms, so the same duty
at the same battery voltage gives less thrust.  The logs carry no temperature; a first-order thermal state
driven by the electrical power the motors turn into heat stands in for it,

    tau_th_s · h' = P − h,    P = Σ_i (p_i V)² / P_REF,    thrust × (1 − kappa_th · h),

with p_i = PWM_i / 65535 and V the battery voltage (p_i V is the voltage a motor sees, (p_i V)² / R the heat it
makes).  `P_REF_V2` is Σ_i (p_i V)² of NanoBench's vehicle hovering at V_ref by the identified thrust map, a
fixed electrical scale (a payload makes the motors work harder and warm faster, it does not change P_REF), so
h → 1 in a long hover of that vehicle and kappa_th is the fraction of thrust it then loses.

Causal and from the inputs alone: h starts cold at the record's first sample and is integrated forward from
the PWM and voltage (exact discretisation, inputs held over a step).  A record cut from a longer flight
(`models.inputs.slice_keeping_heat`, the diagnosis's held-out part of one flight) carries the motor power
before the cut in its meta (`HISTORY_KEY`), and starts as warm as the flight was there.  The parameters are the prior's
(`models.crazyflie`: `kappa_th`, `tau_th_s`; a prior without them has no heating).  Heating is not a function
of (x, u) at one instant, so it is applied to the inputs: through the battery voltage the prior sees,
V → V·(1 − kappa_th h)^(1/gamma), which multiplies the prior's thrust by (1 − kappa_th h) exactly and keeps
the inputs' shape (stored models, generated code).  The per-flight thrust gain (`models.crazyflie.thrust_gain`) is
calibrated after it, so the gain takes the flight's level and the heating the drift within it.

Identified on the NanoBench flights, pooled (the mocap's body-z specific force against the prior's, a free gain
per flight, cold start at the flying window's start; the values are `models.crazyflie.IDENTIFIED`'s).  The two
trade off: flights of 20-40 s determine only their ratio, the drift rate from cold, so the diagnosis moves
kappa_th alone.  The held-out evidence is on the results page `docs/results/transfer.md` ("What the Crazyflie
prior and residual are given"); a state carried over between flights in flying order is on
`docs/results/thrust-maps.md` ("Motor heating").
"""
from __future__ import annotations

import numpy as np

from . import prior as cf

MIN_GAMMA = 0.1   # below this |gamma| the battery voltage cannot carry a thrust factor (thrust_gain too)

PWM_FULL_SCALE = 65535.0
# Flight.meta: P of every sample before a slice's first, oldest first (a plain Flight.slice drops it)
HISTORY_KEY = "motor_power_before"
PWM = slice(4, 8)
VBAT = cf.INPUT_NAMES.index("vbat")


def hover_power(params: dict) -> float:
    """Σ_i (p_i V)² of the four motors hovering at V_ref by the thrust map ``params``, V²."""
    duty = cf.hover_pwm(params) / PWM_FULL_SCALE
    return 4.0 * (duty * params.get("v_ref", cf.V_REF)) ** 2


# the electrical power scale of h, V²: NanoBench's vehicle hovering at V_ref (`hover_power(cf.IDENTIFIED)` when
# kappa_th was identified).  A number, not that call: a stored kappa_th means a loss per unit of this h, which
# must not move if the thrust map's parameters are ever refitted.
P_REF_V2 = 36.72689857119545


def motor_power(u: np.ndarray) -> np.ndarray:
    """P = Σ_i (p_i V)² / `P_REF_V2`, the drive of the thermal state, for inputs ``u`` of shape (..., 9)."""
    u = np.asarray(u, dtype=float)
    return ((u[..., PWM] / PWM_FULL_SCALE * u[..., [VBAT]]) ** 2).sum(axis=-1) / P_REF_V2


def thermal_state(u: np.ndarray, dt: float, tau_th_s: float, power_before=None) -> np.ndarray:
    """The motors' thermal state over a record, cold at its first sample unless its history is given.

    Parameters
    ----------
    u : ndarray, shape (T, 9)
        `models.crazyflie.INPUT_NAMES` inputs: attitude, PWM of motors 1..4 (0-65535), battery voltage (V).
    dt : float
        Sample time, s.
    tau_th_s : float
        Thermal time constant, s.
    power_before : array_like, shape (T0,), optional
        `motor_power` of the T0 samples before the record (same grid), oldest first: the flight it was cut from.

    Returns
    -------
    ndarray, shape (T,)
        h, 1 at the steady state of the reference hover (`P_REF_V2`); h[k] uses the inputs before sample k
        only; h[0] = 0 without a history.
    """
    from scipy.signal import lfilter  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    before = np.zeros(0) if power_before is None else np.asarray(power_before, dtype=float).reshape(-1)
    decay = np.exp(-dt / tau_th_s)
    power = np.concatenate([before, motor_power(u)])
    h, _ = lfilter([0.0, 1.0 - decay], [1.0, -decay], power, zi=[0.0])   # h[k+1] = decay h[k] + (1-decay) P[k]
    return h[len(before):]


def with_motor_heating(u: np.ndarray, dt: float, params: dict, power_before=None) -> tuple[np.ndarray, float]:
    """The inputs with the battery voltage scaled so the prior's thrust carries the heating loss (1 − κ h).

    Parameters
    ----------
    u : ndarray, shape (T, 9)
        `models.crazyflie.INPUT_NAMES` inputs.
    dt : float
        Sample time, s.
    params : dict
        The prior's parameters: ``kappa_th`` (1; absent or 0: no heating), ``tau_th_s`` (s) and ``gamma``
        (below `MIN_GAMMA` in magnitude the voltage cannot carry the loss: none applied).
    power_before : array_like, optional
        The record's history, as `thermal_state` takes it (a slice's ``meta[HISTORY_KEY]``).

    Returns
    -------
    (ndarray, shape (T, 9), float)
        A copy of u, voltage column scaled; the largest thrust loss over the record, % (0 when none applied).
    """
    u = np.array(u, dtype=float)
    kappa, gamma = float(params.get("kappa_th", 0.0)), float(params["gamma"])
    if abs(gamma) < MIN_GAMMA or kappa == 0.0 or len(u) == 0:
        return u, 0.0
    factor = 1.0 - kappa * thermal_state(u, dt, float(params["tau_th_s"]), power_before)
    factor = np.clip(factor, 0.5, 1.0)   # h is bounded by the motors' full power; never more than half the thrust
    u[:, VBAT] *= factor ** (1.0 / gamma)
    return u, float(100.0 * (1.0 - factor.min()))
