"""Recordings that hold more, or less, than one clean flight: what a log from another lab looks like.

`recording` turns a SimulatedFlight into a canonical Flight on a uniform grid that carries what a Crazyflie
logs beside the pose and the accelerometer: the motor PWM (0 while the motors are off, spinning from take-off
to touchdown) and an accelerometer that is still at rest (0.001 g of noise on the floor, as NanoBench's
onboard-filtered IMU) and vibrates while the motors run.  It can start late (logging began in the air),
stop early (the vehicle still flying), and add a hand pick-up after landing (the vehicle lifted with the
motors off).  Write it in any format with `ingest.sim.export.write_canonical_flight` (ALL_CANONICAL_FORMATS;
the motor PWM only in MOTOR_FORMATS); its
``meta["sim_start_s"]`` puts it on simulation time, where `flight_truth` says when the vehicle really was
airborne.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..flight import Flight
from ..frames import GRAVITY
from .simulation import SimulatedFlight

HOVER_PWM = 40_000.0          # a Crazyflie 2.1 hovers at ~60 % of the 16-bit PWM range
PWM_NOISE = 300.0
REST_NOISE_G = 0.001          # NanoBench on the floor: 0.001 g (onboard low-pass)
VIBRATION_G = 0.01            # motors running: 0.005-0.05 g on NanoBench
HAND_TREMOR_G = 0.02          # held in a hand: tremor and the hand's motion
HAND_LIFT_M = 0.6             # the vehicle is lifted this high ...
HAND_LIFT_S = 1.0             # ... over this long
HAND_WAIT_S = 1.0             # after lying this long on the floor after touchdown


@dataclass
class Truth:
    """When the simulated vehicle was airborne (simulation time, s).

    Attributes
    ----------
    lift_off_s : float
        The vehicle first rises ``height_m`` above the floor.
    touch_down_s : float
        It last comes down below that height before the motors stop.
    motors_on_s, motors_off_s : float
        The motors start (take-off) and stop (touchdown).
    """
    lift_off_s: float
    touch_down_s: float
    motors_on_s: float
    motors_off_s: float


def flight_truth(sim: SimulatedFlight, height_m: float = 0.10) -> Truth:
    """The simulator's truth of when the flight was airborne, from the true heights."""
    truth = sim.truth
    floor = float(truth.p[0, 2])
    powered = (truth.t >= sim.phases.takeoff) & (truth.t <= sim.phases.touchdown)
    airborne = truth.t[powered & (truth.p[:, 2] > floor + height_m)]
    return Truth(float(airborne[0]), float(airborne[-1]), sim.phases.takeoff, sim.phases.touchdown)


def recording(sim: SimulatedFlight, *, start_s: float | None = None, stop_s: float | None = None,
              hand_pickup: bool = False, motors: bool = True, rate_hz: float = 100.0, seed: int = 0) -> Flight:
    """The simulated flight as a log recorded from ``start_s`` to ``stop_s`` (simulation time, s).

    Parameters
    ----------
    sim : SimulatedFlight
        Simulated with enough ground time after touchdown for a hand pick-up (``Timing.sit_after_s`` >=
        HAND_WAIT_S + HAND_LIFT_S + 1 s) when ``hand_pickup``.
    start_s, stop_s : float, optional
        The stretch recorded (default: the whole simulation).
    hand_pickup : bool
        Lift the vehicle by HAND_LIFT_M, motors off, HAND_WAIT_S after touchdown.
    motors : bool
        Carry the ``motors`` channel (PWM, 4 motors); without it only the pose and accelerometer tell.
    rate_hz : float
        Grid rate, Hz.
    seed : int
        Noise seed.

    Returns
    -------
    Flight
        ``t`` (s) from the recording's start, which lies at simulation time ``meta["sim_start_s"]``; ``p``
        (m), ``quat``, ``a_meas`` (m/s², world), channels ``acc_body`` (m/s², body) and ``motors`` (PWM,
        when asked).
    """
    rng = np.random.default_rng(seed)
    start = 0.0 if start_s is None else start_s
    stop = sim.phases.end if stop_s is None else stop_s
    t = start + np.arange(int(np.floor((stop - start) * rate_hz + 1e-9)) + 1) / rate_hz
    states = sim.truth.at(t)
    p, a = states.p.copy(), states.a.copy()
    powered = (t >= sim.phases.takeoff) & (t <= sim.phases.touchdown)
    held = np.zeros(len(t), dtype=bool)
    if hand_pickup:
        u = (t - (sim.phases.touchdown + HAND_WAIT_S)) / HAND_LIFT_S
        inside = np.clip(u, 0.0, 1.0)
        h = inside ** 3 * (10 - 15 * inside + 6 * inside ** 2)
        ddh = np.where((u > 0) & (u < 1), 60 * inside * (1 - inside) * (1 - 2 * inside), 0.0) / HAND_LIFT_S ** 2
        p[:, 2] += HAND_LIFT_M * h
        a[:, 2] += HAND_LIFT_M * ddh
        held = u > 0
    from scipy.spatial.transform import Rotation  # scipy.spatial costs ~0.5 s to import: on first use

    body = Rotation.from_quat(states.quat).inv().apply(a + [0.0, 0.0, GRAVITY])
    noise_g = np.where(powered, VIBRATION_G, np.where(held, HAND_TREMOR_G, REST_NOISE_G))
    body += rng.normal(0.0, 1.0, body.shape) * (noise_g * GRAVITY)[:, None]
    p += rng.normal(0.0, sim.sensors.mocap_position_noise_m, p.shape)
    channels = {"acc_body": body}
    if motors:
        channels["motors"] = np.where(powered[:, None], HOVER_PWM + rng.normal(0.0, PWM_NOISE, (len(t), 4)), 0.0)
    acc_world = Rotation.from_quat(states.quat).apply(body) - [0.0, 0.0, GRAVITY]
    return Flight(t - start, p, acc_world, states.quat, channels,
                  {"name": sim.name, "rate_hz": rate_hz, "sim_start_s": start})
