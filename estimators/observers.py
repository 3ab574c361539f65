"""Pre-training observers g (eq. 6): measurements -> state observations ζ for Algorithm 1.

As in Sec. V: a KF for the cartpole and the quadrotor, a precursory UKF followed by a linear KF for the
ground robot.  They run offline, so each ends with a Rauch-Tung-Striebel backward pass (no lag to learn).
The model-based alternative is the unscented RTS smoother (`smoother.run_urts`) with a given model's bundle
(the prior, or a KNODE learned in an earlier round, `estimators.algorithm1`).
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from learnest.models.checks import check_dt, check_sequence
from learnest.models.knode import HybridModel
from learnest.models.noise import NoiseModel
from learnest.models.systems import GroundRobot, System, make_system

from .batch import batch_smoother
from .kf import kinematic_smoother, linearize
from .params import EstimatorParams
from .prepared import model_params
from .smoother import run_urts
from .ukf import run_ukf


def observe_cartpole(system: System, y: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """Constant-acceleration KF + RTS on the measured position and angle gives their rates.

    y (T, 2) = [p (m), α (rad)] -> ζ (T, 4) = [p, ṗ, α, α̇]; ``u`` is unused.
    """
    pos, vel, _ = kinematic_smoother(y, dt, meas_std=system.meas_noise_std, jerk_std=200.0)
    return np.column_stack([pos[:, 0], vel[:, 0], pos[:, 1], vel[:, 1]])


class _PlanarKinematics:
    """Constant-velocity point in the plane with a slowly varying heading, seen by the robot's sensors."""

    def __init__(self, robot: GroundRobot) -> None:
        self.robot, self.n, self.n_inputs, self.n_meas = robot, 5, 0, robot.n_meas

    def step(self, x: np.ndarray, u: np.ndarray | None, dt: float) -> np.ndarray:
        out = np.array(x, dtype=float, copy=True)
        out[..., 0] += dt * x[..., 2]
        out[..., 1] += dt * x[..., 3]
        return out

    def h(self, x: np.ndarray, u: np.ndarray | None = None) -> np.ndarray:
        state = np.stack([x[..., 0], x[..., 1], np.hypot(x[..., 2], x[..., 3]), x[..., 4]], axis=-1)
        return self.robot.h(state)


def observe_robot(system: System, y: np.ndarray, u: np.ndarray, dt: float, smooth: bool = False) -> np.ndarray:
    """Precursory UKF (ranges + heading -> position, heading), then a linear KF + RTS for the speed.

    y (T, 5) = [r1..r4 (m), ψ (rad)] -> ζ (T, 4) = [x (m), y (m), v (m/s), ψ (rad)]; ``u`` is unused.
    ``system`` must be a `GroundRobot` (its sensor positions locate the robot).  ``smooth`` adds the
    unscented RTS backward pass to the precursory UKF (the paper's observer is the filter alone).
    """
    if not isinstance(system, GroundRobot):
        raise TypeError(f"observe_robot needs a GroundRobot, got {type(system).__name__}")
    kinematics = _PlanarKinematics(system)
    x0 = _trilaterate(system, y[0])
    Q = np.diag([1e-6, 1e-6, 4e-4, 4e-4, 1e-4])
    P0 = np.diag([1.0, 1.0, 4.0, 4.0, 0.1])
    # the robot's sensors with their fixed (the paper's) noise; Q and P0 are the observer's own, for its kinematics
    params = EstimatorParams(kinematics, dt, Q, NoiseModel.paper(system).R, P0, x0)
    forward = (run_urts(params, y) if smooth else run_ukf(params, y)).means
    planar = np.column_stack([forward[:, 0], forward[:, 1], forward[:, 4]])
    pos, vel, _ = kinematic_smoother(planar, dt, meas_std=[0.03, 0.03, np.deg2rad(0.5)], jerk_std=5.0)
    speed = np.hypot(vel[:, 0], vel[:, 1])
    return np.column_stack([pos[:, 0], pos[:, 1], speed, pos[:, 2]])


def _trilaterate(system: GroundRobot, ranges: np.ndarray) -> np.ndarray:
    """Least-squares position from the first set of ranges (linearised by differencing sensor 0)."""
    s = np.asarray(system.sensors)
    r = np.asarray(ranges[: len(s)])
    A = 2 * (s[1:] - s[0])
    b = r[0] ** 2 - r[1:] ** 2 + (s[1:] ** 2).sum(1) - (s[0] ** 2).sum()
    xy = np.linalg.lstsq(A, b, rcond=None)[0]
    return np.array([xy[0], xy[1], 0.0, 0.0, ranges[-1]])


def observe_quadrotor(system: System, y: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """The prior is linear (p, v, a kinematic chain), so the observer is a KF + RTS on that prior, computed
    as the equal batch least-squares solve (`batch.batch_smoother`: filterpy's KF + RTS estimates to rounding,
    in one compiled block-tridiagonal solve instead of a Python loop over the samples).

    y (T, 6) = [p (m), a (m/s²)] -> ζ (T, 9) = [p, v (m/s), a]; the first velocity guess is 0; ``u`` is unused.
    """
    x0 = np.concatenate([y[0, :3], np.zeros(3), y[0, 3:]])
    params = model_params(HybridModel(system, "prior"), x0, check_dt(dt))
    F, H = linearize(params.model, params.dt)
    return batch_smoother(F, H, params.Q, params.R, params.x0, params.P0,
                          check_sequence("y", y, cols=system.n_meas))


def observe_crazyflie(system: System, y: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """The same KF + RTS on the kinematic chain as for the paper's quadrotor: the observer knows nothing
    of the motors, so what the residual learns is not an artefact of the thrust model it corrects."""
    kinematic = make_system("quadrotor", dt=dt, n_samples=len(y))
    return observe_quadrotor(kinematic, y, np.zeros((len(y), 0)), dt)


# An observer: (system, y (T, m), u (T, p), dt s) -> ζ (T, n).
Observer = Callable[[System, np.ndarray, np.ndarray, float], np.ndarray]

OBSERVERS: dict[str, Observer] = {"cartpole": observe_cartpole, "robot": observe_robot, "quadrotor": observe_quadrotor,
             "crazyflie": observe_crazyflie}


def pretraining_observer(system: System, y: ArrayLike, u: ArrayLike, dt: float) -> np.ndarray:
    """ζ_1..ζ_M = g(y_1..y_M, u_1..u_M), eq. (6): y (T, m), u (T, p), dt s -> ζ (T, n).

    Raises
    ------
    KeyError
        If ``system.name`` has no observer (cartpole, robot and quadrotor have one).
    """
    return OBSERVERS[system.name](system, np.asarray(y, float), np.asarray(u, float), dt)


def full_state_observer(system: System, x_measured: ArrayLike, dt: float) -> np.ndarray:
    """The "full state" variant of Algorithm 1: every state is measured (y = x + v, v ~ state noise);
    the observer is then a per-channel constant-acceleration KF + RTS that only removes that noise.
    x_measured (T, n) -> smoothed states (T, n)."""
    pos, _, _ = kinematic_smoother(x_measured, dt, meas_std=system.state_noise_std,
                                   jerk_std=_JERK_STD[system.name])
    return pos


_JERK_STD = {"cartpole": 200.0, "robot": 5.0, "quadrotor": 50.0, "crazyflie": 50.0}
