"""The Crazyflie prior's thrust gain on one flight: one number, calibrated from the mocap pose and the inputs.

Why: the prior's thrust map has one set of parameters for a vehicle, but the thrust per PWM and volt moves
from flight to flight: the motors warm over a session, a battery sags differently, a payload changes what the
thrust must carry.  Even with the motors' heating in the map (`models.crazyflie.motor_heating`), real flights
differ from it by a percent or two, and a 1 % error is 0.1 m/s² of vertical acceleration all flight long.  A
KNODE residual learns its training flight's offset and carries it to the others, where it fits or not by
chance.  Calibrated per flight, the prior and every estimator built on it estimate better in both transfer
directions (the results page `docs/results/transfer.md`, "What the Crazyflie prior and residual are given").

The gain c is the ratio of the mocap's to the prior's body-z specific force, summed over the airborne samples:
mocap R(q)ᵀ(p̈ + g e₃)·e₃ with p̈ from twice-differentiated position, low-passed at 2 Hz like the thrust axis
(`models.crazyflie.thrust_axis`), against `models.crazyflie.specific_force_body` on the same attitude, velocity, height
and inputs.  It is applied through the battery voltage the prior sees, V → V·c^(1/γ): the prior's thrust is
∝ (V/V_ref)^γ, so this multiplies it by c exactly and keeps the inputs' shape (stored models, generated code).
With thrust in N (crazyswarm2's ``ctrlLee.thrustSI``) the thrust is the four columns themselves, scaled by c: a
controller whose command over-promises the thrust made (`docs/results/crazyflie-flights.md`) is then the vehicle's.

Offline, like the thrust axis: one number from the whole record, later samples included.  It needs a
flight: a record with less than `MIN_AIRBORNE_S` above the floor, or a prior whose |γ| is below `MIN_GAMMA`
(the voltage cannot carry the gain) and whose thrust is not in N, keeps gain 1.  The diagnosis does not
calibrate it: a payload or a thrust-gain effect is what it looks for, and the gain would absorb it.
"""
from __future__ import annotations

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.align import FLYING_HEIGHT_M
from learnest.ingest.frames import GRAVITY

from . import prior as cf
from .motor_heating import MIN_GAMMA
from .thrust_axis import EDGE_S, LOWPASS_HZ

MIN_AIRBORNE_S = 3.0
GAIN_BOUNDS = (1.0 / 3.0, 3.0)    # beyond these the thrust map is not this vehicle's, or the inputs are wrong
VBAT = cf.INPUT_NAMES.index("vbat")
THRUST_COLUMNS = slice(cf.INPUT_NAMES.index("pwm1"), cf.INPUT_NAMES.index("pwm4") + 1)


def thrust_gain(p: np.ndarray, u: np.ndarray, dt: float, params: dict) -> float:
    """The flight's thrust gain against the prior's thrust map.

    Parameters
    ----------
    p : ndarray, shape (T, 3)
        Mocap position, world frame (z up, the floor at 0), m.
    u : ndarray, shape (T, 9)
        The prior's inputs (`models.crazyflie.INPUT_NAMES`): attitude (scalar-last quaternion, already on the
        thrust axis), PWM of motors 1..4, battery voltage (V).
    dt : float
        Sample time, s.
    params : dict
        The prior's parameters (`models.crazyflie.IDENTIFIED` keys).

    Returns
    -------
    float
        c, the mocap's body-z specific force over the prior's, summed over the airborne samples (1 for a
        record with less than `MIN_AIRBORNE_S` airborne or sampled too coarsely to low-pass, and for a prior
        whose |gamma| is below `MIN_GAMMA`).  With the motors' heating applied to ``u`` first
        (`models.crazyflie.motor_heating`), it is the flight's level against the heated map.

    Raises
    ------
    ValueError
        If c lies outside `GAIN_BOUNDS` (the thrust map, the PWM or the voltage are not this vehicle's).
    """
    from learnest.models.filters import lowpass

    p, u = np.asarray(p, dtype=float), np.asarray(u, dtype=float)
    edge = int(round(EDGE_S / dt))
    carried = cf.thrust_source_of(params) == "thrust_n" or abs(params["gamma"]) >= MIN_GAMMA
    if not carried or 1.0 / dt < 2.5 * LOWPASS_HZ or len(p) <= 2 * edge + 2:
        return 1.0   # the inputs cannot carry a gain (`with_thrust_gain`), or too little record to low-pass
    velocity = np.gradient(p, dt, axis=0)
    acceleration = lowpass(np.gradient(velocity, dt, axis=0), dt, LOWPASS_HZ)
    R = np.array(cf.rotation_columns(*u[:, :4].T))                       # (3, 3, T), body -> world
    measured = np.einsum("it,ti->t", R[:, 2, :], acceleration + np.array([0.0, 0.0, GRAVITY]))
    predicted = np.asarray(cf.specific_force_body(list(lowpass(velocity, dt, LOWPASS_HZ).T), p[:, 2],
                                                  list(u.T), params)[0][2], dtype=float)
    airborne = np.zeros(len(p), dtype=bool)
    airborne[edge:len(p) - edge] = p[edge:len(p) - edge, 2] > FLYING_HEIGHT_M
    airborne &= np.isfinite(measured) & np.isfinite(predicted)
    if airborne.sum() * dt < MIN_AIRBORNE_S:
        return 1.0
    gain = float(np.sum(measured[airborne]) / np.sum(predicted[airborne]))
    if not GAIN_BOUNDS[0] <= gain <= GAIN_BOUNDS[1]:
        raise InvalidInput(f"the mocap sees {gain:.2f} times the thrust the prior's map predicts from the motors and "
                         f"the battery (expected within {GAIN_BOUNDS[0]:.2f}-{GAIN_BOUNDS[1]:.0f}): are the PWM and "
                         "voltage channels this vehicle's, in their units?")
    return gain


def with_thrust_gain(u: np.ndarray, gain: float, gamma: float, source: str = "pwm") -> np.ndarray:
    """The inputs with the prior's thrust scaled by gain: the battery voltage by gain^(1/gamma), or, with thrust in
    N (``source`` "thrust_n", where the thrust is the columns themselves), the four thrust columns by gain.

    Parameters
    ----------
    u : ndarray, shape (T, 9)
        `models.crazyflie.INPUT_NAMES` inputs.
    gain : float
        `thrust_gain`.
    gamma : float
        The prior's voltage exponent (thrust ∝ V^gamma); below `MIN_GAMMA` in magnitude u is returned as is
        (but with thrust in N).
    source : str
        The prior's thrust source (`models.crazyflie.THRUST_SOURCES`).

    Returns
    -------
    ndarray, shape (T, 9)
        A copy, its voltage column or (thrust in N) its thrust columns scaled.
    """
    u = np.array(u, dtype=float)
    if source == "thrust_n":
        u[:, THRUST_COLUMNS] *= gain
    elif abs(gamma) >= MIN_GAMMA and gain != 1.0:
        u[:, VBAT] *= gain ** (1.0 / gamma)
    return u
