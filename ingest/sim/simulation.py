"""A closed-loop Crazyflie simulator that writes every supported log format, with the truth kept.

Model (world frame z-up, SI units, quaternions scalar-last as in ingest.flight):
  translation   m p̈ = T R e3 − m g e3 − k_drag v        (linear rotor drag, isotropic)
  control       a_cmd = a_ref + Kp (p_ref − p) + Kd (v_ref − v);  F = m (a_cmd + g e3);
                desired body z along F, desired yaw from the reference;  T = F · (R e3), clamped to
                [0, max_thrust] (the thrust acts along the *current* body z, as in Lee/Mellinger)
  attitude      first-order lag towards the desired attitude (time constant τ, yaw included): every
                step rotates the body by the fraction 1 − exp(−dt/τ) of the rotation that is left
  integration   1 kHz, control held over each step (the firmware's loop rate).  Translation by
                semi-implicit Euler (v += a dt, then p += v dt): the recorded a_k is then *exactly* the
                central second difference of the recorded positions, so the truth is self-consistent to
                machine precision; the attitude step is the exact solution of the lag for a target held
                over the step, and the body rate is that step's rotation / dt (integrating the true gyro
                reproduces the true attitudes exactly).
  ground        the vehicle rests (v = a = 0, motors off) level before take-off, and after the landing
                reference reaches the ground where and as it touched down (within mm of z = 0).

Flight timeline (Timing): sit on the ground, take off vertically (minimum-jerk) to the trajectory's start,
hover, fly the trajectory (its speed ramps up and down smoothly), hover, land vertically, sit.  So the
take-off/landing cut of ingest.align applies as on real logs.

Sensors (SensorModel, all parameters known):
  mocap          100 Hz: position + white noise (0.5 mm), attitude · exp(white rotation noise)
  accelerometer  500 Hz, body specific force f = R^T (p̈ + g e3) in g, then in this order:
                 misalignment (IMU frame = body rotated by roll, then pitch:  f_imu = R_mis^T f),
                 scale and bias (IMU axes, bias in m/s²), first-order low-pass (`lowpass_hz`, run at
                 1 kHz), delay (the sample stamped t holds the value of t − delay_s), white noise (g)
  gyro           same stamps, misalignment and delay as the accelerometer; white noise (rad/s)

`write_flight` writes a SimulatedFlight as nanobench, usd, usd-v1, vicon+cfclient, mcap-ros2 or mcap-json;
`sim_times` maps a Flight read back from those files onto simulation time; `make_sample_logs` writes the
bundled sample_logs/ (python -m learnest.ingest.sim.simulation [DIR]).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.signal import lfilter, lfilter_zi
from scipy.spatial.transform import Rotation

from ..flight import Flight
from ..formats.crazyflie_usd import reader as usd
from ..formats.mcap import reader as mcap_log
from ..formats.nanobench import reader as nanobench
from ..formats.vicon_cfclient.reader import write_cfclient_csv, write_vicon_csv
from ..frames import GRAVITY, imu_misalignment

SIM_RATE_HZ = 1000.0
CRAZYFLIE_MASS_KG = 0.032
# Rotor drag of a Crazyflie 2.x: Förster's system identification (ETH Zurich, 2015) gives ≈ 9.2e-7 kg/rad
# times the summed rotor speed; at hover each rotor turns ≈ 1850 rad/s (m g / 4 = k_thrust ω², k_thrust
# ≈ 2.3e-8 N s²), so k_drag ≈ 9.2e-7 · 4 · 1850 ≈ 0.007 kg/s: 0.2 m/s² of deceleration at 1 m/s, small
# next to the manoeuvres but visible to an estimator (it is the kind of residual a learned model finds).
CRAZYFLIE_DRAG_KG_S = 0.007
# Total thrust of four 7 mm motors with stock propellers is ≈ 58 g (thrust-to-weight ≈ 1.8).
CRAZYFLIE_MAX_THRUST_N = 0.57

# Where simulation time 0 lies on each file's own clock (see sim_times).
NANOBENCH_EPOCH_S = 1_700_000_000.0     # NanoBench stamps rows with Unix time
USD_BOOT_S = 23.456                     # uSD stamps: time since the Crazyflie booted
CFCLIENT_BOOT_S = 41.237                # cfclient Timestamp: ms since boot (another boot than the uSD one)
VICON_START_S = 0.2                     # the Vicon capture starts 0.2 s after the cfclient log
# The pair's two clocks: t_vicon = t_cfclient + CFCLIENT_CLOCK_OFFSET_S (t_cfclient = Timestamp / 1000).
CFCLIENT_CLOCK_OFFSET_S = -(CFCLIENT_BOOT_S + VICON_START_S)
CFCLIENT_RATE_HZ = 100.0                # a cfclient log block runs at ≤ 100 Hz over the radio

FORMATS = ("nanobench", "usd", "usd-v1", "vicon+cfclient", "mcap-ros2", "mcap-json")
SOURCE_TIME_AT_SIM_ZERO = {"nanobench": NANOBENCH_EPOCH_S, "usd": USD_BOOT_S, "usd-v1": USD_BOOT_S,
                           "vicon+cfclient": -VICON_START_S, "mcap-ros2": 0.0, "mcap-json": 0.0}


# -- quintic smoothstep: the building block of every smooth start and stop -------------------------------
def _smoothstep(u):
    """h(u) = 10u³ − 15u⁴ + 6u⁵ on [0, 1] (clipped) with h', h'' and the integral H: zero velocity and
    acceleration at both ends, so references start and stop without a jump in acceleration."""
    u = np.clip(u, 0.0, 1.0)
    h = u ** 3 * (10 - 15 * u + 6 * u * u)
    dh = 30 * u * u * (1 - u) ** 2
    ddh = 60 * u * (1 - u) * (1 - 2 * u)
    integral = u ** 4 * (2.5 - 3 * u + u * u)
    return h, dh, ddh, integral


def _minimum_jerk(t, start, stop, duration):
    """(p, v, a) of a rest-to-rest minimum-jerk move from start to stop; held at the ends."""
    h, dh, ddh, _ = _smoothstep(np.asarray(t, float) / duration)
    delta = np.asarray(stop, float) - np.asarray(start, float)
    return (start + h[:, None] * delta, (dh / duration)[:, None] * delta,
            (ddh / duration ** 2)[:, None] * delta)


# -- trajectories ------------------------------------------------------------------------------------------
@dataclass(kw_only=True)
class Trajectory:
    """A path p(s) in the nominal time s.  Flown over `duration_s`: the speed ds/dt ramps smoothly from
    0 to 1 over ramp_s, stays at 1, and ramps down over the last ramp_s, so s runs over [0, s_end]."""
    duration_s: float = 10.0
    ramp_s: float = 1.5

    @property
    def s_end(self) -> float:
        return self.duration_s - self.ramp_s

    def path(self, s):
        """(p, dp/ds, d²p/ds²), each (N, 3)."""
        raise NotImplementedError

    def flown(self, tau):
        """(p, v, a, s) at times tau from the start of the flying part (held outside it)."""
        if self.duration_s < 2 * self.ramp_s:
            raise ValueError("duration_s must be at least twice ramp_s")
        tau = np.clip(np.asarray(tau, float), 0.0, self.duration_s)
        r = self.ramp_s
        s, s_dot, s_ddot = tau - r / 2, np.ones_like(tau), np.zeros_like(tau)
        up, down = tau < r, tau > self.duration_s - r
        h, dh, _, integral = _smoothstep(tau / r)
        s[up], s_dot[up], s_ddot[up] = r * integral[up], h[up], dh[up] / r
        h, dh, _, integral = _smoothstep((self.duration_s - tau) / r)
        s[down], s_dot[down], s_ddot[down] = self.s_end - r * integral[down], h[down], -dh[down] / r
        p, dp, ddp = self.path(s)
        return p, dp * s_dot[:, None], ddp * (s_dot ** 2)[:, None] + dp * s_ddot[:, None], s


@dataclass(kw_only=True)
class Circle(Trajectory):
    """Counter-clockwise circle at constant speed, starting at center + (radius, 0)."""
    radius: float = 0.5
    speed: float = 0.5
    altitude: float = 1.0
    center: tuple = (0.0, 0.0)

    def path(self, s):
        w = self.speed / self.radius
        angle = w * np.asarray(s, float)
        c, sn, zero = np.cos(angle), np.sin(angle), np.zeros_like(angle)
        p = np.column_stack([self.center[0] + self.radius * c, self.center[1] + self.radius * sn,
                             np.full_like(angle, self.altitude)])
        dp = self.radius * w * np.column_stack([-sn, c, zero])
        ddp = -self.radius * w * w * np.column_stack([c, sn, zero])
        return p, dp, ddp


@dataclass(kw_only=True)
class Figure8(Trajectory):
    """Lemniscate of Gerono: x = size·sin(Ωs), y = (size/2)·sin(2Ωs), Ω = 2π/period; starts at the centre."""
    size: float = 0.6
    period: float = 6.0
    altitude: float = 1.0
    center: tuple = (0.0, 0.0)

    def path(self, s):
        w = 2 * np.pi / self.period
        angle = w * np.asarray(s, float)
        zero = np.zeros_like(angle)
        half = self.size / 2
        p = np.column_stack([self.center[0] + self.size * np.sin(angle),
                             self.center[1] + half * np.sin(2 * angle), np.full_like(angle, self.altitude)])
        dp = np.column_stack([self.size * w * np.cos(angle), half * 2 * w * np.cos(2 * angle), zero])
        ddp = np.column_stack([-self.size * w * w * np.sin(angle), -half * 4 * w * w * np.sin(2 * angle), zero])
        return p, dp, ddp


@dataclass(kw_only=True)
class RandomWaypoints(Trajectory):
    """A C² cubic spline through `count` random points in `box` (seeded), knots spaced by distance/speed,
    zero velocity at both ends.  duration_s follows from the path (length / speed + ramp_s)."""
    count: int = 5
    box: tuple = ((-0.8, 0.8), (-0.8, 0.8), (0.6, 1.3))
    speed: float = 0.5
    seed: int = 0
    duration_s: float = field(init=False, default=0.0)  # follows from the path

    def __post_init__(self):
        rng = np.random.default_rng(self.seed)
        low, high = np.array(self.box, float).T
        self.points = low + (high - low) * rng.random((self.count, 3))
        knots = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(self.points, axis=0), axis=1))] / self.speed
        self.duration_s = float(knots[-1] + self.ramp_s)
        self._spline = CubicSpline(knots, self.points, bc_type="clamped")

    def path(self, s):
        s = np.asarray(s, float)
        return self._spline(s), self._spline(s, 1), self._spline(s, 2)


# -- the reference over the whole flight -------------------------------------------------------------------
@dataclass
class Timing:
    sit_before_s: float = 1.5
    takeoff_s: float = 2.0
    hover_s: float = 0.5
    land_s: float = 2.0
    sit_after_s: float = 1.0


@dataclass
class Phases:
    """Simulation times (s) where the flight's phases begin."""
    takeoff: float
    fly: float          # the trajectory starts (speed ramps up)
    fly_end: float      # the trajectory ends (speed back to 0)
    land: float
    touchdown: float    # the landing reference reaches the ground; motors off
    end: float


