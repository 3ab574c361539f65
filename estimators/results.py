"""What the estimators return: named tuples with named fields (dynamax's habit), never bare tuples."""
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
