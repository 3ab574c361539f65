"""Linear Kalman filtering on filterpy: the KF estimator for linear priors and the pre-training observers.

The pre-training observer runs offline (Phase 1 of Algorithm 1), so it adds the Rauch-Tung-Striebel
backward pass: a forward KF alone lags by its own time constant and that lag would be learned as a
spurious residual.
"""
from __future__ import annotations

from typing import Literal, overload

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from learnest.models.checks import check_dt, check_sequence

from .params import EstimatorParams
from .protocols import StateSpaceModel
from .results import FilterResult, SmootherResult


def linearize(model: StateSpaceModel, dt: float, x_op: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(F, H): exact Jacobians of the discrete model step (RK4 of f_c, as every estimator here uses)
    and of h at x_op (default 0), with u = 0.  For a linear prior they are the model, not an approximation.

    Returns
    -------
    F : ndarray, shape (n, n)
    H : ndarray, shape (m, n)
    """
    x, u = ca.SX.sym("x", model.n), ca.SX.sym("u", model.n_inputs)
    jacobians = ca.Function("FH", [x, u], [ca.jacobian(model.step(x, u, dt), x), ca.jacobian(model.h(x, u), x)])
    x_op = np.zeros(model.n) if x_op is None else x_op
    F, H = jacobians(x_op, np.zeros(model.n_inputs))
    return np.array(F), np.array(H)


def _filter(F, H, Q, R, x0, P0, y, smooth: bool):
    """x0, P0 describe the state at the first sample: update with y[0], then predict/update."""
    from filterpy.kalman import KalmanFilter  # imports scipy.stats (~2 s): on first use, not on import

    kf = KalmanFilter(dim_x=F.shape[0], dim_z=H.shape[0])
    kf.F, kf.H, kf.Q, kf.R, kf.x, kf.P = F, H, Q, R, x0.copy(), P0.copy()
    means, covs = np.empty((len(y), len(x0))), np.empty((len(y), len(x0), len(x0)))
    innovations = np.empty(y.shape)
    for k, measurement in enumerate(y):
        if k:
            kf.predict()
        kf.update(measurement)
        means[k], covs[k], innovations[k] = kf.x, kf.P, kf.y
    if smooth:
        means, covs, _, _ = kf.rts_smoother(means, covs)
    return means, covs, innovations


@overload
def run_kf(params: EstimatorParams, y: ArrayLike, u: None = None, *, smooth: Literal[False] = False) -> FilterResult:
    ...


@overload
def run_kf(params: EstimatorParams, y: ArrayLike, u: None = None, *, smooth: Literal[True]) -> SmootherResult:
    ...


def run_kf(params: EstimatorParams, y: ArrayLike, u: None = None, *,
           smooth: bool = False) -> FilterResult | SmootherResult:
    """Kalman filter (or RTS smoother) of a whole sequence with the linear model's exact discretisation.

    Parameters
    ----------
    params : EstimatorParams
        The model, linear in x (its Jacobians at 0 are used) and without inputs; dt (s); the process noise
        per step Q (n, n), the measurement noise R (m, m), the first state's guess x0 (n,) and its
        covariance P0 (n, n).
    y : array_like, shape (T, m)
        Measurements.
    u : None
        Unused (the linear models here have no inputs); accepted for the estimators' common signature.
    smooth : bool
        Return the fixed-interval (RTS) smoothed estimates x̂_{k|T} instead of x̂_{k|k}.

    Returns
    -------
    FilterResult or SmootherResult
        A `FilterResult` of x̂_{k|k}, or with ``smooth`` a `SmootherResult` of x̂_{k|T}: ``t = k * dt``,
        means (T, n), covariances (T, n, n), innovations (T, m) of the forward pass.

    Raises
    ------
    InvalidInput
        On wrong shapes, non-finite values, a bad ``dt`` or a covariance that is not positive definite.
    """
    model = params.model
    y = check_sequence("y", y, cols=model.n_meas)
    params = params.checked()
    F, H = linearize(model, params.dt)
    means, covariances, innovations = _filter(F, H, params.Q, params.R, params.x0, params.P0, y, smooth)
    kind = SmootherResult if smooth else FilterResult
    return kind(params.dt * np.arange(len(y)), means, covariances, innovations)


def kinematic_smoother(positions: ArrayLike, dt: float, meas_std: ArrayLike, accel_std: float = 1.0,
                       jerk_std: float = 50.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-channel constant-acceleration KF + RTS: positions (T, k) -> (positions, velocities, accels).

    Used as the pre-training observer when only positions (or angles) of a nonlinear system are
    measured: it knows nothing of the system, only that its trajectories are smooth.

    Parameters
    ----------
    positions : array_like, shape (T, k) or (T,)
        Measured positions (or angles), one channel per column.
    dt : float
        Sample time, s.
    meas_std : float or array_like, shape (k,)
        Measurement noise standard deviation per channel, in the channel's unit.
    accel_std : float
        Sets the initial acceleration variance, 100·accel_std² (not a process noise).
    jerk_std : float
        White-jerk process noise standard deviation, channel unit per s³.

    Returns
    -------
    positions, velocities, accelerations : ndarray, each shape (T, k)
        RTS-smoothed, in the channel's unit, per s and per s².
    """
    dt = check_dt(dt)
    positions = check_sequence("positions", positions)
    F = np.array([[1.0, dt, dt**2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    G = np.array([[dt**3 / 6], [dt**2 / 2], [dt]])
    Q = (G @ G.T) * jerk_std**2
    H = np.array([[1.0, 0.0, 0.0]])
    out = np.empty(positions.shape + (3,))
    std = np.broadcast_to(np.asarray(meas_std, dtype=float), (positions.shape[1],))
    for j in range(positions.shape[1]):
        x0 = np.array([positions[0, j], 0.0, 0.0])
        P0 = np.diag([std[j] ** 2, 10.0, accel_std**2 * 100])
        means = _filter(F, H, Q, np.array([[std[j] ** 2]]), x0, P0, positions[:, j:j + 1], smooth=True)[0]
        out[:, j] = means
    return out[..., 0], out[..., 1], out[..., 2]
