"""Training envelope: the region of [state, input] space a KNODE's training data covered, and how much of an
evaluation record lies outside it.

A learned residual is only known where it was trained; outside, the network extrapolates and its estimates can be
worse than the prior's (an evaluation lap flown slower than any part of the training lap). The envelope is a box per
network input: the 0.5 and 99.5 percentiles of the observer's estimates and of the inputs over the training record.
Percentiles rather than min/max so that a few observer glitches do not stretch the box; a box rather than a joint
density because it is compact (two numbers per dimension, stored in the model's meta), needs no tuning, and names the
dimension that was left.  Its limit: it cannot see holes inside the box (a hover judged by a model trained on circles
has velocities inside the circles' range) - it catches new speeds, accelerations and inputs, not new combinations of
them.

Leaving the box only matters where the network's answer depends on what it never saw.  With the trained
residual at hand (`envelope_report(..., residual=...)`), each sample outside is clipped back onto the
widened box and the residual evaluated both ways: the record is flagged only when the answer moves by more
than `SENSITIVITY` times the residual's training RMS on more than `THRESHOLD` of its samples.  Why: on real
flights the box alone flags nearly every flight of another trajectory family (each flight flies at its own
battery voltage), though clipping the network's inputs to the box barely changes most of their estimates; the
residual-aware check flags a record only where the answer moves (its flags on the transfer flights are on the
results page `docs/results/transfer.md`).  Table I's check (`workflows.table1`) is the box, the rule its robot
target was measured with.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from .checks import check_sequence

QUANTILES = (0.005, 0.995)
# A tanh network extrapolates smoothly a little past its data: samples within 10 % of the box's width
# beyond its edges count as inside.
MARGIN = 0.10
# Flag a record when more than 5 % of its samples lie outside the widened box in some (flagged) dimension:
# chosen on Table I's seeds to flag the one whose KNODE is worse than its prior and few where the KNODE is fine
# (benchmarks/results/envelope_check_robot.md).
THRESHOLD = 0.05
# A sample extrapolates when clipping it onto the box moves ‖Δθ‖ by more than half the training RMS of ‖Δθ‖.
SENSITIVITY = 0.5


def training_envelope(zeta: ArrayLike, u: ArrayLike, names: list[str], invariant: tuple = (),
                      residual: Callable | None = None) -> dict:
    """The box of the training data, to store with the model.

    Parameters
    ----------
    zeta : array_like, shape (T, n)
        The observer's state estimates the network was trained on.
    u : array_like, shape (T, p)
        The inputs (p may be 0).
    names : list of str
        n + p names, states then inputs.
    invariant : tuple of str
        Dimensions the physics does not depend on (`System.invariant_states`): reported, never flagged.
    residual : callable, optional
        The trained residual Δθ(x (T, n), u (T, p)) -> (T, n); its training RMS sets the scale of
        `envelope_report`'s residual-aware check.

    Returns
    -------
    dict
        ``names``, ``low`` and ``high`` (the QUANTILES, in each dimension's unit), ``quantiles``,
        ``margin``, ``threshold``, ``invariant``, ``samples``; with ``residual`` also ``residual_rms``
        (RMS of ‖Δθ‖ over the training data, in the states' derivative units) and ``sensitivity``.
    """
    data = _features(zeta, u)
    low, high = np.quantile(data, QUANTILES, axis=0)
    envelope = {"names": list(names), "low": low.tolist(), "high": high.tolist(), "quantiles": list(QUANTILES),
                "margin": MARGIN, "threshold": THRESHOLD, "invariant": [n for n in invariant if n in names],
                "samples": len(data)}
    if residual is not None:
        zeta = np.asarray(zeta, dtype=float)
        change = np.linalg.norm(residual(zeta, data[:, zeta.shape[1]:]), axis=1)
        envelope.update(residual_rms=float(np.sqrt(np.mean(change**2))), sensitivity=SENSITIVITY)
    return envelope


def envelope_report(envelope: dict, x: ArrayLike, u: ArrayLike, residual: Callable | None = None) -> dict:
    """How much of a record lies outside a stored training envelope.

    Parameters
    ----------
    envelope : dict
        `training_envelope`'s output.
    x : array_like, shape (T, n)
        State estimates of the record, from the same observer as the training data.
    u : array_like, shape (T, p)
        Its inputs.
    residual : callable, optional
        The model's trained residual Δθ(x, u) (batched, numpy).  Used when the envelope stored its
        ``residual_rms``: the record is then flagged only if the residual's answer depends on where it
        left the box (module docstring).

    Returns
    -------
    dict
        ``fraction_outside`` (share of samples outside in any flagged dimension), ``per_state``
        {name: share outside}, ``states_outside`` (flagged dimensions above the threshold, worst first),
        ``outside_training_envelope`` (bool), ``threshold``, ``invariant`` (reported only); with the
        residual-aware check also ``fraction_extrapolating`` (share of samples whose ‖Δθ‖ moves by more
        than ``sensitivity`` × ``residual_rms`` when clipped onto the box) and ``residual_checked`` True.

    Raises
    ------
    InvalidInput
        If the record's width does not match the envelope's dimensions.
    """
    names = envelope["names"]
    data = check_sequence("x and u", _features(x, u), cols=len(names))
    low, high = np.asarray(envelope["low"]), np.asarray(envelope["high"])
    slack = envelope.get("margin", MARGIN) * (high - low)
    outside = (data < low - slack) | (data > high + slack)                       # (T, n + p)
    threshold = envelope.get("threshold", THRESHOLD)
    invariant = set(envelope.get("invariant", ()))
    flagged = np.array([name not in invariant for name in names])
    share = outside.mean(axis=0)
    worst_first = [names[j] for j in np.argsort(-share) if flagged[j] and share[j] > threshold]
    report = {"fraction_outside": float(outside[:, flagged].any(axis=1).mean()) if flagged.any() else 0.0,
              "per_state": {name: round(float(s), 4) for name, s in zip(names, share)},
              "states_outside": worst_first, "outside_training_envelope": bool(worst_first),
              "threshold": threshold, "invariant": sorted(invariant)}
    if residual is not None and envelope.get("residual_rms"):
        # invariant dimensions are not clipped: leaving their range is not new physics
        clipped = np.where(flagged, np.clip(data, low - slack, high + slack), data)
        n = np.asarray(x).shape[1]
        moved = np.linalg.norm(residual(data[:, :n], data[:, n:]) - residual(clipped[:, :n], clipped[:, n:]), axis=1)
        extrapolating = float(np.mean(moved > envelope.get("sensitivity", SENSITIVITY) * envelope["residual_rms"]))
        report.update(fraction_extrapolating=extrapolating, residual_checked=True,
                      outside_training_envelope=bool(worst_first) and extrapolating > threshold)
    return report


def _features(x: ArrayLike, u: ArrayLike) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return np.concatenate([x, np.asarray(u, dtype=float).reshape(len(x), -1)], axis=1)
