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

from learnest.models.checks import check_inputs, check_sequence

from .params import EstimatorParams


def linearized_covariances(params: EstimatorParams, means: ArrayLike, u: ArrayLike | None = None) -> np.ndarray:
    """P_{k|k} of an EKF linearised along ``means`` (predict with u[k-1], update at y[k]).

    Parameters
    ----------
    params : EstimatorParams
        The model (CasADi-traceable ``step(x, u, dt)`` and ``h(x, u)``), dt (s), the process noise per step
        Q (n, n), the measurement noise R (m, m) and the first state's prior covariance P0 (n, n); x0 is
        not used (the trajectory is given).
    means : array_like, shape (T, n)
        The state trajectory to linearise along (e.g. MHE estimates x̂_{k|k}).
    u : array_like, shape (T, p), optional
        Inputs; None for a model without inputs.

    Returns
    -------
    ndarray, shape (T, n, n)
        Filtered covariances, symmetric.
    """
    model = params.model
    n = model.n
    means = check_sequence("means", means, cols=n)
    T = len(means)
    u = check_inputs(u, T, model.n_inputs)
    params = params.checked()
    dt, Q, R, P = params.dt, params.Q, params.R, params.P0.copy()
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
