"""A covariance kept symmetric positive definite, with its Cholesky factor (shared by the UKF and its points)."""
from __future__ import annotations

import numpy as np
from scipy.linalg import lapack


def spd_factor(P: np.ndarray, floor: float = 1e-15) -> tuple[np.ndarray, np.ndarray]:
    """Symmetrise P and return (P, L) with L Lᵀ = P.

    If Cholesky fails, the spectrum is lifted just above zero; if even that fails (a spread of
    eigenvalues beyond double precision), L is a clipped eigen square root instead of a triangle.
    LAPACK's potrf is called directly: numpy's wrapper costs four times more on a 9x9 matrix.
    """
    P = 0.5 * (P + P.T)
    L, info = lapack.dpotrf(P, lower=1)
    if info == 0:
        return P, L
    eigval, eigvec = np.linalg.eigh(P)
    P = P + np.eye(len(P)) * (floor * max(1.0, eigval[-1]) - eigval[0])
    L, info = lapack.dpotrf(P, lower=1)
    if info == 0:
        return P, L
    return P, eigvec * np.sqrt(np.maximum(eigval, floor * max(1.0, eigval[-1])))
