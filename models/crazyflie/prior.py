"""Crazyflie 2.x physics driven by its inputs: thrust map from motor PWM, battery voltage, rotor drag,
ground effect, motor lag.  Written once against the numpy/torch/CasADi namespace of `models.backend`.

Every number has one home here: `PUBLIC` holds published values with their source, `IDENTIFIED` the
values fitted on the real NanoBench flights (the fit's intervals and held-out scores are on the results page
`docs/results/crazyflie-physics.md`), `BOUNDS` the physically plausible range of each parameter.
Parameter names follow the effect contract (`EFFECTS` below): `m_kg`, `gamma`, `k_xy`, `k_z`, `r_m`, `tau_s`.

Thrust of one motor (N), PWM p in 0..65535, battery voltage V (V):

    T_i = (q_pwm2 · a2 · p² + a1 · p + a0) · (V / V_ref)^gamma

with Förster's Crazyflie 2.0 coefficients a2, a1, a0 and q_pwm2 = 1 reproducing his map exactly.
Why a voltage factor: the logged `motor.m1..m4` are the duty cycles *after* the firmware's battery
compensation (on NanoBench the logged duty is 65535·volts(cmd_thrust)/vbat), so at a given PWM the motor
sees a voltage proportional to the battery's.

Specific force in the body frame (what the accelerometer reads, m/s²), with v_b = Rᵀ v:

    f_b = [0, 0, Σ T_i · G(z) / m_kg] − diag(k_xy, k_xy, k_z) · v_b

G(z) = 1 / (1 − (r_m / (4 z))²) is Cheeseman & Bennett's ground-effect factor (z above the floor, z = 0
in the mocap frame), and the world acceleration is a = R f_b − g e₃.

Motor heating (`kappa_th`, `tau_th_s`) multiplies the thrust by 1 − kappa_th·h, h a thermal state of the
inputs' history (`models.crazyflie.motor_heating`); it is not a function of (x, u) at one instant, so it is applied to
the inputs before they reach these functions (`models.inputs.system_inputs`, `models.crazyflie.identify`).
"""
from __future__ import annotations

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.frames import GRAVITY

from ..backend import ops_for

# -- published values ----------------------------------------------------------------------------------
# J. Förster, "System Identification of the Crazyflie 2.0 Nano Quadrocopter", BSc thesis, ETH Zürich,
# 2015 (listed on Bitcraze's "PWM to Thrust" page, crazyflie-firmware docs, functional-areas/pwm-to-thrust):
# static thrust of one motor+propeller vs the 16-bit PWM command, F = a2·p² + a1·p + a0 in N.
FOERSTER_A2 = 2.130295e-11    # N
FOERSTER_A1 = 1.032633e-6     # N
FOERSTER_A0 = 5.484560e-4     # N
# Förster, same thesis: rotor speed vs PWM, ω = 0.04076521·p + 380.8359 (rad/s), and the rotor-drag
# coefficients of F_aero = K · (Σ ω_i) · v_body with K = diag(-9.1785e-7, -9.1785e-7, -10.311e-7) kg/rad.
FOERSTER_OMEGA_SLOPE = 0.04076521   # rad/s per PWM count
FOERSTER_OMEGA_OFFSET = 380.8359    # rad/s
FOERSTER_K_DRAG_XY = 9.1785e-7      # kg/rad
FOERSTER_K_DRAG_Z = 10.311e-7       # kg/rad
# Bitcraze, Crazyflie 2.1 product page / datasheet: take-off weight 27 g; propellers 45 mm diameter.
BITCRAZE_MASS_KG = 0.027
BITCRAZE_ROTOR_RADIUS_M = 0.0225
# crazyflie-firmware, src/drivers/src/motors.c (motorsCompensateBatteryVoltage): "A LiPo battery is
# supposed to be 4.2V charged, 3.7V mid-charge and 3V discharged" -> the reference voltage of the map.
V_REF = 3.7
PWM_MAX = 65535.0


