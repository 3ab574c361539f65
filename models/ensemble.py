"""An ensemble of residuals: their mean is the model's residual, their disagreement its epistemic uncertainty.

Members are trained alike on the same flights from different initial weights and mini-batch orders
(`estimators.algorithm1.Algorithm1.fit_flights` with ``TrainingConfig.ensemble``).  Where the training data pinned
the residual down they agree; where a flight leaves it (another speed, another height, another battery) each
extrapolates its own way.  Their mean is one ordinary network: the members' hidden layers side by side and their
output layers averaged, so the estimators, the compiled code and the file format see a plain `Residual`.
Their spread enters the filters as process noise (`spread_variance`), so the learned part counts less on a
flight where the members disagree.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from learnest.errors import InvalidInput

from .knode import Residual

MIN_MEMBERS = 2


def mean_residual(members: Sequence[Residual]) -> Residual:
    """The network whose output is the mean of ``members``' (one hidden layer each, one frame), carrying them.

    Raises
    ------
    InvalidInput
        Fewer than `MIN_MEMBERS` members, members of different frames or not of one hidden layer.
    """
    members = list(members)
    if len(members) < MIN_MEMBERS:
        raise InvalidInput(f"an ensemble needs at least {MIN_MEMBERS} residuals, got {len(members)}")
    if len({m.frame for m in members}) != 1 or any(len(m.layers) != 2 for m in members):
        raise InvalidInput("ensemble members must share a frame and have one hidden layer each")
    k = len(members)
    hidden_w = np.vstack([np.asarray(m.layers[0][0], dtype=float) for m in members])
    hidden_b = np.concatenate([np.asarray(m.layers[0][1], dtype=float) for m in members])
    out_w = np.hstack([np.asarray(m.layers[1][0], dtype=float) for m in members]) / k
    out_b = np.mean([np.asarray(m.layers[1][1], dtype=float) for m in members], axis=0)
    return Residual([(hidden_w, hidden_b), (out_w, out_b)], members[0].frame, members)


def spread_variance(residual: Residual, x: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
    """Process noise per step (n,) that the members' disagreement stands for along a flight.

    Parameters
    ----------
    residual : Residual
        With ``members`` (`mean_residual`).
    x : ndarray, shape (T, n)
        States along the flight (in the states' units).
    u : ndarray, shape (T, p)
        Inputs.
    dt : float
        Step, s.

    Returns
    -------
    ndarray, shape (n,)
        dt² times the mean over the flight of the members' variance of each ẋ row: one RK4 step moves the state
        by about dt·Δθ, so a field uncertain by σ adds (dt σ)² to the step's covariance.  Zeros without members.
    """
    if not residual.members:
        return np.zeros(np.shape(x)[-1])
    outputs = np.stack([member(np.asarray(x, dtype=float), np.asarray(u, dtype=float)) for member in residual.members])
    return dt * dt * np.mean(np.var(outputs, axis=0), axis=0)
