"""The analytic flight the MCAP and ROS-bag tests (and the bag decoders' hostile-input tests) write and read
back: a circle at 1 m height, attitude from the thrust direction, varying yaw."""
import numpy as np
from scipy.spatial.transform import Rotation

from learnest.ingest.frames import GRAVITY

RADIUS, OMEGA = 0.6, 1.5             # m, rad/s: 1.35 m/s² centripetal acceleration
DURATION = 6.0                       # s
MOCAP_RATE, IMU_RATE = 100.0, 250.0  # Hz; the 100 Hz grid meets every mocap sample, every other IMU one
Z_UP = np.array([0.0, 0.0, 1.0])


def true_position(t):
    return np.column_stack([RADIUS * np.cos(OMEGA * t), RADIUS * np.sin(OMEGA * t), 1.0 + 0.05 * np.sin(0.8 * t)])


def true_acceleration(t):
    return np.column_stack([-RADIUS * OMEGA**2 * np.cos(OMEGA * t), -RADIUS * OMEGA**2 * np.sin(OMEGA * t),
                            -0.05 * 0.64 * np.sin(0.8 * t)])


def true_rotation(t):
    """Body-to-world rotations: body z along the thrust a + g ẑ with a varying yaw, then a fixed 6°/4°
    mounting tilt so that every accelerometer axis carries signal (an axis mix-up cannot pass)."""
    z_thrust = true_acceleration(t) + GRAVITY * Z_UP
    z_thrust /= np.linalg.norm(z_thrust, axis=1, keepdims=True)
    yaw = 0.4 + 0.8 * np.sin(2.0 * t)
    heading = np.column_stack([np.cos(yaw), np.sin(yaw), np.zeros_like(yaw)])
    y_body = np.cross(z_thrust, heading)
    y_body /= np.linalg.norm(y_body, axis=1, keepdims=True)
    x_body = np.cross(y_body, z_thrust)
    thrust_frame = np.stack([x_body, y_body, z_thrust], axis=-1)
    return thrust_frame @ Rotation.from_euler("xy", [0.10, -0.07]).as_matrix()


def true_quaternion(t):
    return Rotation.from_matrix(true_rotation(t)).as_quat()      # scalar last, like the Flight


def accelerometer_g(t):
    """What an ideal accelerometer reads: the specific force R^T (a + g ẑ) in the body frame, in g."""
    return np.einsum("tji,tj->ti", true_rotation(t), true_acceleration(t) + GRAVITY * Z_UP) / GRAVITY


def mocap_times(duration=DURATION, rate=MOCAP_RATE):
    return np.arange(int(round(duration * rate)) + 1) / rate


def imu_times(duration=DURATION, rate=IMU_RATE):
    return np.arange(int(round(duration * rate)) + 1) / rate


def acc_interpolation_tolerance(imu_rate=IMU_RATE):
    """Bound on |a_meas - a_true| at grid points: the mocap attitude is exact there (every grid point is a
    mocap sample), so the only error is the linear interpolation of the accelerometer between its samples:
    per axis at most dt²/8 · max|f''|, scaled by g and rotated (rotation keeps the norm)."""
    fine = np.linspace(0.0, DURATION, 60001)
    second_derivative = np.gradient(np.gradient(accelerometer_g(fine), fine, axis=0), fine, axis=0)
    per_axis = (1.0 / imu_rate) ** 2 / 8 * np.abs(second_derivative).max(axis=0)
    # A 250 Hz IMU is low-passed before the 100 Hz grid (ingest.align.anti_alias): this signal has nothing above
    # 40 Hz, but the zero-phase filter starts up at the recording's edges, which costs up to ~3e-7 m/s² there.
    filter_start_up = 5e-7 if imu_rate > 1.5 * 100.0 else 0.0
    return 1.05 * GRAVITY * float(np.linalg.norm(per_axis)) + 1e-9 + filter_start_up   # 5 %: estimate of f''


def source_times(flight):
    """The recording time (s from the first message) of each Flight row."""
    start = flight.meta.get("flying_window", {}).get("start_s", 0.0)
    return flight.t + flight.meta["t0_source_s"] + start


def assert_matches_truth(flight, acc_tolerance, position_tolerance=1e-6):
    t = source_times(flight)
    np.testing.assert_allclose(flight.p, true_position(t), rtol=0, atol=position_tolerance)
    error = np.linalg.norm(flight.a_meas - true_acceleration(t), axis=1)
    assert error.max() <= acc_tolerance, (error.max(), acc_tolerance)
