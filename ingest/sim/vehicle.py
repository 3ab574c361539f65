"""The vehicle and its closed loop: PD + feed-forward position control, thrust along the current body z,
a first-order attitude lag, linear rotor drag, integrated at 1 kHz; the true states it flies."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..frames import GRAVITY
from .trajectories import SIM_RATE_HZ, Phases, Reference

CRAZYFLIE_MASS_KG = 0.032
# Rotor drag of a Crazyflie 2.x: Förster's system identification (ETH Zurich, 2015) gives ≈ 9.2e-7 kg/rad
# times the summed rotor speed; at hover each rotor turns ≈ 1850 rad/s (m g / 4 = k_thrust ω², k_thrust
# ≈ 2.3e-8 N s²), so k_drag ≈ 9.2e-7 · 4 · 1850 ≈ 0.007 kg/s: 0.2 m/s² of deceleration at 1 m/s, small
# next to the manoeuvres but visible to an estimator (it is the kind of residual a learned model finds).
CRAZYFLIE_DRAG_KG_S = 0.007
# Total thrust of four 7 mm motors with stock propellers is ≈ 58 g (thrust-to-weight ≈ 1.8).
CRAZYFLIE_MAX_THRUST_N = 0.57


@dataclass
class Vehicle:
    """The simulated quadrotor and its position controller (defaults: a Crazyflie 2.x).

    Attributes
    ----------
    mass : float
        kg.
    drag : float
        Linear, isotropic rotor drag, kg/s (force -drag · v, world frame).
    attitude_tau_s : float
        Time constant of the first-order attitude lag, s.
    max_thrust_n : float
        Total thrust limit, N (the commanded thrust is clipped to [0, max_thrust_n]).
    kp, kd : (3,) tuples
        PD gains per world axis (x, y, z), 1/s² and 1/s.
    """
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
        from scipy.spatial.transform import Rotation  # scipy.spatial costs ~0.5 s to import: on first use

        world = self.a + [0.0, 0.0, GRAVITY]
        return Rotation.from_quat(self.quat).inv().apply(world)


def fly(ref: Reference, phases: Phases, vehicle: Vehicle) -> States:
    """The true states over the whole reference: resting before take-off, the closed loop from take-off to
    touchdown, resting where it touched down after (motors off)."""
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
    return States(ref.t, p, v, a, quat, omega)
