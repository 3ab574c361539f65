"""What one estimator run is given besides the data: one frozen bundle (dynamax's ``params`` habit).

A filter's estimate depends on its model, its grid and its noise together, so they travel as one object:
two runs given the same `EstimatorParams` cannot disagree about any of them, and a call site cannot pair
one model with another model's noise.  `estimators.prepared.prepare` builds the bundles of a flight (the
model's and its prior's, `PreparedFlight.params`); the UKF, the MHE, the smoothers and the KF take one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from learnest.models.checks import check_covariance, check_dt, check_vector

from .protocols import StateSpaceModel

if TYPE_CHECKING:
    from learnest.models.noise import NoiseModel


@dataclass(frozen=True, eq=False)
class EstimatorParams:
    """The model, grid, noise and first state of one estimator run.

    Nothing is checked on construction: a factory (`estimators.ukf.make_ukf`) may be handed deliberately
    broken noise, and each estimator asks for what it needs (`checked`).

    Attributes
    ----------
    model : StateSpaceModel
        Discrete model x_{k+1} = step(x_k, u_k, dt), y_k = h(x_k, u_k): n states, p inputs, m measurements.
    dt : float
        Sample time, s.
    Q : ndarray, shape (n, n)
        Process noise covariance per step, in the states' squared units.
    R : ndarray, shape (m, m)
        Measurement noise covariance, in the measurements' squared units.
    P0 : ndarray, shape (n, n)
        Covariance of the first state's guess.
    x0 : ndarray, shape (n,)
        The first state's guess (the MHE's first arrival state x̄).
    """

    model: StateSpaceModel
    dt: float
    Q: np.ndarray
    R: np.ndarray
    P0: np.ndarray
    x0: np.ndarray

    @classmethod
    def from_noise(cls, model: StateSpaceModel, dt: float, noise: NoiseModel, x0: np.ndarray) -> EstimatorParams:
        """The bundle of ``model`` on a grid of ``dt`` s run with ``noise`` (its Q, R, P0), from ``x0`` (n,)."""
        return cls(model, dt, noise.Q, noise.R, noise.P0, x0)

    def checked(self, singular_q: bool = True) -> EstimatorParams:
        """This bundle as float arrays, checked against its model's sizes.

        Parameters
        ----------
        singular_q : bool
            Accept a positive semi-definite Q (the UKF and the smoothers do); False asks for a definite one
            (the MHE inverts it).

        Raises
        ------
        InvalidInput
            On a bad ``dt``; a Q, R or P0 of the wrong size, not finite, not symmetric or not positive
            definite (Q semi-definite when ``singular_q``); an x0 of the wrong size or not finite.
        """
        n = self.model.n
        dt = check_dt(self.dt)
        Q = check_covariance("Q", self.Q, n, allow_singular=singular_q)
        R = check_covariance("R", self.R, self.model.n_meas)
        x0, P0 = check_vector("x0", self.x0, n), check_covariance("P0", self.P0, n)
        return EstimatorParams(self.model, dt, Q, R, P0, x0)