def pwm_for_thrust(thrust_n, params: dict | None = None, vbat=None):
    """The PWM (0..65535 scale, not clipped) at which one motor gives ``thrust_n`` (N) on the PWM map ``params``
    (Förster's quadratic, its square term × ``q_pwm2``; default Förster's) at battery voltage ``vbat`` (V;
    None: the map without the battery, i.e. at v_ref): the root on the map's rising branch, for either sign
    of the square term.  Where no PWM gives the thrust, the vertex (the map's extreme); `hover_pwm` refuses
    that case.  ``thrust_n`` and ``vbat`` may be arrays (broadcast)."""
    params = params or {}
    thrust_n = np.asarray(thrust_n, dtype=float)
    if vbat is not None:
        thrust_n = thrust_n / (np.asarray(vbat, dtype=float) / params.get("v_ref", V_REF)) ** params["gamma"]
    a2, a1, a0 = params.get("q_pwm2", 1.0) * FOERSTER_A2, FOERSTER_A1, FOERSTER_A0 - thrust_n
    if abs(a2) < 1e-30:
        return -a0 / a1
    return (-a1 + np.sqrt(np.maximum(a1 * a1 - 4.0 * a2 * a0, 0.0))) / (2.0 * a2)


def _hover_pwm(mass_kg: float) -> float:
    """PWM of each of 4 motors that holds mass_kg on Förster's map at V_ref (positive root)."""
    return float(pwm_for_thrust(mass_kg * GRAVITY / 4.0))


def _rotor_drag_per_second(k_aero: float, mass_kg: float) -> float:
    """Förster's K (kg/rad) times the summed rotor speed at hover, over the mass: a rate in 1/s."""
    omega = FOERSTER_OMEGA_SLOPE * _hover_pwm(mass_kg) + FOERSTER_OMEGA_OFFSET
    return k_aero * 4.0 * omega / mass_kg


PUBLIC = {
    "m_kg": BITCRAZE_MASS_KG,
    "gamma": 1.0,      # the firmware's compensation (duty = volts / vbat) treats thrust as set by duty·V
    "q_pwm2": 1.0,     # Förster's quadratic term unchanged
    "k_xy": _rotor_drag_per_second(FOERSTER_K_DRAG_XY, BITCRAZE_MASS_KG),   # ≈ 0.25 1/s
    "k_z": _rotor_drag_per_second(FOERSTER_K_DRAG_Z, BITCRAZE_MASS_KG),     # ≈ 0.28 1/s
    "r_m": BITCRAZE_ROTOR_RADIUS_M,
    # No published Crazyflie 2.x motor time constant was found in the sources above; 30 ms is the order
    # of magnitude of small brushed motors and the value the simulated tests use.
    "tau_s": 0.03,
    "v_ref": V_REF,
    # No published thermal model of the Crazyflie's motors was found: no heating, and the identified time
    # constant (models.crazyflie.motor_heating).
    "kappa_th": 0.0,
    "tau_th_s": 75.0,
}

# Fitted on the 16 usable NanoBench flights of CF_01, all pooled (intervals and held-out scores:
# docs/results/crazyflie-physics.md).  m_kg is an *effective* mass relative to Förster's map: NanoBench's vehicle
# carries markers and maybe a deck, and its motors/propellers are not Förster's, so mass and thrust gain are one
# number here.
IDENTIFIED = {
    "m_kg": 0.0190,
    "gamma": 0.42,
    "q_pwm2": -0.153,
    "k_xy": 0.40,
    "k_z": 0.108,
    "r_m": BITCRAZE_ROTOR_RADIUS_M,   # not identifiable at 1 m flying height: the public value is kept
    "tau_s": 0.061,
    # the acceleration across the thrust axis follows the logged attitude through this lag (`Crazyflie` system);
    # equal to tau_s, the whole world acceleration relaxes as one (docs/results/lag-axes.md)
    "tau_att_s": 0.061,
    "v_ref": V_REF,
    # motor heating (models.crazyflie.motor_heating), fitted after the rest with a free thrust gain per flight
    # (docs/results/transfer.md): thrust × (1 − kappa_th·h), τ_th ḣ = P − h
    "kappa_th": 0.055,
    "tau_th_s": 75.0,
}

