"""UKF (eq. 3) on filterpy's UnscentedKalmanFilter and MerweScaledSigmaPoints.

Two changes to the textbook loop, both for models that are neural networks: every sigma point goes
through the model in one batched call (filterpy calls fx once per point), and the covariance is kept
symmetric positive definite so that long runs never die in a Cholesky factorisation.
"""
from __future__ import annotations

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter, unscented_transform

from estimators.checks import check_covariance, check_dt, check_sequence, check_vector


def robust_sqrt(P: np.ndarray) -> np.ndarray:
    """Upper factor U with UᵀU = P; falls back to a clipped eigen-decomposition if Cholesky fails."""
    P = 0.5 * (P + P.T)
    try:
        return np.linalg.cholesky(P).T  # numpy's is several times cheaper than scipy's on tiny matrices
    except np.linalg.LinAlgError:
        eigval, eigvec = np.linalg.eigh(P)
        floor = 1e-12 * max(eigval.max(), 1e-12)
        return (eigvec * np.sqrt(np.maximum(eigval, floor))).T


def _make_spd(P: np.ndarray, floor: float = 1e-15) -> np.ndarray:
    """Symmetrise; if a Cholesky factorisation fails, lift the spectrum just above zero."""
    P = 0.5 * (P + P.T)
    try:
        np.linalg.cholesky(P)  # the cheap test, passes on almost every step
        return P
    except np.linalg.LinAlgError:
        eigval = np.linalg.eigvalsh(P)
        return P + np.eye(len(P)) * (floor * max(1.0, eigval[-1]) - eigval[0])


class VectorizedMerwePoints(MerweScaledSigmaPoints):
    """filterpy's scaled sigma points (same weights, same sqrt), built without a Python loop over n."""

    def sigma_points(self, x, P):
        x = np.atleast_1d(np.asarray(x, dtype=float))
        U = self.sqrt(self.alpha**2 * (self.n + self.kappa) * P)  # (λ + n) P, λ = α²(n + κ) - n
        return np.vstack([x, x + U, x - U])


class BatchedUKF(UnscentedKalmanFilter):
    """filterpy's UKF with fx(sigmas (2n+1, n), dt, u) and hx(sigmas, u) evaluated in one call each."""

    def compute_process_sigmas(self, dt, fx=None, **fx_args):
        sigmas = self.points_fn.sigma_points(self.x, self.P)
        self.sigmas_f = np.asarray((fx or self.fx)(sigmas, dt, **fx_args))

    def predict(self, dt=None, UT=None, fx=None, **fx_args):
        super().predict(dt, UT, fx, **fx_args)
        self.P = self.P_prior = _make_spd(self.P)

    def update(self, z, R=None, UT=None, hx=None, **hx_args):
        R = self.R if R is None else R
        self.sigmas_h = np.asarray((hx or self.hx)(self.sigmas_f, **hx_args))
        zp, self.S = unscented_transform(self.sigmas_h, self.Wm, self.Wc, R)
        self.SI = np.linalg.inv(self.S)
        dx, dz = self.sigmas_f - self.x, self.sigmas_h - zp
        Pxz = (dx * self.Wc[:, None]).T @ dz
        self.K = Pxz @ self.SI
        self.y = z - zp
        self.x = self.x + self.K @ self.y
        self.P = _make_spd(self.P - self.K @ self.S @ self.K.T)
        self.z = np.array(z, copy=True)
        self.x_post, self.P_post = self.x.copy(), self.P.copy()


def make_ukf(model, dt, Q, R, x0, P0, alpha: float = 1e-3, beta: float = 2.0, kappa: float = 0.0):
    n = model.n
    points = VectorizedMerwePoints(n, alpha=alpha, beta=beta, kappa=kappa, sqrt_method=robust_sqrt)
    ukf = BatchedUKF(dim_x=n, dim_z=R.shape[0], dt=dt, points=points, sqrt_fn=robust_sqrt,
                     fx=lambda sigmas, dt, u: model.step(sigmas, np.broadcast_to(u, (len(sigmas), len(u))), dt),
                     hx=lambda sigmas, u: model.h(sigmas, np.broadcast_to(u, (len(sigmas), len(u)))))
    ukf.x, ukf.P, ukf.Q, ukf.R = x0.copy(), P0.copy(), Q, R
    return ukf


def run_ukf(model, y, u, dt, Q, R, x0, P0, alpha: float = 1e-3, return_innovations: bool = False):
    """Filter a whole sequence: update with y[0] at x0, then predict with u[k-1] and update with y[k]."""
    dt, n = check_dt(dt), model.n
    y = check_sequence("y", y, cols=model.system.m)
    u = check_sequence("u", np.asarray(u, dtype=float).reshape(len(y), -1), rows=len(y), cols=model.system.p)
    Q, R = check_covariance("Q", Q, n, allow_singular=True), check_covariance("R", R, y.shape[1])
    x0, P0 = check_vector("x0", x0, n), check_covariance("P0", P0, n)
    ukf = make_ukf(model, dt, Q, R, x0, P0, alpha=alpha)
    ukf.sigmas_f = ukf.points_fn.sigma_points(ukf.x, ukf.P)
    estimates, innovations = np.empty((len(y), n)), np.empty(y.shape)
    for k in range(len(y)):
        if k:
            ukf.predict(u=u[k - 1])
        ukf.update(y[k], u=u[k])
        estimates[k], innovations[k] = ukf.x, ukf.y
    return (estimates, innovations) if return_innovations else estimates
