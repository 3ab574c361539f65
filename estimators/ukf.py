"""UKF (eq. 3) on filterpy's UnscentedKalmanFilter and MerweScaledSigmaPoints.

Three changes to the textbook loop, all for models that are neural networks: every sigma point goes
through the model in one batched call (filterpy calls fx once per point); the covariance is kept
symmetric positive definite so that long runs never die in a Cholesky factorisation; and each covariance
is factorised once, with the factor kept for the next sigma points (filterpy factorises it twice more).
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
from numpy.typing import ArrayLike
from scipy.linalg import lapack

from learnest.models.checks import check_covariance, check_dt, check_inputs, check_sequence, check_vector

from .protocols import StateSpaceModel
from .results import FilterResult


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


class VectorizedMerwePoints(MerweScaledSigmaPoints):
    """filterpy's scaled sigma points (same weights), built from a Cholesky factor without a Python loop."""

    def __init__(self, n: int, alpha: float, beta: float, kappa: float = 0.0) -> None:
        super().__init__(n, alpha, beta, kappa)
        self._scale = np.sqrt(alpha**2 * (n + kappa))  # sqrt(λ + n), λ = α²(n + κ) − n

    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The 2n+1 sigma points of mean x (n,) and covariance P (n, n), shape (2n+1, n)."""
        return self.from_factor(np.atleast_1d(np.asarray(x, dtype=float)), spd_factor(P)[1])

    def from_factor(self, x: np.ndarray, L: np.ndarray) -> np.ndarray:
        """Points x, x ± columns of sqrt(λ + n)·L, where L Lᵀ = P."""
        spread = self._scale * L.T
        return np.concatenate([x[None], x + spread, x - spread])


class BatchedUKF(UnscentedKalmanFilter):
    """filterpy's UKF with fx(sigmas (2n+1, n), dt, u) and hx(sigmas, u) evaluated in one call each.

    The same algorithm as filterpy's predict/update (sigma points re-drawn after the prediction, so the
    update sees Q), written without the duplicate factorisations. Covariances it stores are read-only:
    an in-place edit would silently outdate the kept factor, so assign a new P instead.
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self._factored = (None, None)  # (P, L) for the covariance last factorised

    def _sigmas(self) -> np.ndarray:
        if self._factored[0] is not self.P:  # P was assigned from outside (e.g. P0)
            self._set_covariance(self.P)
        return self.points_fn.from_factor(self.x, self._factored[1])

    def _set_covariance(self, P: np.ndarray) -> None:
        P, L = spd_factor(np.asarray(P, dtype=float))
        P.flags.writeable = False
        self.P, self._factored = P, (P, L)

    def _transform(self, sigmas: np.ndarray, noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The unscented transform: weighted mean and covariance of the points, plus the noise."""
        mean = self.Wm @ sigmas
        spread = sigmas - mean
        return mean, (spread.T * self.Wc) @ spread + noise

    def predict(self, dt: float | None = None, UT: Callable | None = None, fx: Callable | None = None,
                **fx_args: Any) -> None:
        """Propagate the sigma points through ``fx`` in one call; sets x, P and x_prior, P_prior.

        ``UT`` is accepted for filterpy compatibility and ignored.
        """
        dt = self._dt if dt is None else dt
        self.sigmas_f = np.asarray((fx or self.fx)(self._sigmas(), dt, **fx_args))
        self.x, P = self._transform(self.sigmas_f, self.Q)
        self._set_covariance(P)
        self.sigmas_f = self._sigmas()  # re-drawn from the predicted covariance, as filterpy does
        self.x_prior, self.P_prior = self.x.copy(), self.P  # P is read-only: no copy needed

    def update(self, z: np.ndarray, R: np.ndarray | None = None, UT: Callable | None = None,
               hx: Callable | None = None, **hx_args: Any) -> None:
        """Measurement update with z (m,); sets x, P, the innovation y, S, K and x_post, P_post.

        ``UT`` is accepted for filterpy compatibility and ignored.
        """
        R = self.R if R is None else R
        self.sigmas_h = np.asarray((hx or self.hx)(self.sigmas_f, **hx_args))
        zp, self.S = self._transform(self.sigmas_h, R)
        self.SI = np.linalg.inv(self.S)
        Pxz = ((self.sigmas_f - self.x).T * self.Wc) @ (self.sigmas_h - zp)
        self.K = Pxz @ self.SI
        self.y = z - zp
        self.x = self.x + self.K @ self.y
        self._set_covariance(self.P - self.K @ self.S @ self.K.T)
        self.z = np.array(z, copy=True)
        self.x_post, self.P_post = self.x.copy(), self.P
        self._log_likelihood = self._likelihood = self._mahalanobis = None  # filterpy recomputes on read


def _rows(u: np.ndarray, count: int) -> np.ndarray:
    """u repeated for each sigma point (np.broadcast_to costs several times more on these sizes)."""
    out = np.empty((count, len(u)))
    out[:] = u
    return out


def make_ukf(model: StateSpaceModel, dt: float, Q: np.ndarray, R: np.ndarray, x0: np.ndarray, P0: np.ndarray,
             alpha: float = 1e-3, beta: float = 2.0, kappa: float = 0.0) -> BatchedUKF:
    """A `BatchedUKF` for ``model`` with Merwe points (alpha, beta, kappa), x = x0 (n,), P = P0 (n, n).

    Q (n, n) and R (m, m) are used as given (no validation here; `run_ukf` validates).  ``predict`` and
    ``update`` take the input as the keyword ``u``, shape (p,).
    """
    n = model.n
    points = VectorizedMerwePoints(n, alpha=alpha, beta=beta, kappa=kappa)
    ukf = BatchedUKF(dim_x=n, dim_z=R.shape[0], dt=dt, points=points,
                     fx=lambda sigmas, dt, u: model.step(sigmas, _rows(u, len(sigmas)), dt),
                     hx=lambda sigmas, u: model.h(sigmas, _rows(u, len(sigmas))))
    ukf.x, ukf.Q, ukf.R = x0.copy(), Q, R
    ukf._set_covariance(P0)
    return ukf


def run_ukf(model: StateSpaceModel, y: ArrayLike, u: ArrayLike | None = None, *, dt: float, Q: ArrayLike,
            R: ArrayLike, x0: ArrayLike, P0: ArrayLike, alpha: float = 1e-3) -> FilterResult:
    """Filter a whole sequence: update with y[0] at x0, then predict with u[k-1] and update with y[k].

    Parameters
    ----------
    model : StateSpaceModel
        Discrete model (`StateSpaceModel`: ``n``, ``n_inputs``, ``n_meas``, ``step``, ``h``).
    y : array_like, shape (T, m)
        Measurements.
    u : array_like, shape (T, p), optional
        Inputs held over [t_k, t_k+1); None for a model without inputs.
    dt : float
        Sample time, s.
    Q : array_like, shape (n, n)
        Process noise covariance per step (may be singular).
    R : array_like, shape (m, m)
        Measurement noise covariance.
    x0 : array_like, shape (n,)
        Prior mean of the first state.
    P0 : array_like, shape (n, n)
        Its covariance.
    alpha : float
        Merwe sigma-point spread.

    Returns
    -------
    FilterResult
        Means (T, n), covariances (T, n, n) and innovations (T, m); ``t = k * dt``.

    Raises
    ------
    InvalidInput
        On wrong shapes, non-finite values, a bad ``dt``, or a covariance that is not symmetric positive
        definite (Q may be semi-definite).
    """
    dt, n = check_dt(dt), model.n
    y = check_sequence("y", y, cols=model.n_meas)
    u = check_inputs(u, len(y), model.n_inputs)
    Q, R = check_covariance("Q", Q, n, allow_singular=True), check_covariance("R", R, y.shape[1])
    x0, P0 = check_vector("x0", x0, n), check_covariance("P0", P0, n)
    ukf = make_ukf(model, dt, Q, R, x0, P0, alpha=alpha)
    ukf.sigmas_f = ukf._sigmas()
    means, innovations = np.empty((len(y), n)), np.empty(y.shape)
    covariances = np.empty((len(y), n, n))
    for k in range(len(y)):
        if k:
            ukf.predict(u=u[k - 1])
        ukf.update(y[k], u=u[k])
        means[k], innovations[k], covariances[k] = ukf.x, ukf.y, ukf.P
    return FilterResult(dt * np.arange(len(y)), means, covariances, innovations)
