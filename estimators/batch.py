"""Fixed-interval smoothing of a linear-Gaussian model as one block-tridiagonal solve.

The RTS smoother's means are the minimiser of the batch least-squares problem
    ‖x_0 - x̄_0‖²_{P0⁻¹} + Σ_k ‖y_k - H x_k‖²_{R⁻¹} + Σ_k ‖x_{k+1} - F x_k‖²_{Q⁻¹},
whose normal equations are block tridiagonal.  The MHE's block Cholesky (`mhe_gn.BlockTridiagonal`,
compiled C) solves them for a whole flight in one pass, where filterpy's predict/update/RTS loop pays Python's
overhead at every step: this is what the quadrotor's pre-training observer runs.
It needs Q invertible (the quadrotor's is diagonal); the kinematic smoother's rank-one Q is not.
"""
from __future__ import annotations

import numpy as np

from .native.block_tridiagonal import BlockTridiagonal


def batch_smoother(F, H, Q, R, x0, P0, y) -> np.ndarray:
    """Smoothed means (T, n) of x_{k+1} = F x_k + w, y_k = H x_k + v, x_0 ~ N(x0, P0).

    Parameters
    ----------
    F : ndarray (n, n)
        State transition.
    H : ndarray (m, n)
        Measurement matrix.
    Q, R, P0 : ndarray (n, n), (m, m), (n, n)
        Process noise, measurement noise (both positive definite) and prior covariances.
    x0 : ndarray (n,)
        Prior mean of the first state.
    y : ndarray (T, m)
        Measurements, one per state.
    """
    y = np.asarray(y, dtype=float)
    T, (m, n) = len(y), H.shape
    Qi, Ri, P0i = np.linalg.inv(Q), np.linalg.inv(R), np.linalg.inv(P0)
    solver = BlockTridiagonal(n, m, T, 0.5 * (Qi + Qi.T), 0.5 * (Ri + Ri.T))
    Fs = np.ascontiguousarray(np.broadcast_to(F, (T, n, n)), dtype=float)
    Hs = np.ascontiguousarray(np.broadcast_to(H, (T, m, n)), dtype=float)
    factor = solver.factor(T, Fs, Hs, 0.5 * (P0i + P0i.T))
    rhs = y @ (Ri @ H)            # rows Hᵀ R⁻¹ y_k
    rhs[0] += P0i @ x0
    return solver.solve(factor, rhs)
