"""The thrust axis against the mocap body frame: one small constant rotation per flight, calibrated from the
mocap pose alone.

Why: the Crazyflie prior turns thrust into world acceleration through the mocap attitude, R(q)·[0, 0, T]. A
quadrotor's thrust acts along its motor axes, so the specific force R(q)ᵀ(p̈ + g e₃) points along the thrust axis
whatever the vehicle does (rotor drag adds a few hundredths of g and averages out over a flight).  On real flights its
mean direction sits a few degrees off the mocap body z axis, different from flight to flight: each degree is about
0.17 m/s² of horizontal acceleration at hover, and the flights with the largest offset are where the Crazyflie prior
does worst against the kinematic one (the results page `docs/results/transfer.md`, "What the Crazyflie prior and
residual are given").  The mocap frame is where the markers are, not where the motors point; the offset is calibrated
per flight, from mocap position and attitude only (no accelerometer, no estimate): two numbers per flight, reported
with the evaluation.  The calibration is offline: it averages over the whole record, later samples included (two
numbers from thousands of samples), so an estimator fed the calibrated attitude is not strictly causal; a record too
short or too coarse to calibrate keeps its attitude as logged (zero offset).
"""
from __future__ import annotations

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.frames import GRAVITY, quat_to_matrix

# p̈ from twice-differentiated mocap position is noise above a few Hz; the mean direction needs the slow part
LOWPASS_HZ = 2.0
EDGE_S = 0.5          # the zero-phase filter's edges are left out
MIN_SECONDS = 3.0     # a shorter record gives no calibration (zero offset)
MIN_RATE_HZ = 2.5 * LOWPASS_HZ   # below this the low-pass is not defined: no calibration
MAX_OFFSET_RAD = np.radians(10.0)   # beyond this the record is not a flight with mocap on the vehicle


def thrust_axis_offset(p: np.ndarray, quat: np.ndarray, dt: float) -> np.ndarray:
    """The mean direction of the specific force in the mocap body frame, as small angles.

    Parameters
    ----------
    p : ndarray, shape (T, 3)
        Mocap position, world frame (z up), m.
    quat : ndarray, shape (T, 4)
        Mocap attitude, scalar-last unit quaternions (body -> world).
    dt : float
        Sample time, s.

    Returns
    -------
    ndarray, shape (2,)
        (d_x, d_y): the body-frame x and y components of the thrust axis's unit vector, the sines of its lean
        towards the mocap body's +x and +y (≈ the angles in rad at these few degrees).  Zero for a record
        shorter than `MIN_SECONDS` or sampled below `MIN_RATE_HZ`.

    Raises
    ------
    ValueError
        If the offset exceeds `MAX_OFFSET_RAD` (the attitude is not the vehicle's, or the record is not
        a flight), or position or attitude hold non-finite values.
    """
    from learnest.models.filters import lowpass

    p, quat = np.asarray(p, dtype=float), np.asarray(quat, dtype=float)
    edge = int(round(EDGE_S / dt))
    if len(p) * dt < MIN_SECONDS or 1.0 / dt < MIN_RATE_HZ:
        return np.zeros(2)
    if not np.isfinite(p).all():
        raise InvalidInput("the mocap position holds non-finite values")
    _check_attitude(quat)
    acc = lowpass(np.gradient(np.gradient(p, dt, axis=0), dt, axis=0), dt, LOWPASS_HZ)
    force_world = acc + np.array([0.0, 0.0, GRAVITY])
    force_body = np.einsum("tji,tj->ti", quat_to_matrix(quat), force_world)[edge:len(p) - edge]
    direction = (force_body / np.linalg.norm(force_body, axis=1, keepdims=True)).mean(axis=0)
    direction /= np.linalg.norm(direction)
    if np.hypot(direction[0], direction[1]) > np.sin(MAX_OFFSET_RAD):
        raise InvalidInput(f"the specific force leans {np.degrees(np.arcsin(np.hypot(*direction[:2]))):.1f}° off the "
                         f"mocap body z axis on average (at most {np.degrees(MAX_OFFSET_RAD):.0f}° expected): "
                         "is the mocap attitude the vehicle's?")
    return direction[:2].copy()


def calibrated_attitude(quat: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """The attitude whose body z axis is the thrust axis: q ⊗ q_δ, with q_δ the shortest rotation taking e₃
    to the unit vector (d_x, d_y, √(1 − d_x² − d_y²)) of `thrust_axis_offset`.

    Parameters
    ----------
    quat : ndarray, shape (T, 4)
        Mocap attitude, scalar-last.
    offset : ndarray, shape (2,)
        (d_x, d_y), the sines `thrust_axis_offset` returns.

    Returns
    -------
    ndarray, shape (T, 4)
        Scalar-last quaternions with R(q ⊗ q_δ) e₃ = R(q) d.
    """
    from scipy.spatial.transform import Rotation  # scipy.spatial costs ~0.5 s to import: on first use

    _check_attitude(quat)
    dx, dy = float(offset[0]), float(offset[1])
    sine = np.hypot(dx, dy)
    if sine == 0.0:
        return np.asarray(quat, dtype=float).copy()
    axis = np.array([-dy, dx, 0.0]) / sine          # e₃ × d, normalised
    delta = Rotation.from_rotvec(axis * np.arcsin(min(sine, 1.0)))
    return (Rotation.from_quat(quat) * delta).as_quat()


def heading_removed(quat: np.ndarray) -> np.ndarray:
    """The attitude with the same body z axis and no heading: the shortest rotation taking e₃ to R(q) e₃.

    Why: the Crazyflie prior's world-frame acceleration depends on the attitude only through the body z axis
    (the thrust direction; its rotor drag is the same along body x and y, so R diag(k_xy, k_xy, k_z) Rᵀ
    depends on R e₃ alone), so the heading is no physics to it, as the position is none.  A KNODE residual
    that reads the heading learns the training flight's, which misleads it on a flight flown at another
    heading (all of that flight's samples outside the training box in qw); on the heading-free input the
    residual cannot tell the two headings apart.

    Parameters
    ----------
    quat : ndarray, shape (T, 4)
        Scalar-last unit quaternions (body -> world).

    Returns
    -------
    ndarray, shape (T, 4)
        Scalar-last unit quaternions with qz = 0 and the same R e₃.  A vehicle upside down (R e₃ = −e₃) has
        no shortest rotation; it maps to a roll of π.
    """
    _check_attitude(quat)
    body_z = quat_to_matrix(quat)[:, :, 2]
    # half-angle form of the rotation e₃ -> z about e₃ × z: (e₃ × z, 1 + e₃·z), normalised
    q = np.column_stack([-body_z[:, 1], body_z[:, 0], np.zeros(len(body_z)), 1.0 + body_z[:, 2]])
    norms = np.linalg.norm(q, axis=1)
    flipped = norms < 1e-9
    q[flipped] = [1.0, 0.0, 0.0, 0.0]
    norms[flipped] = 1.0
    return q / norms[:, None]


def _check_attitude(quat: np.ndarray) -> None:
    norms = np.linalg.norm(quat, axis=-1)
    if not (np.isfinite(norms).all() and (norms > 0).all()):
        bad = np.flatnonzero(~(np.isfinite(norms) & (norms > 0)))
        raise InvalidInput(f"the attitude holds non-finite or zero quaternions ({len(bad)} rows, first at row "
                           f"{bad[0]})")
