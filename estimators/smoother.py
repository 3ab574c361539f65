"""Unscented Rauch-Tung-Striebel smoother (Särkkä 2008): x̂_{k|T} from a UKF's x̂_{k|k}, P_{k|k}.

Used by the pre-training observers, which run offline: a forward filter's estimates of the unmeasured
states lag and carry the filter's transients, and the network learns those artefacts as dynamics; the
backward pass uses every measurement of the record for every estimate.  filterpy's
``UnscentedKalmanFilter.rts_smoother`` calls ``fx`` once per sigma point and without inputs, so the
backward pass is written here with the batched model call the UKF uses.
"""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from learnest.models.checks import check_covariance, check_dt, check_inputs, check_sequence

from .covariance_factor import repairs_warned, spd_factor
from .params import EstimatorParams
from .results import FilterResult, SmootherResult
from .ukf import run_ukf


def _merwe_weights(n: int, alpha: float, beta: float = 2.0, kappa: float = 0.0):
    """Mean and covariance weights of the 2n+1 scaled sigma points, and the spread sqrt(n + λ)."""
    lam = alpha**2 * (n + kappa) - n
    wm = np.full(2 * n + 1, 0.5 / (n + lam))
    wc = wm.copy()
    wm[0] = lam / (n + lam)
    wc[0] = lam / (n + lam) + (1 - alpha**2 + beta)
    return wm, wc, np.sqrt(n + lam)


def urts_backward(params: EstimatorParams, filtered: FilterResult, u: ArrayLike | None = None, *,
                  alpha: float = 1.0) -> SmootherResult:
    """Backward pass of the unscented RTS smoother over a forward UKF's output.

    Parameters
    ----------
    params : EstimatorParams
        What the forward filter ran with; the model (``step`` batched over rows), dt (s) and the process
        noise per step Q (n, n) are used.
    filtered : FilterResult
        Forward estimates: means (T, n) x̂_{k|k}, covariances (T, n, n) P_{k|k}.
    u : array_like, shape (T, p), optional
        Inputs held over [t_k, t_k+1); None for a model without inputs.
    alpha : float
        Sigma-point spread of the backward pass.  1 (points at ±sqrt(n)·σ) rather than the forward
        filter's 1e-3: the cross-covariance is then a secant over the state's spread, and the central
        weight stays positive, which keeps the smoothed covariance well conditioned.

    Returns
    -------
    SmootherResult
        Smoothed means (T, n) x̂_{k|T} and covariances (T, n, n) P_{k|T}; ``t``, the innovations and the
        log-likelihoods are the forward filter's.
    """
    model = params.model
    dt = check_dt(params.dt)
    means, covs = filtered.means, filtered.covariances
    T, n = means.shape
    u = check_inputs(u, T, model.n_inputs)
    Q = check_covariance("Q", params.Q, n, allow_singular=True)
    wm, wc, scale = _merwe_weights(n, alpha)
    out_m, out_P = means.copy(), covs.copy()
    with repairs_warned("URTS smoother"):   # a repaired covariance warns once per pass
        for k in range(T - 2, -1, -1):
            spread = scale * spd_factor(covs[k])[1].T                     # rows: scaled square-root columns
            sigmas = np.concatenate([means[k][None], means[k] + spread, means[k] - spread])
            ahead = np.asarray(model.step(sigmas, np.broadcast_to(u[k], (len(sigmas), u.shape[1])).copy(), dt))
            m_pred = wm @ ahead
            d_ahead, d_now = ahead - m_pred, sigmas - means[k]
            P_pred = (d_ahead.T * wc) @ d_ahead + Q
            cross = (d_now.T * wc) @ d_ahead                               # C_{k,k+1}
            gain = np.linalg.solve(P_pred.T, cross.T).T                    # G = C P_pred⁻¹ (P_pred symmetric)
            out_m[k] = means[k] + gain @ (out_m[k + 1] - m_pred)
            out_P[k] = spd_factor(covs[k] + gain @ (out_P[k + 1] - P_pred) @ gain.T)[0]
    return SmootherResult(filtered.t, out_m, out_P, filtered.innovations, filtered.log_likelihoods)


def run_urts(params: EstimatorParams, y: ArrayLike, u: ArrayLike | None = None) -> SmootherResult:
    """Fixed-interval smoothing of a whole sequence: `run_ukf` forward, then `urts_backward`.

    Parameters
    ----------
    params : EstimatorParams
        The model (``n``, ``n_inputs``, ``n_meas``, batched ``step`` and ``h``), dt (s), the process noise
        per step Q (n, n), the measurement noise R (m, m), the first state's guess x0 (n,) and its
        covariance P0 (n, n), as for `run_ukf`.
    y : array_like, shape (T, m)
        Measurements.
    u : array_like, shape (T, p), optional
        Inputs held over [t_k, t_k+1); None for a model without inputs.

    Returns
    -------
    SmootherResult
        Smoothed means (T, n) and covariances (T, n, n); innovations (T, m) of the forward pass.

    Raises
    ------
    InvalidInput
        On wrong shapes, non-finite values, a bad ``dt`` or a covariance that is not positive definite.
    """
    y = check_sequence("y", y, cols=params.model.n_meas)
    params = params.checked()
    filtered = run_ukf(params, y, u)
    return urts_backward(params, filtered, u)