@dataclass
class Reference:
    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    yaw: np.ndarray


def reference(trajectory: Trajectory, timing: Timing, yaw_rad: float, yaw_rate: float):
    """(Reference on the 1 kHz grid, Phases).  Yaw: yaw_rad + yaw_rate · s along the trajectory."""
    fly = timing.sit_before_s + timing.takeoff_s + timing.hover_s
    land = fly + trajectory.duration_s + timing.hover_s
    phases = Phases(takeoff=timing.sit_before_s, fly=fly, fly_end=fly + trajectory.duration_s, land=land,
                    touchdown=land + timing.land_s, end=land + timing.land_s + timing.sit_after_s)
    t = np.arange(int(round(phases.end * SIM_RATE_HZ)) + 1) / SIM_RATE_HZ

    first, last = trajectory.path(np.array([0.0, trajectory.s_end]))[0]
    ground_first, ground_last = first * [1, 1, 0], last * [1, 1, 0]
    p, v, a = (np.zeros((len(t), 3)) for _ in range(3))
    rising, flying, landing = t < phases.fly, (t >= phases.fly) & (t < phases.land), t >= phases.land
    for mask, values in ((rising, _minimum_jerk(t[rising] - phases.takeoff, ground_first, first, timing.takeoff_s)),
                         (flying, trajectory.flown(t[flying] - phases.fly)[:3]),
                         (landing, _minimum_jerk(t[landing] - phases.land, last, ground_last, timing.land_s))):
        p[mask], v[mask], a[mask] = values
    s = trajectory.flown(t - phases.fly)[3]
    return Reference(t, p, v, a, yaw_rad + yaw_rate * s), phases


