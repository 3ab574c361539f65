"""Simulated Crazyflie flights whose truth is `models.crazyflie`: the test bench of the Crazyflie diagnosis.

A position controller flies the input-driven model closed-loop along a varied path: take-off hover a few
cm above the floor (ground effect), a climb, circles at several speeds with climbs and descents (thrust
and airspeed vary), a descent and a landing hover.  The battery sags linearly over the flight.  What the
truth differs in from the prior (payload mass, voltage exponent, rotor drag, motor lag, ground effect) is
set by ``truth`` (its ``kappa_th``, ``tau_th_s``: motors that lose thrust as they warm, `motor_heating`,
from cold at the start); the controller flies with the prior's thrust map and an integrator, as the firmware does.

The Flight carries what a NanoBench log carries: mocap position and attitude, the accelerometer's
body-frame specific force (``acc_body``, white noise, optionally the sensor's low-pass), the four motor PWM
(``motors``) and the battery voltage (``vbat``).  The motor lag acts on the body-frame specific force as a
first-order filter, the form `models.crazyflie.identify` predicts.  Writing these inputs into the log formats of
`ingest` is not done here (ingest must not import models).
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.clock import CRAZYFLIE_ACCEL_LOWPASS
from learnest.ingest.flight import Flight
from learnest.ingest.frames import GRAVITY

from ..effects import predict_acc_body, world_from_body
from . import prior as cf
from .identify import lowpass
from .motor_heating import motor_power

SUBSTEPS = 5                    # integration steps per logged sample (2 ms at 100 Hz)
KP, KD, KI = 6.0, 4.5, 2.0      # position loop (1/s², 1/s, 1/s³): a tight tracker, as a tuned Crazyflie's
TORQUE_SPREAD = 0.01            # per-motor thrust differences (attitude control), fraction of the mean


@dataclass(frozen=True)
class SimulatedFlight:
    """Settings of one simulated flight.

    Attributes
    ----------
    truth : dict
        Parameters of the vehicle flown (`models.crazyflie.IDENTIFIED` keys).
    controller : dict
        Parameters the controller's thrust map assumes (the prior).
    duration_s : float
        Length, s (take-off and landing hovers included).
    vbat : tuple of float
        Battery voltage at start and end, V (linear sag).
    speeds : tuple of float
        Circle speeds, m/s, flown in turn (shuffled per seed).
    hover_height_m : float
        Height of the take-off and landing hovers, m (ground effect acts below ~4 rotor radii).
    accel_noise : float
        Accelerometer white noise, m/s² per sample (vibration-dominated in flight).
    mocap_noise : float
        Mocap position noise, m.
    vbat_noise : float
        Voltage reading noise, V.
    accel_lpf_hz : float or None
        Cut-off of the accelerometer's own 2-pole Butterworth low-pass, run as the firmware runs it on the
        sensor's 1 kHz samples (the firmware's is 30 Hz, `ingest.clock.CRAZYFLIE_ACCEL_LOWPASS`); None: no
        filter.  Its group delay (7.5 ms at 30 Hz) is a real accelerometer delay that a diagnosis reports.
    rate_hz : float
        Log rate, Hz.
    thrust_source : {"pwm", "rpm", "thrust_n"}
        What the log carries of the thrust (`models.crazyflie.THRUST_SOURCES`): motor PWM (``motors``), the
        rotor speed the motors reach (``rotor_speed``, rad/s, after their lag, on Förster's rotor-speed fit),
        or the controller's collective thrust command in N (``thrust_si``, before the motors' lag); the
        battery voltage is logged with each.  ``truth`` and ``controller`` are PWM maps here whatever
        their ``thrust_source`` says: the vehicle is always driven by PWM.
    accel_bias : tuple of float
        Accelerometer offset, body frame, m/s² (`models.effects.predict_acc_body`'s ``bias_x..z``).
    accel_tilt_rad : tuple of float
        (roll, pitch) of the IMU against the mocap body frame, rad (``roll_rad``, ``pitch_rad``).
    turn : {1, -1}
        Sense of the circles seen from above: 1 counter-clockwise, -1 clockwise.  With one seed, the two are
        mirror images of each other (the same radius, speeds, climbs; the heading's sway mirrored too).
    """

    truth: dict = field(default_factory=lambda: dict(cf.IDENTIFIED))
    controller: dict = field(default_factory=lambda: dict(cf.IDENTIFIED))
    duration_s: float = 30.0
    vbat: tuple = (4.1, 3.4)
    speeds: tuple = (0.5, 1.0, 1.5)
    hover_height_m: float = 0.05
    accel_noise: float = 0.1
    mocap_noise: float = 3e-4
    vbat_noise: float = 0.005
    accel_lpf_hz: float | None = None
    rate_hz: float = 100.0
    thrust_source: str = "pwm"
    accel_bias: tuple = (0.0, 0.0, 0.0)
    accel_tilt_rad: tuple = (0.0, 0.0)
    turn: int = 1


def reference_path(settings: SimulatedFlight, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """(t, p, v, a, yaw): the path to fly, (T,), (T, 3) m, m/s, m/s², (T,) rad, smooth (1 Hz low-pass)."""
    dt = 1.0 / settings.rate_hz
    t = np.arange(int(round(settings.duration_s * settings.rate_hz))) * dt
    hover, climb = 2.5, 2.5                       # s at the floor, s to climb (and to descend)
    up = np.clip((t - hover) / climb, 0, 1)
    down = np.clip((settings.duration_s - hover - t) / climb, 0, 1)
    airborne = np.minimum(up, down)
    airborne = airborne * airborne * (3 - 2 * airborne)   # smoothstep
    radius = rng.uniform(0.4, 0.7)
    speeds = rng.permutation(settings.speeds)
    cruise = np.clip(t - hover - climb, 0, None)
    cruise_s = max(settings.duration_s - 2 * (hover + climb), 1.0)
    speed = speeds[np.minimum((cruise / cruise_s * len(speeds)).astype(int), len(speeds) - 1)]
    if settings.turn not in (1, -1):
        raise InvalidInput(f"a simulated flight's turn must be 1 (counter-clockwise) or -1 (clockwise), "
                           f"not {settings.turn!r}")
    phase = settings.turn * (rng.uniform(0, 2 * np.pi) + np.cumsum(speed * airborne) * dt / radius)
    height = 1.0 + rng.uniform(0.2, 0.4) * np.sin(2 * np.pi * t / rng.uniform(3.0, 5.0))
    p = np.column_stack([radius * np.cos(phase) * airborne, radius * np.sin(phase) * airborne,
                         settings.hover_height_m + (height - settings.hover_height_m) * airborne])
    p = lowpass(p, dt, 1.0)
    v = np.gradient(p, dt, axis=0)
    a = np.gradient(v, dt, axis=0)
    yaw = settings.turn * 0.4 * np.sin(2 * np.pi * t / rng.uniform(8.0, 12.0))
    return t, p, v, a, yaw


def _pwm_for(thrust_n: np.ndarray, vbat: float, params: dict) -> np.ndarray:
    """PWM (0..65535) at which each motor gives thrust_n (N) at vbat (V) on the map ``params``."""
    return np.clip(cf.pwm_for_thrust(thrust_n, params, vbat), 0.0, cf.PWM_MAX)


def _attitude(force: np.ndarray, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """(R body-to-world, its quaternion scalar last) with body z along ``force`` and heading ``yaw`` (rad).

    Written out rather than through scipy: it runs once per logged sample in the closed loop."""
    b3 = force / np.sqrt(force @ force)
    heading = (np.cos(yaw), np.sin(yaw))
    b2 = np.array([-b3[2] * heading[1], b3[2] * heading[0], b3[0] * heading[1] - b3[1] * heading[0]])  # b3 × h
    b2 /= np.sqrt(b2 @ b2)
    b1 = np.array([b2[1] * b3[2] - b2[2] * b3[1], b2[2] * b3[0] - b2[0] * b3[2], b2[0] * b3[1] - b2[1] * b3[0]])
    R = np.column_stack([b1, b2, b3])
    # the vehicle never tilts past 90°, so 1 + trace > 0 and the scalar part is the safe pivot
    w = 0.5 * np.sqrt(1.0 + R[0, 0] + R[1, 1] + R[2, 2])
    quat = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 4 * w * w]) / (4 * w)
    return R, quat


def simulate_crazyflie(settings: SimulatedFlight = SimulatedFlight(), seed: int = 0, name: str | None = None) -> Flight:
    """Fly ``settings.truth`` closed-loop along a varied path and log it as a Flight.

    The inputs are held over each sample, and so is the specific force they command (the motor lag
    filters it exactly, as `models.crazyflie.identify.first_order_lag` assumes); position and velocity are
    integrated in `SUBSTEPS` steps per sample.

    Parameters
    ----------
    settings : SimulatedFlight
    seed : int
        Seed of the path (radius, speed order, climbs, yaw), the motor spread and the sensor noise.
    name : str, optional
        The flight's name (default ``"sim_crazyflie_<seed>"``).

    Returns
    -------
    Flight
        T = duration·rate rows: ``p`` (m, mocap noise), ``quat`` (scalar last), ``a_meas`` (m/s², world,
        gravity removed), channels ``acc_body`` (T, 3) m/s², ``motors`` (T, 4) PWM, ``vbat`` (T,) V; its
        ``meta["simulated_truth"]`` holds ``settings.truth``.
    """
    rng = np.random.default_rng(seed)
    # the vehicle is driven by PWM whatever the log records of it
    truth = {k: v for k, v in settings.truth.items() if k != cf.THRUST_SOURCE_KEY}
    ctrl = {k: v for k, v in settings.controller.items() if k != cf.THRUST_SOURCE_KEY}
    if settings.thrust_source not in cf.THRUST_SOURCES:
        raise InvalidInput(f"thrust_source {settings.thrust_source!r} is not one of {', '.join(cf.THRUST_SOURCES)}")
    t, p_ref, v_ref, a_ref, yaw = reference_path(settings, rng)
    n, dt = len(t), 1.0 / settings.rate_hz
    h = dt / SUBSTEPS
    volts, spread = _battery_and_spread(settings, n, rng)
    decay = _lag_decay(h, truth["tau_s"])
    gravity = np.array([0.0, 0.0, GRAVITY])
    p, v = p_ref[0].copy(), np.zeros(3)
    heat = {"h": 0.0}      # the motors' thermal state (models.crazyflie.motor_heating), cold at the start
    kappa_th = float(truth.get("kappa_th", 0.0))
    heat_decay = np.exp(-dt / truth["tau_th_s"]) if kappa_th else 0.0

    command = {"thrust_n": 0.0}

    def step(k: int, trim: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(R, u, commanded body specific force) at sample k: the controller's inputs and their effect."""
        force = a_ref[k] + KP * (p_ref[k] - p) + KD * (v_ref[k] - v) + gravity
        R, quat = _attitude(force, yaw[k])
        per_motor = ctrl["m_kg"] * trim * float(force @ R[:, 2]) / 4.0
        command["thrust_n"] = 4.0 * per_motor
        u = np.concatenate([quat, _pwm_for(per_motor * (1 + spread[k]), volts[k], ctrl), [volts[k]]])
        f_b, _ = cf.specific_force_body(list(v), p[2], list(u), truth)
        f_b = np.array([float(c) for c in f_b])
        if kappa_th:   # warm motors: the thrust the truth's map gives, × (1 − κ h)
            f_b[2] -= kappa_th * heat["h"] * float(cf.thrust_acceleration(p[2], list(u), truth))
        return R, u, f_b

    trim = _hover_trim(step)   # start in a steady hover
    f = step(0, trim)[2]
    log_p, log_f, log_u = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 9))
    log_thrust_cmd, log_motor_thrust, log_f_cmd = np.empty(n), np.empty((n, 4)), np.empty((n, 3))
    motor = np.array([float(cf.motor_thrust(x, volts[0], truth)) for x in step(0, trim)[1][4:8]])
    lagless = truth["tau_s"] <= 1e-6
    for k in range(n):
        R, u, f_cmd = step(k, trim)
        motor_cmd = np.array([float(cf.motor_thrust(x, volts[k], truth)) for x in u[4:8]])
        if lagless:   # no lag: the force is the command's from the sample on (not the last sample's)
            f, motor = f_cmd, motor_cmd
        log_p[k], log_f[k], log_u[k], log_f_cmd[k] = p, f, u, f_cmd
        # the controller's thrust command (N) and each motor's thrust after its lag (what its speed gives)
        log_thrust_cmd[k], log_motor_thrust[k] = command["thrust_n"], motor
        motor = motor_cmd + (motor - motor_cmd) * decay[-1]
        p, v = _substeps(p, v, R, f_cmd, f, decay, h, gravity)
        f = f_cmd + (f - f_cmd) * decay[-1]
        trim += KI * (p_ref[k, 2] - p[2]) * dt / GRAVITY
        if kappa_th:   # exact step of τ h' = P − h with the power of this sample's inputs held
            heat["h"] = heat_decay * heat["h"] + (1.0 - heat_decay) * float(motor_power(u))

    return _as_flight(settings, rng, t, log_p, (log_f, log_f_cmd), log_u, log_thrust_cmd, log_motor_thrust, truth,
                      name or f"sim_crazyflie_{seed}")