# Plausible ranges: fits are constrained to them and the effect library may use them as priors.
# Physical, not numerical: thrust grows with the battery voltage (gamma ≥ 0), a brushed 7-mm motor's lag is
# tens of ms (≤ 0.1 s), rotor drag opposes the airspeed (k ≥ 0), and the ground effect's radius is the
# rotor's within a factor of 2 (Cheeseman–Bennett's r is the rotor radius; a fit far from it is another
# effect, e.g. a height-dependent thrust error, taking the term's place).  A fit at one of these bounds is
# not an identified value (`models.diagnosis`).
BOUNDS = {
    "m_kg": (0.005, 0.1),     # an effective mass against a PWM map can be below any real vehicle's
    "gamma": (0.0, 3.0),
    "q_pwm2": (-3.0, 3.0),
    "k_xy": (0.0, 2.0),
    "k_z": (0.0, 2.0),
    "r_m": (0.5 * BITCRAZE_ROTOR_RADIUS_M, 2.0 * BITCRAZE_ROTOR_RADIUS_M),
    "tau_s": (0.0, 0.1),
    "tau_att_s": (0.0, 0.1),
    "v_ref": (V_REF, V_REF),
    "kappa_th": (0.0, 0.3),
    "tau_th_s": (5.0, 600.0),
}

UNITS = {"m_kg": "kg", "gamma": "1", "q_pwm2": "1", "k_xy": "1/s", "k_z": "1/s", "r_m": "m", "tau_s": "s",
         "tau_att_s": "s", "v_ref": "V", "kappa_th": "1", "tau_th_s": "s"}

# The effect contract: effect id -> its parameters and the one-line equation it adds to the prior.
# Nominal values: PUBLIC (published) and IDENTIFIED (NanoBench); ranges: BOUNDS; units: UNITS.
EFFECTS = {
    "mass": {"params": ("m_kg",), "equation": "v̇ = R(q)·[0, 0, Σ T_i]ᵀ / m_kg − g e₃  (a payload raises m_kg)"},
    "battery_thrust": {"params": ("gamma",),
                       "equation": "T_i = (q_pwm2·a2·p_i² + a1·p_i + a0)·(V / V_ref)^gamma, V_ref = 3.7 V"},
    "rotor_drag": {"params": ("k_xy", "k_z"), "equation": "f_b −= diag(k_xy, k_xy, k_z)·Rᵀ v"},
    "ground_effect": {"params": ("r_m",), "equation": "Σ T_i /= 1 − (r_m / (4 z))²  (Cheeseman–Bennett)"},
    "motor_lag": {"params": ("tau_s",),
                  "equation": "b₃ᵀȧ = b₃ᵀ(a_cmd(v, z, u) − a) / tau_s  (along the thrust axis b₃)"},
    # tau_th_s is held at the prior's: flights of 20-40 s determine kappa_th/tau_th_s, not both (motor_heating)
    "motor_heating": {"params": ("kappa_th",),
                      "equation": "Σ T_i ×= 1 − kappa_th·h,  tau_th_s·ḣ = Σ (p_i V)² / P_ref − h  (cold at the start)"},
}

# The inputs the prior needs, in order: mocap attitude (scalar last), 4 motor PWM, battery voltage.
INPUT_NAMES = ("qx", "qy", "qz", "qw", "pwm1", "pwm2", "pwm3", "pwm4", "vbat")