# -- vehicle and closed loop -------------------------------------------------------------------------------
@dataclass
class Vehicle:
    mass: float = CRAZYFLIE_MASS_KG
    drag: float = CRAZYFLIE_DRAG_KG_S          # kg/s, linear, isotropic
    attitude_tau_s: float = 0.03
    max_thrust_n: float = CRAZYFLIE_MAX_THRUST_N
    # PD gains (1/s², 1/s): critically damped at 4 rad/s horizontally and 5.5 rad/s vertically, far
    # inside the stability bound Kd > τ·Kp that the attitude lag sets on the horizontal loop.
    kp: tuple = (16.0, 16.0, 30.0)
    kd: tuple = (8.0, 8.0, 11.0)


def _yaw_quat(yaw: float) -> tuple:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def _matrix_to_quat(r00, r01, r02, r10, r11, r12, r20, r21, r22) -> tuple:
    """Shepperd's method (scalar last), branch on the largest diagonal term for accuracy."""
    trace = r00 + r11 + r22
    if trace > 0:
        s = 2 * math.sqrt(trace + 1)
        return (r21 - r12) / s, (r02 - r20) / s, (r10 - r01) / s, s / 4
    if r00 > r11 and r00 > r22:
        s = 2 * math.sqrt(1 + r00 - r11 - r22)
        return s / 4, (r01 + r10) / s, (r02 + r20) / s, (r21 - r12) / s
    if r11 > r22:
        s = 2 * math.sqrt(1 + r11 - r00 - r22)
        return (r01 + r10) / s, s / 4, (r12 + r21) / s, (r02 - r20) / s
    s = 2 * math.sqrt(1 + r22 - r00 - r11)
    return (r02 + r20) / s, (r12 + r21) / s, s / 4, (r10 - r01) / s


