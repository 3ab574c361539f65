"""filterpy's UKF with batched sigma points: the classes `estimators.ukf` builds its filter from.

Kept apart from `estimators.ukf` because importing filterpy imports scipy.stats (about 2 s): code that
only needs the UKF's functions, results or checks does not pay for it until a filter is made.
"""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from .covariance_factor import spd_factor


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