# What the four thrust columns of the inputs carry (the prior's ``thrust_source``, a string: absent means
# "pwm").  The columns keep their names and places whatever they carry, so every estimator, the KNODE and
# stored models take the same 9 inputs:
#   "pwm"       motor PWM 0..65535 and the battery voltage: T_i = map(PWM_i)·(V / V_ref)^gamma;
#   "rpm"       rotor speed ω_i in rad/s (an rpm deck): T_i = map(p(ω_i)), p(ω) = (ω − ω₀) / slope on
#               Förster's linear rotor-speed fit, so one thrust map serves both; the battery plays no part
#               (the measured rotor speed already carries it), and neither does the motor's lag;
#   "thrust_n"  the controller's collective thrust in N split equally over the four columns (crazyswarm2's
#               ctrlLee.thrustSI): T_i = column_i·(V / V_ref)^gamma, the mass the only scale between thrust and
#               acceleration; gamma (0 in the prior) is what the firmware's battery compensation leaves.
THRUST_SOURCES = ("pwm", "rpm", "thrust_n")
THRUST_SOURCE_KEY = "thrust_source"


def thrust_source_of(params: dict) -> str:
    """The prior's thrust source (`THRUST_SOURCES`), "pwm" when it names none."""
    return str(params.get(THRUST_SOURCE_KEY, "pwm"))


def prior_for(source: str, mass_kg: float | None = None, base: dict | None = None) -> dict:
    """The prior's parameters for flights whose thrust comes from ``source``.

    "pwm": ``base`` (default `IDENTIFIED`, whose m_kg is an effective mass against Förster's map) as is.
    "rpm" and "thrust_n": the thrust is known on an absolute scale, so ``m_kg`` is the vehicle's mass:
    ``mass_kg`` when declared, else Bitcraze's 27 g; the battery exponent and the motor heating are 0 (the
    source already carries the battery and the motors' state); the quadratic term is Förster's; the rpm
    source's motor lag is 0 (a measured rotor speed lags nothing), the commanded thrust keeps ``base``'s.
    A declared ``mass_kg`` with "pwm" is not put into the map (it would replace the map's effective mass):
    the diagnosis reports a payload relative to it instead.
    """
    if source not in THRUST_SOURCES:
        raise InvalidInput(f"thrust source {source!r} is not one of {', '.join(THRUST_SOURCES)}")
    params = dict(IDENTIFIED if base is None else base)
    if source == "pwm":
        params.pop(THRUST_SOURCE_KEY, None)
        return params
    params.update({"m_kg": float(mass_kg) if mass_kg else BITCRAZE_MASS_KG, "gamma": 0.0, "q_pwm2": 1.0,
                   "kappa_th": 0.0, THRUST_SOURCE_KEY: source})
    if source == "rpm":
        params["tau_s"] = 0.0
    return params


# -- the model, one definition for numpy / torch / CasADi -------------------------------------------
def motor_thrust(pwm, vbat, params):
    """Thrust of one motor (N) from its thrust column (PWM 0..65535, rotor speed rad/s or thrust N, by the
    prior's `thrust_source_of`) and the battery voltage (V); any array kind."""
    source = thrust_source_of(params)
    if source == "thrust_n":
        # gamma here (0 in the prior): how the thrust made departs from the command with the battery, i.e. the
        # vehicle's exponent less the one the firmware's compensation assumes
        return pwm * (vbat / params.get("v_ref", V_REF)) ** params["gamma"]
    if source == "rpm":
        pwm = (pwm - FOERSTER_OMEGA_OFFSET) / FOERSTER_OMEGA_SLOPE
    poly = params.get("q_pwm2", 1.0) * FOERSTER_A2 * pwm**2 + FOERSTER_A1 * pwm + FOERSTER_A0
    if source == "rpm":
        return poly
    return poly * (vbat / params.get("v_ref", V_REF)) ** params["gamma"]


def thrust_columns_for(thrust_n, source: str, params: dict | None = None):
    """The inverse of `motor_thrust` without the battery: what a thrust column reads when its motor gives
    ``thrust_n`` (N): PWM on the map (at V_ref), rotor speed (rad/s), or the thrust itself."""
    thrust_n = np.asarray(thrust_n, dtype=float)
    if source == "thrust_n":
        return thrust_n
    pwm = pwm_for_thrust(thrust_n, {"q_pwm2": 1.0 if params is None else params.get("q_pwm2", 1.0)})
    return pwm if source == "pwm" else FOERSTER_OMEGA_SLOPE * pwm + FOERSTER_OMEGA_OFFSET


