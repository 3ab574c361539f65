"""What the estimators return: named tuples with named fields (dynamax's habit), never bare tuples or arrays."""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


class FilterResult(NamedTuple):
    """A filtered sequence (dynamax/filterpy habit: means AND covariances).

    Attributes
    ----------
    t : ndarray, shape (T,)
        Time of each estimate, s.
    means : ndarray, shape (T, n)
        Filtered state estimates x̂_{k|k}, in the model's state units.
    covariances : ndarray, shape (T, n, n)
        Their covariances P_{k|k}.
    innovations : ndarray, shape (T, m)
        Measurement innovations y_k - ŷ_{k|k-1} (ŷ the predicted measurement; for the UKF the unscented
        mean of h over the sigma points), in the measurement units.
    log_likelihoods : ndarray, shape (T,), or None
        log N(innovation_k; 0, S_k) per step (nats), S_k the predicted measurement covariance: the filter's
        innovation likelihood, which noise identification maximises (`estimators.noise_identification`).
        NaN at a step whose S could not be factored; None from an estimator that does not compute it.
    """

    t: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    innovations: np.ndarray
    log_likelihoods: np.ndarray | None = None


class SmootherResult(NamedTuple):
    """A smoothed sequence: every estimate uses the whole record (the RTS smoothers, `run_kf(smooth=True)`).

    Attributes
    ----------
    t : ndarray, shape (T,)
        Time of each estimate, s.
    means : ndarray, shape (T, n)
        Smoothed state estimates x̂_{k|T}, in the model's state units.
    covariances : ndarray, shape (T, n, n)
        Their covariances P_{k|T}.
    innovations : ndarray, shape (T, m)
        The forward filter's innovations y_k - ŷ_{k|k-1}, in the measurement units: how well the model
        explains the measurements (a smoother has no innovations of its own).
    log_likelihoods : ndarray, shape (T,), or None
        The forward filter's per-step innovation log-likelihoods (nats), None where it does not compute them.
    """

    t: np.ndarray
    means: np.ndarray
    covariances: np.ndarray
    innovations: np.ndarray
    log_likelihoods: np.ndarray | None = None


class MHEResult(NamedTuple):
    """A moving-horizon estimate of a whole sequence (`estimators.mhe.MHE.run`, `learnest.mhe`).

    Attributes
    ----------
    t : ndarray, shape (T,)
        Time of each estimate, s from the record's start.
    means : ndarray, shape (T, n)
        x̂_{k|k}, the last node of each window.
    covariances : ndarray, shape (T, n, n), or None
        Their covariances, from the EKF recursion linearised along the estimates (exact for a linear
        model, where MHE with the Kalman arrival cost equals the Kalman filter); None when the run was not
        asked for them (they cost several times the Gauss–Newton run itself).
    solver_failures : int
        Windows whose NLP solver reported failure (`learnest.mhe` also warns of them: `NumericalWarning`).
    """

    t: np.ndarray
    means: np.ndarray
    covariances: np.ndarray | None
    solver_failures: int
