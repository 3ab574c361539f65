"""Covariances along a given state trajectory, for estimators that return only means (the MHE).

The MHE's estimate x̂_{k|k} is the last node of a least-squares problem; its covariance is the inverse
curvature of that problem.  With the EKF arrival cost used here, that curvature is what an extended
Kalman filter linearised along the estimates accumulates, and for a linear-Gaussian model it is exact:
MHE with the Kalman arrival cost IS the Kalman filter, means and covariances (tested against `run_kf`).
"""
from __future__ import annotations

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from learnest.models.checks import check_covariance, check_dt, check_inputs, check_sequence

from .protocols import StateSpaceModel


def linearized_covariances(model: StateSpaceModel, means: ArrayLike, u: ArrayLike | None = None, *, dt: float,
                           Q: ArrayLike, R: ArrayLike, P0: ArrayLike) -> np.ndarray:
    """P_{k|k} of an EKF linearised along ``means`` (predict with u[k-1], update at y[k]).

    Parameters
    ----------
    model : HybridModel
        Discrete model with CasADi-traceable ``step(x, u, dt)`` and ``h(x, u)``.
    means : array_like, shape (T, n)
        The state trajectory to linearise along (e.g. MHE estimates x̂_{k|k}).
    u : array_like, shape (T, p), optional
        Inputs; None for a model without inputs.
    dt : float
        Sample time, s.
    Q, R, P0 : array_like, shapes (n, n), (m, m), (n, n)
        Process noise per step, measurement noise and the first state's prior covariance.

    Returns
    -------
    ndarray, shape (T, n, n)
        Filtered covariances, symmetric.
    """
    dt, n = check_dt(dt), model.n
    means = check_sequence("means", means, cols=n)
    T = len(means)
    u = check_inputs(u, T, model.n_inputs)
    Q = check_covariance("Q", Q, n, allow_singular=True)
    R = check_covariance("R", R, model.n_meas)
    P = check_covariance("P0", P0, n).copy()
    x, v = ca.SX.sym("x", n), ca.SX.sym("u", model.n_inputs)
    jac_f = ca.Function("F", [x, v], [ca.jacobian(model.step(x, v, dt), x)])
    jac_h = ca.Function("H", [x, v], [ca.jacobian(model.h(x, v), x)])
    covariances = np.empty((T, n, n))
    for k in range(T):
        if k:
            F = np.asarray(jac_f(means[k - 1], u[k - 1]))
            P = F @ P @ F.T + Q
        H = np.asarray(jac_h(means[k], u[k]))
        gain = np.linalg.solve(H @ P @ H.T + R, H @ P).T
        identity_minus = np.eye(n) - gain @ H
        P = identity_minus @ P @ identity_minus.T + gain @ R @ gain.T  # Joseph form: stays SPD
        covariances[k] = P = 0.5 * (P + P.T)
    return covariances