def ground_effect(z, r_m):
    """Cheeseman–Bennett thrust factor 1 / (1 − (r/4z)²) at height z (m) above the floor.

    Heights below 2 r are treated as 2 r (the factor there is 1.016): the formula diverges at z = r/4
    and is not meant for a vehicle sitting on the floor."""
    ops = ops_for(z)
    z_safe = 0.5 * (z + 2.0 * r_m + ops.sqrt((z - 2.0 * r_m) ** 2 + 1e-8))  # smooth max(z, 2r)
    ratio = r_m / (4.0 * z_safe)
    return 1.0 / (1.0 - ratio * ratio)


def rotation_columns(qx, qy, qz, qw):
    """Rows of R(q) (body -> world) for a unit scalar-last quaternion, as 9 scalars/arrays r[i][j]."""
    return ((1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)),
            (2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)),
            (2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)))


def thrust_acceleration(z, u, params):
    """Collective thrust over the mass, Σ T_i · G(z) / m_kg (m/s², along body z): the specific force at rest.

    ``z`` the height above the floor (m), ``u`` the 9 `INPUT_NAMES` inputs; any array kind."""
    thrust = sum(motor_thrust(p, u[8], params) for p in u[4:8])
    if params.get("r_m", 0.0) > 0.0:
        thrust = thrust * ground_effect(z, params["r_m"])
    return thrust / params["m_kg"]


def specific_force_body(v_world, z, u, params):
    """Body-frame specific force (m/s², the accelerometer's reading) predicted from the inputs.

    Parameters
    ----------
    v_world : list of 3 arrays/symbols
        Velocity in the world frame (m/s), each of batch shape (...).
    z : array/symbol
        Height above the floor (m), batch shape (...).
    u : list of 9 arrays/symbols
        `INPUT_NAMES`: quaternion (scalar last), PWM of motors 1..4 (0..65535), battery voltage (V).
    params : dict
        `PUBLIC` / `IDENTIFIED` keys.

    Returns
    -------
    (list of 3 body-frame components, R as nested tuples)
    """
    R = rotation_columns(*u[:4])
    vb = [R[0][i] * v_world[0] + R[1][i] * v_world[1] + R[2][i] * v_world[2] for i in range(3)]  # Rᵀ v
    fz = thrust_acceleration(z, u, params) - params["k_z"] * vb[2]
    return [-params["k_xy"] * vb[0], -params["k_xy"] * vb[1], fz], R


def world_acceleration(v_world, z, u, params):
    """Predicted world-frame acceleration a = R f_b − g e₃ (m/s²), the quantity `Flight.a_meas` holds."""
    f_b, R = specific_force_body(v_world, z, u, params)
    return [R[i][0] * f_b[0] + R[i][1] * f_b[1] + R[i][2] * f_b[2] - (GRAVITY if i == 2 else 0.0)
            for i in range(3)]


def hover_pwm(params, vbat: float | None = None) -> float:
    """The PWM (equal on 4 motors) at which the thrust holds the vehicle level in still air, far from
    the floor, at battery voltage vbat (default v_ref): a root of a quadratic in PWM."""
    vbat = params.get("v_ref", V_REF) if vbat is None else vbat
    per_motor = params["m_kg"] * GRAVITY / 4.0
    pwm = float(pwm_for_thrust(per_motor, params, vbat))
    made = (params.get("q_pwm2", 1.0) * FOERSTER_A2 * pwm**2 + FOERSTER_A1 * pwm + FOERSTER_A0) \
        * (vbat / params.get("v_ref", V_REF)) ** params["gamma"]
    if not np.isclose(made, per_motor, rtol=1e-9, atol=1e-12):    # no PWM on the map gives it: the vertex
        raise InvalidInput(f"the thrust map {params} cannot hold {params['m_kg']} kg at {vbat} V")
    return pwm