def _desired_quat(fx, fy, fz, yaw_cos, yaw_sin) -> tuple:
    """Attitude with body z along the force F and the body x as close to the yaw heading as possible."""
    norm = math.sqrt(fx * fx + fy * fy + fz * fz)
    b3 = (fx / norm, fy / norm, fz / norm) if norm > 1e-9 else (0.0, 0.0, 1.0)
    b2 = (-b3[2] * yaw_sin, b3[2] * yaw_cos, b3[0] * yaw_sin - b3[1] * yaw_cos)     # b3 × heading
    n2 = math.sqrt(b2[0] ** 2 + b2[1] ** 2 + b2[2] ** 2)
    b2 = (b2[0] / n2, b2[1] / n2, b2[2] / n2)
    b1 = (b2[1] * b3[2] - b2[2] * b3[1], b2[2] * b3[0] - b2[0] * b3[2], b2[0] * b3[1] - b2[1] * b3[0])
    return _matrix_to_quat(b1[0], b2[0], b3[0], b1[1], b2[1], b3[1], b1[2], b2[2], b3[2])


def _closed_loop(ref: Reference, vehicle: Vehicle, start: int, stop: int, q0: tuple):
    """Integrate steps start..stop-1 of the reference; returns p, v, a, quat, omega for rows start..stop
    (row stop is the state after the last step, with a and omega left at zero)."""
    dt = 1.0 / SIM_RATE_HZ
    m, k_drag, g = vehicle.mass, vehicle.drag, GRAVITY
    kpx, kpy, kpz = vehicle.kp
    kdx, kdy, kdz = vehicle.kd
    alpha = 1.0 - math.exp(-dt / vehicle.attitude_tau_s)
    p_ref, v_ref, a_ref = (x[start:stop].tolist() for x in (ref.p, ref.v, ref.a))
    yaw_cos, yaw_sin = np.cos(ref.yaw[start:stop]).tolist(), np.sin(ref.yaw[start:stop]).tolist()

    rows = stop - start + 1
    out = np.zeros((rows, 16))    # p(3) v(3) a(3) quat(4) omega(3)
    px, py, pz = ref.p[start]
    vx = vy = vz = 0.0
    qx, qy, qz, qw = q0
    for k in range(rows - 1):
        (rx, ry, rz), (rvx, rvy, rvz), (rax, ray, raz) = p_ref[k], v_ref[k], a_ref[k]
        fx = m * (rax + kpx * (rx - px) + kdx * (rvx - vx))
        fy = m * (ray + kpy * (ry - py) + kdy * (rvy - vy))
        fz = m * (raz + kpz * (rz - pz) + kdz * (rvz - vz) + g)
        # thrust along the current body z axis
        bx, by, bz = 2 * (qx * qz + qy * qw), 2 * (qy * qz - qx * qw), 1 - 2 * (qx * qx + qy * qy)
        thrust = min(max(fx * bx + fy * by + fz * bz, 0.0), vehicle.max_thrust_n)
        ax = (thrust * bx - k_drag * vx) / m
        ay = (thrust * by - k_drag * vy) / m
        az = (thrust * bz - k_drag * vz) / m - g
        # attitude: rotate by the fraction alpha of the body-frame rotation to the desired attitude
        dx, dy, dz, dw = _desired_quat(fx, fy, fz, yaw_cos[k], yaw_sin[k])
        ex = qw * dx - qx * dw - qy * dz + qz * dy          # conj(q) ⊗ q_desired
        ey = qw * dy + qx * dz - qy * dw - qz * dx
        ez = qw * dz - qx * dy + qy * dx - qz * dw
        ew = qw * dw + qx * dx + qy * dy + qz * dz
        if ew < 0:
            ex, ey, ez, ew = -ex, -ey, -ez, -ew
        sine = math.sqrt(ex * ex + ey * ey + ez * ez)
        angle = alpha * 2 * math.atan2(sine, ew)
        if sine > 1e-15:
            ux, uy, uz = ex / sine, ey / sine, ez / sine
        else:
            ux = uy = uz = 0.0
        out[k] = (px, py, pz, vx, vy, vz, ax, ay, az, qx, qy, qz, qw,
                  ux * angle / dt, uy * angle / dt, uz * angle / dt)
        s, c = math.sin(angle / 2), math.cos(angle / 2)
        sx, sy, sz = ux * s, uy * s, uz * s
        qx, qy, qz, qw = (qw * sx + qx * c + qy * sz - qz * sy, qw * sy - qx * sz + qy * c + qz * sx,
                          qw * sz + qx * sy - qy * sx + qz * c, qw * c - qx * sx - qy * sy - qz * sz)
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
        qx, qy, qz, qw = qx / norm, qy / norm, qz / norm, qw / norm
        # semi-implicit Euler
        vx, vy, vz = vx + ax * dt, vy + ay * dt, vz + az * dt
        px, py, pz = px + vx * dt, py + vy * dt, pz + vz * dt
    out[-1, :13] = (px, py, pz, vx, vy, vz, 0, 0, 0, qx, qy, qz, qw)
    return out[:, 0:3], out[:, 3:6], out[:, 6:9], out[:, 9:13], out[:, 13:16]