def _battery_and_spread(settings: SimulatedFlight, n: int, rng: np.random.Generator):
    """The battery voltage (T,) V, falling linearly, and each motor's torque spread (T, 4)."""
    volts = np.linspace(settings.vbat[0], settings.vbat[1], n)
    spread = TORQUE_SPREAD * rng.standard_normal((n, 4))
    spread -= spread.mean(axis=1, keepdims=True)            # differential: the collective is unchanged
    return volts, spread


def _lag_decay(h: float, tau_s: float) -> np.ndarray:
    """(SUBSTEPS + 1,): the lagged force at the start of each substep and at the end of the sample is
    f_cmd + (f - f_cmd)·decay (a motor lag of ``tau_s`` s, substeps of ``h`` s)."""
    return np.exp(-np.arange(SUBSTEPS + 1) * h / tau_s) if tau_s > 1e-6 else np.r_[1.0, np.zeros(SUBSTEPS)]


def _hover_trim(step) -> float:
    """The thrust trim that makes the controller hold the true vehicle in a steady hover, as the firmware's
    integrator has done by the time a flight's log starts."""
    trim = 1.0
    for _ in range(3):
        trim *= GRAVITY / step(0, trim)[2][2]
    return trim


def _substeps(p: np.ndarray, v: np.ndarray, R: np.ndarray, f_cmd: np.ndarray, f: np.ndarray, decay: np.ndarray,
              h: float, gravity: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Position (m) and velocity (m/s) after one sample's substeps of ``h`` s, the body force lagging from
    ``f`` towards ``f_cmd`` (`_lag_decay`).  Symplectic Euler with the acceleration at the start of each
    substep: the second difference of the logged positions then is the acceleration at the sample, not a
    substep later."""
    for fraction in decay[:-1]:
        v = v + h * (R @ (f_cmd + (f - f_cmd) * fraction) - gravity)
        p = p + h * v
    return p, v


SENSOR_RATE_HZ = CRAZYFLIE_ACCEL_LOWPASS.rate_hz   # the accelerometer's sampling rate on the vehicle


def _sensor_reading(settings: SimulatedFlight, forces: tuple[np.ndarray, np.ndarray], t: np.ndarray, tau_s: float,
                    sensor: dict, noise: np.ndarray) -> np.ndarray:
    """What the accelerometer logs (T, 3), m/s²: the body specific force through the sensor model
    (`models.effects.predict_acc_body`) plus ``noise``; with ``settings.accel_lpf_hz``, through its own
    2-pole low-pass run on the sensor's 1 kHz samples of the force as it moves within each logged sample
    (from its value at the sample towards the command, with the motor lag ``tau_s``), read at the log's
    instants (a log block samples the latest filtered value).

    ``forces`` = (the body force at each sample, the force commanded over it), each (T, 3) m/s²."""
    f_start, f_cmd = forces
    if not settings.accel_lpf_hz:
        return predict_acc_body(f_start, t, sensor) + noise
    from scipy.signal import lfilter  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    up = max(1, int(round(SENSOR_RATE_HZ / settings.rate_hz)))
    within = np.exp(-np.arange(up) / (up * settings.rate_hz * tau_s)) if tau_s > 1e-6 else np.zeros(up)
    fine = (f_cmd[:, None, :] + (f_start - f_cmd)[:, None, :] * within[None, :, None]).reshape(-1, 3)
    fine_t = np.arange(len(fine)) / (up * settings.rate_hz)
    read = predict_acc_body(fine, fine_t, sensor) + np.repeat(noise, up, axis=0)
    lowpass = replace(CRAZYFLIE_ACCEL_LOWPASS, cutoff_hz=settings.accel_lpf_hz, rate_hz=up * settings.rate_hz)
    b, a = lowpass.coefficients()
    return lfilter(b, a, read - read[0], axis=0)[::up] + read[0]


def _as_flight(settings: SimulatedFlight, rng: np.random.Generator, t: np.ndarray, log_p: np.ndarray,
               forces: tuple[np.ndarray, np.ndarray], log_u: np.ndarray, log_thrust_cmd: np.ndarray,
               log_motor_thrust: np.ndarray,
               truth: dict, name: str) -> Flight:
    """The simulated states and inputs as the sensors log them (`simulate_crazyflie`'s Flight)."""
    n = len(t)
    sensor = {"roll_rad": settings.accel_tilt_rad[0], "pitch_rad": settings.accel_tilt_rad[1],
              **{f"bias_{a}": b for a, b in zip("xyz", settings.accel_bias)}}
    noise = settings.accel_noise * rng.standard_normal(forces[0].shape)
    acc = _sensor_reading(settings, forces, t, float(truth["tau_s"]), sensor, noise)
    positions = log_p + settings.mocap_noise * rng.standard_normal(log_p.shape)
    channels = {"acc_body": acc, "vbat": log_u[:, 8] + settings.vbat_noise * rng.standard_normal(n)}
    if settings.thrust_source == "pwm":
        channels["motors"] = log_u[:, 4:8]
    elif settings.thrust_source == "rpm":
        channels["rotor_speed"] = cf.thrust_columns_for(log_motor_thrust, "rpm")
    else:
        channels["thrust_si"] = log_thrust_cmd.reshape(n, 1)
    meta = {"name": name, "adapter": "simulated crazyflie",
            "quality": {"ok": True, "issues": []}, "simulated_truth": dict(truth)}
    return Flight(t, positions, world_from_body(acc, log_u[:, :4]), log_u[:, :4], channels, meta)
