"""Frame math shared by every layer: gravity, quaternions, body<->world, the IMU's mounting rotation.

Imports nothing of ours, so models and estimators may use it without pulling in the readers.
Quaternions are scalar-last [qx, qy, qz, qw]; "world" is z-up.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from scipy.spatial.transform import Rotation

GRAVITY = 9.80665  # m/s², standard gravity


def imu_misalignment(roll: float, pitch: float) -> Rotation:
    """Rotation body <- IMU of an accelerometer mounted tilted by roll (about x), then pitch (about y):
    it reads R⁻¹ f for the body-frame specific force f.  The simulator and the diagnosis share it."""
    from scipy.spatial.transform import Rotation  # scipy.spatial costs ~0.5 s to import: on first use

    return Rotation.from_euler("ZYX", [0.0, pitch, roll])


def quat_to_matrix(quat: np.ndarray) -> np.ndarray:
    """(T, 4) scalar-last unit quaternions -> (T, 3, 3) body-to-world rotation matrices."""
    q = np.asarray(quat, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def world_acceleration(acc_body_g: np.ndarray, quat: np.ndarray) -> np.ndarray:
    """Body-frame specific force in g -> world-frame acceleration in m/s² with gravity removed."""
    specific_force = np.einsum("tij,tj->ti", quat_to_matrix(quat), np.asarray(acc_body_g) * GRAVITY)
    return specific_force - np.array([0.0, 0.0, GRAVITY])