# -- true states -------------------------------------------------------------------------------------------
@dataclass
class States:
    """True states at times t: p (m), v (m/s), a = p̈ (m/s², world), quat (body -> world, scalar last),
    omega (body rates, rad/s)."""
    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    a: np.ndarray
    quat: np.ndarray
    omega: np.ndarray

    def at(self, t) -> States:
        """Linear interpolation (normalised for quaternions); exact at the simulation's own steps."""
        t = np.asarray(t, float)

        def interp(values):
            return np.column_stack([np.interp(t, self.t, values[:, j]) for j in range(values.shape[1])])
        quat = interp(self.quat)
        return States(t, interp(self.p), interp(self.v), interp(self.a),
                      quat / np.linalg.norm(quat, axis=1, keepdims=True), interp(self.omega))

    def specific_force_body(self) -> np.ndarray:
        """What an ideal accelerometer at the centre of mass reads, m/s² in the body frame."""
        world = self.a + [0.0, 0.0, GRAVITY]
        return Rotation.from_quat(self.quat).inv().apply(world)


# -- sensors -----------------------------------------------------------------------------------------------
@dataclass
class SensorModel:
    mocap_rate_hz: float = 100.0
    mocap_position_noise_m: float = 0.0005
    mocap_attitude_noise_rad: float = 0.002
    imu_rate_hz: float = 500.0
    acc_noise_g: float = 0.02
    gyro_noise_rad_s: float = 0.005
    bias: tuple = (0.0, 0.0, 0.0)            # m/s², IMU axes
    scale: tuple = (1.0, 1.0, 1.0)
    delay_s: float = 0.0                     # > 0: the IMU lags the mocap
    misalignment: tuple = (0.0, 0.0)         # (roll, pitch) rad of the IMU frame vs the body frame
    lowpass_hz: float | None = None          # first-order, on the accelerometer

    @classmethod
    def ideal(cls, **changes) -> SensorModel:
        """No noise and no effects (then only the file formats' quantisation separates files from truth)."""
        return cls(**{"mocap_position_noise_m": 0.0, "mocap_attitude_noise_rad": 0.0, "acc_noise_g": 0.0,
                      "gyro_noise_rad_s": 0.0, **changes})

    def changes(self) -> dict:
        """Every setting that differs from the defaults (noise, rates and effects), for READMEs."""
        nominal = SensorModel()
        return {name: value for name, value in vars(self).items() if value != getattr(nominal, name)}

    def misalignment_rotation(self) -> Rotation:
        return imu_misalignment(*self.misalignment)     # body <- IMU


@dataclass
class Mocap:
    t: np.ndarray          # s, simulation time
    p: np.ndarray          # m, with noise
    quat: np.ndarray       # with noise
    truth: States


@dataclass
class Imu:
    t: np.ndarray          # s, simulation time (the stamps; with delay_s the values are older)
    acc_g: np.ndarray      # IMU frame, g
    gyro: np.ndarray       # IMU frame, rad/s
    truth: States          # at the stamps
    setpoint: np.ndarray   # the reference position at the stamps (m)


@dataclass
class SimulatedFlight:
    truth: States          # every 1 kHz step
    reference: Reference
    mocap: Mocap
    imu: Imu
    phases: Phases
    trajectory: Trajectory
    vehicle: Vehicle
    sensors: SensorModel
    seed: int
    name: str = "simulated"


def _sample_times(end_s: float, rate_hz: float) -> np.ndarray:
    return np.arange(int(np.floor(end_s * rate_hz + 1e-9)) + 1) / rate_hz


def _noise(seed: int, stream: int, shape, std: float) -> np.ndarray:
    """White noise of one sensor stream; each stream has its own generator, so changing one sensor's
    settings leaves the others' noise as it was."""
    if std == 0:
        return np.zeros(shape)
    return np.random.default_rng([seed, stream]).normal(0.0, std, shape)


def _sample_mocap(truth: States, sensors: SensorModel, seed: int) -> Mocap:
    t = _sample_times(truth.t[-1], sensors.mocap_rate_hz)
    exact = truth.at(t)
    p = exact.p + _noise(seed, 1, exact.p.shape, sensors.mocap_position_noise_m)
    quat = exact.quat
    if sensors.mocap_attitude_noise_rad > 0:
        jitter = Rotation.from_rotvec(_noise(seed, 2, exact.p.shape, sensors.mocap_attitude_noise_rad))
        quat = (Rotation.from_quat(exact.quat) * jitter).as_quat()
    return Mocap(t, p, quat, exact)


def _first_order_lowpass(values: np.ndarray, cutoff_hz: float, rate_hz: float) -> np.ndarray:
    """1/(τs + 1) as the pole-matched recursion y[k] = α x[k] + (1 − α) y[k−1], started in steady state at
    the first value.  It uses x[k], not the zero-order hold's x[k−1], so it leads that by one 1-kHz step."""
    alpha = 1.0 - math.exp(-2 * math.pi * cutoff_hz / rate_hz)
    b, a = [alpha], [1.0, alpha - 1.0]
    zi = lfilter_zi(b, a)[:, None] * values[:1]
    return lfilter(b, a, values, axis=0, zi=zi)[0]


def _delayed(t_sim, values, t_stamps, delay_s: float) -> np.ndarray:
    """Values at t_stamps − delay (held at the first value before the start)."""
    return np.column_stack([np.interp(t_stamps - delay_s, t_sim, values[:, j]) for j in range(values.shape[1])])


def _sample_imu(truth: States, ref: Reference, sensors: SensorModel, seed: int) -> Imu:
    t = _sample_times(truth.t[-1], sensors.imu_rate_hz)
    to_imu = sensors.misalignment_rotation().inv()
    force = to_imu.apply(truth.specific_force_body()) * sensors.scale + sensors.bias
    if sensors.lowpass_hz:
        force = _first_order_lowpass(force, sensors.lowpass_hz, SIM_RATE_HZ)
    acc = _delayed(truth.t, force, t, sensors.delay_s) / GRAVITY + _noise(seed, 3, (len(t), 3), sensors.acc_noise_g)
    rates = _delayed(truth.t, to_imu.apply(truth.omega), t, sensors.delay_s)
    gyro = rates + _noise(seed, 4, (len(t), 3), sensors.gyro_noise_rad_s)
    setpoint = np.column_stack([np.interp(t, ref.t, ref.p[:, j]) for j in range(3)])
    return Imu(t, acc, gyro, truth.at(t), setpoint)


def simulate(trajectory: Trajectory, *, vehicle: Vehicle | None = None, sensors: SensorModel | None = None,
             timing: Timing | None = None, yaw_rad: float = 0.0, yaw_rate: float = 0.0, seed: int = 0,
             name: str = "simulated") -> SimulatedFlight:
    """Fly `trajectory` (with take-off and landing) in closed loop and sample the sensors."""
    vehicle, sensors, timing = vehicle or Vehicle(), sensors or SensorModel(), timing or Timing()
    ref, phases = reference(trajectory, timing, yaw_rad, yaw_rate)
    n = len(ref.t)
    start, stop = int(round(phases.takeoff * SIM_RATE_HZ)), int(round(phases.touchdown * SIM_RATE_HZ))
    q0 = _yaw_quat(ref.yaw[start])
    p, v, a, omega = (np.zeros((n, 3)) for _ in range(4))
    quat = np.tile(q0, (n, 1))
    p[:start] = ref.p[start]
    flown = _closed_loop(ref, vehicle, start, stop, q0)
    for array, values in zip((p, v, a, quat, omega), flown):
        array[start:stop + 1] = values
    p[stop:], quat[stop:], v[stop:] = p[stop], quat[stop], 0.0   # motors off: resting where it touched down
    truth = States(ref.t, p, v, a, quat, omega)
    return SimulatedFlight(truth, ref, _sample_mocap(truth, sensors, seed), _sample_imu(truth, ref, sensors, seed),
                           phases, trajectory, vehicle, sensors, seed, name)


# -- writing the formats -----------------------------------------------------------------------------------
def _on_times(t_from, values, t_to) -> np.ndarray:
    return np.column_stack([np.interp(t_to, t_from, values[:, j]) for j in range(values.shape[1])])


def _decimated(imu: Imu, rate_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(t, acc_g, gyro, setpoint) at rate_hz: every n-th sample when the IMU rate is a multiple, as a
    log block samples the current value; otherwise interpolated."""
    ratio = (len(imu.t) - 1) / (imu.t[-1] * rate_hz)
    if abs(ratio - round(ratio)) < 1e-9 and round(ratio) >= 1:
        pick = slice(None, None, int(round(ratio)))
        return imu.t[pick], imu.acc_g[pick], imu.gyro[pick], imu.setpoint[pick]
    t = _sample_times(imu.t[-1], rate_hz)
    return t, _on_times(imu.t, imu.acc_g, t), _on_times(imu.t, imu.gyro, t), _on_times(imu.t, imu.setpoint, t)


def _write_nanobench(sim: SimulatedFlight, path: Path) -> list[Path]:
    # The NanoBench recorder resampled every onboard stream onto the Vicon stamps by linear interpolation.
    t = sim.mocap.t
    nanobench.write(path, NANOBENCH_EPOCH_S + t, sim.mocap.p, sim.mocap.quat, _on_times(sim.imu.t, sim.imu.acc_g, t),
                    gyro=_on_times(sim.imu.t, sim.imu.gyro, t), setpoint=_on_times(sim.imu.t, sim.imu.setpoint, t))
    return [path]


def _write_usd(sim: SimulatedFlight, path: Path, version: int, pose_stream: str) -> list[Path]:
    """The firmware's layout: a fixed-frequency stream at the IMU rate with acc (g), gyro (deg/s) and the
    setpoint (ctrltargetZ, int16 mm); the mocap pose (locSrv) either sample-and-hold inside it (what real
    logs hold) or in its own event stream at the mocap frames ("event")."""
    imu, mocap = sim.imu, sim.mocap
    fixed = {f"acc.{axis}": ("f", imu.acc_g[:, j]) for j, axis in enumerate("xyz")}
    fixed.update({f"gyro.{axis}": ("f", np.degrees(imu.gyro[:, j])) for j, axis in enumerate("xyz")})
    fixed.update({f"ctrltargetZ.{axis}": ("h", 1000 * imu.setpoint[:, j]) for j, axis in enumerate("xyz")})
    pose = np.column_stack([mocap.p, mocap.quat])
    names = ("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw")
    events = {"fixedFrequency": {"t": USD_BOOT_S + imu.t, "vars": fixed}}
    if pose_stream == "fixed":
        latest = np.searchsorted(mocap.t, imu.t + 1e-9, side="right") - 1     # the last frame received
        fixed.update({name: ("f", pose[latest, j]) for j, name in enumerate(names)})
    elif pose_stream == "event":
        pose_vars = {name: ("f", pose[:, j]) for j, name in enumerate(names)}
        events["locSrvPose"] = {"t": USD_BOOT_S + mocap.t, "vars": pose_vars}
    else:
        raise ValueError(f"usd pose_stream must be 'fixed' or 'event', not {pose_stream!r}")
    usd.write(path, events, version=version)
    return [path]


def _write_vicon_cfclient(sim: SimulatedFlight, vicon_path: Path, cfclient_path: Path) -> list[Path]:
    """Two clocks: the Vicon export counts from its first frame (VICON_START_S after the cfclient log
    began), the cfclient log stamps ms since boot (CFCLIENT_BOOT_S at simulation time 0)."""
    mocap = sim.mocap
    seen = mocap.t >= VICON_START_S - 1e-9
    write_vicon_csv(vicon_path, mocap.t[seen] - VICON_START_S, mocap.p[seen], mocap.quat[seen],
                    rate_hz=sim.sensors.mocap_rate_hz, units="mm")
    t, acc, gyro, setpoint = _decimated(sim.imu, CFCLIENT_RATE_HZ)
    extra = {f"gyro.{axis}": np.degrees(gyro[:, j]) for j, axis in enumerate("xyz")}
    extra.update({f"ctrltarget.{axis}": setpoint[:, j] for j, axis in enumerate("xyz")})
    write_cfclient_csv(cfclient_path, CFCLIENT_BOOT_S + t, acc, extra)
    return [vicon_path, cfclient_path]


def write_flight(sim: SimulatedFlight, fmt: str, directory, stem: str, *, usd_pose_stream: str = "fixed") -> list[Path]:
    """Write one simulated flight in format `fmt` (see FORMATS) into directory; returns the files to give to
    ingest.read_flights (the Vicon export first for "vicon+cfclient")."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    if fmt == "nanobench":
        return _write_nanobench(sim, directory / f"{stem}.csv")
    if fmt in ("usd", "usd-v1"):
        return _write_usd(sim, directory / stem, 2 if fmt == "usd" else 1, usd_pose_stream)
    if fmt == "vicon+cfclient":
        return _write_vicon_cfclient(sim, directory / f"{stem}_vicon.csv", directory / f"{stem}_cfclient.csv")
    if fmt in ("mcap-ros2", "mcap-json"):
        path = directory / f"{stem}.mcap"
        writer = mcap_log.write_ros2 if fmt == "mcap-ros2" else mcap_log.write_json
        writer(path, sim.mocap.t, sim.mocap.p, sim.mocap.quat, sim.imu.acc_g, t_acc=sim.imu.t)
        return [path]
    raise ValueError(f"unknown format {fmt!r} (one of {', '.join(FORMATS)})")


def sim_times(flight: Flight, fmt: str) -> np.ndarray:
    """Simulation time of every row of a Flight read back from a file that write_flight wrote in `fmt`.

    The Flight's t restarts at 0 where its grid starts (meta t0_source_s, on the file's clock) plus the
    take-off cut; each format puts simulation time 0 at SOURCE_TIME_AT_SIM_ZERO[fmt] on that clock (for
    vicon+cfclient, the Vicon clock, on which the Flight lives)."""
    start = flight.meta.get("flying_window", {}).get("start_s", 0.0)
    return flight.t + (flight.meta["t0_source_s"] - SOURCE_TIME_AT_SIM_ZERO[fmt]) + start


# -- sample logs -------------------------------------------------------------------------------------------
SAMPLE_CIRCLE = dict(radius=0.5, speed=0.6, altitude=1.0, duration_s=6.5)
SAMPLE_BIAS_M_S2 = (0.15, -0.10, 0.20)

# name -> (format, trajectory, simulate() keywords, write_flight() keywords, note for the README)
SAMPLE_FLIGHTS = {
    **{f"circle_rep{k}": ("nanobench", Circle(**SAMPLE_CIRCLE), {"seed": k}, {}, "")
       for k in (1, 2, 3, 4)},
    "effects_circle_acc_bias": ("nanobench", Circle(**SAMPLE_CIRCLE),
                                {"seed": 5, "sensors": SensorModel(bias=SAMPLE_BIAS_M_S2)}, {},
                                "constant accelerometer bias in m/s², IMU axes = body axes"),
    "pair_circle": ("vicon+cfclient", Circle(**SAMPLE_CIRCLE), {"seed": 6}, {},
                    f"two clocks: t_vicon = Timestamp/1000 + ({CFCLIENT_CLOCK_OFFSET_S:.3f} s); cfclient at "
                    f"{CFCLIENT_RATE_HZ:g} Hz"),
    "usd_figure8_v2": ("usd", Figure8(size=0.6, period=6.0, altitude=1.0, duration_s=7.0), {"seed": 7}, {},
                       "locSrv sample-and-hold in the 500 Hz fixed-frequency stream (real firmware layout)"),
    "usd_circle_v1_pose_event": ("usd-v1", Circle(**SAMPLE_CIRCLE), {"seed": 8}, {"usd_pose_stream": "event"},
                                 "version 1 (ms stamps); locSrv in its own event stream at the mocap frames"),
    "mcap_waypoints_ros2": ("mcap-ros2", RandomWaypoints(count=5, speed=0.5, seed=3),
                            {"seed": 9, "yaw_rad": 0.3, "yaw_rate": 0.2}, {},
                            "PoseStamped + sensor_msgs/Imu; yaw 0.3 rad + 0.2 rad/s along the path"),
    "mcap_figure8_json": ("mcap-json", Figure8(size=0.8, period=8.0, altitude=0.8, duration_s=7.0), {"seed": 10}, {},
                          "foxglove.PoseInFrame + learnest.Acceleration (g)"),
}


def sample_flight(name: str) -> SimulatedFlight:
    """The simulation behind one of the bundled sample logs (its truth included)."""
    _, trajectory, options, _, _ = SAMPLE_FLIGHTS[name]
    return simulate(trajectory, name=name, **options)


def make_sample_logs(directory) -> list[Path]:
    """Write every SAMPLE_FLIGHTS log and a README.md into directory (flat: `learnest demo` reads the
    files of one folder); deterministic.  Returns the files written."""
    directory = Path(directory)
    written, rows = [], []
    for name, (fmt, trajectory, _, write_options, note) in SAMPLE_FLIGHTS.items():
        sim = sample_flight(name)
        files = write_flight(sim, fmt, directory, name, **write_options)
        written += files
        rows.append((files, fmt, _trajectory_text(trajectory), sim, note))
    readme = directory / "README.md"
    readme.write_text(_readme(rows), encoding="utf-8")
    return written + [readme]


def _trajectory_text(trajectory: Trajectory) -> str:
    if isinstance(trajectory, Circle):
        return f"circle r {trajectory.radius:g} m, {trajectory.speed:g} m/s, z {trajectory.altitude:g} m"
    if isinstance(trajectory, Figure8):
        return f"figure-eight {trajectory.size:g} m, period {trajectory.period:g} s, z {trajectory.altitude:g} m"
    return f"{trajectory.count} random waypoints (seed {trajectory.seed}), {trajectory.speed:g} m/s"


def _readme(rows) -> str:
    nominal = SensorModel()
    lines = [
        "# Sample logs (simulated)",
        "",
        "Written by `python -m ingest.simulator sample_logs` (`ingest.simulator.make_sample_logs`): a closed-loop",
        "Crazyflie simulation (32 g, linear rotor drag 0.007 kg/s, PD + feed-forward position control, 30 ms",
        "attitude lag, 1 kHz) flying each trajectory with take-off and landing. Deterministic: the same code",
        "writes the same bytes. The truth behind a file: `ingest.simulator.sample_flight(stem)` (the pair:",
        "`sample_flight('pair_circle')`).",
        "",
        f"Sensors of every file: mocap {nominal.mocap_rate_hz:g} Hz with "
        f"{nominal.mocap_position_noise_m * 1e3:g} mm position and {nominal.mocap_attitude_noise_rad:g} rad "
        f"attitude noise; IMU {nominal.imu_rate_hz:g} Hz, accelerometer noise {nominal.acc_noise_g:g} g, "
        f"gyro noise {nominal.gyro_noise_rad_s:g} rad/s; no bias, scale error, delay, misalignment or low-pass.",
        "The sensors column lists every setting of a file that differs from these; there are no other effects.",
        "",
        "| file(s) | format | trajectory | flight | sensors | note |",
        "|---|---|---|---|---|---|",
    ]
    for files, fmt, trajectory, sim, note in rows:
        names = " + ".join(f"`{path.name}`" for path in files)
        flight = (f"{sim.phases.end:.1f} s (trajectory {sim.phases.fly:.1f}-{sim.phases.fly_end:.1f} s), "
                  f"seed {sim.seed}")
        changes = ", ".join(f"{name}={value}" for name, value in sim.sensors.changes().items()) or "nominal"
        lines.append(f"| {names} | {fmt} | {trajectory} | {flight} | {changes} | {note} |")
    lines += [
        "",
        "Train on one circle (`circle_rep1.csv`), evaluate on the other circles and on the other formats.",
        "Clocks: NanoBench `t` = 1.7e9 s + simulation time; uSD stamps = simulation time + "
        f"{USD_BOOT_S} s (boot); MCAP stamps start at 1.7e9 s; the Vicon export starts {VICON_START_S} s "
        f"after the cfclient log, whose Timestamp is ms since a boot {CFCLIENT_BOOT_S} s before the log "
        "(the reader estimates that offset from the data).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[2] / "sample_logs"
    for path in make_sample_logs(target):
        print(f"{path}  {path.stat().st_size / 1024:.0f} kB")
