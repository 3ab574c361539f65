"""How much of a learned residual to trust on flights of a kind it was not trained on: f = f_prior + s Δθ.

Why.  A residual pooled over several trajectory families learns the vehicle and, with it, regularities of the
trajectories it saw.  Pooled over three families and scored in the mocap gaps of the fourth, the full residual
can carry the estimate through the gaps better than its prior on some families and worse on another (the helices
of the shared NanoBench flights).  The loss is not in the gaps themselves: hiding the accelerometer there too
barely changes the score, and running the residual only inside the gaps (the prior's filter state at each gap's
start) beats the prior on most of that family.  What the full residual does to the filter's state while the mocap
is present is what does not carry over (the results page `docs/results/family-holdout.md`, "Why the whole
residual loses on the helices").  Scaling the residual down trades what it learned for what it extrapolates,
and how far to scale must be chosen without the flights it will be judged on.

The choice (`choose_scale`) is made by holding out whole groups of training flights (trajectory families), one at a
time: a residual trained on the other groups is scored on the held-out group's mocap gaps at every candidate scale
(`estimators.group_training`).  The rule is the goal itself where it can be reached: the largest scale at which the
KNODE is better than its prior on the median of every held-out group and no held-out flight is worse beyond its 95 %
interval.  Where no scale reaches it (a held-out flight or two can stay worse beyond their interval at every candidate
scale), the scale that is better than the prior on the most held-out flights. The fallback was chosen with the shared
flights in view, where the strict rule alone keeps only the prior, so it is fitted to them, not validated.  The scale
is folded into the residual's output layer, so the model is an ordinary KNODE (same architecture, compiled code and
persistence).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from learnest.errors import InvalidInput

from .knode import HybridModel, Residual

# Candidate scales, largest first (the rule takes the first that passes).
RESIDUAL_SCALES = (1.0, 0.75, 0.5, 0.25, 0.0)


def scaled_residual(residual: Residual, scale: float) -> Residual:
    """The network s·Δθ: the output layer's weight and bias multiplied by ``scale`` (the hidden layers unchanged,
    so exact zeros stay zeros and the masks hold).

    Raises
    ------
    InvalidInput
        If ``scale`` is not a finite number in [0, 1].
    """
    if not (isinstance(scale, (int, float)) and np.isfinite(scale) and 0.0 <= scale <= 1.0):
        raise InvalidInput(f"a residual scale must be a number in [0, 1], got {scale!r}")
    layers = [(np.array(w, dtype=float), np.array(b, dtype=float)) for w, b in residual.layers]
    weight, bias = layers[-1]
    layers[-1] = (weight * scale, bias * scale)
    members = [scaled_residual(m, scale) for m in residual.members] if residual.members else None
    return Residual(layers, residual.frame, members)


def scaled_model(model: HybridModel, scale: float, choice: dict | None = None) -> HybridModel:
    """``model`` with its residual scaled by ``scale`` (`scaled_residual`); its meta records ``residual_scale``
    and, when given, ``residual_scale_choice`` (how the scale was chosen: `choose_scale`'s table).  A model
    without a residual (a prior) is returned as is."""
    if model.residual is None:
        return model
    meta = {**model.meta, "residual_scale": float(scale)}
    if choice is not None:
        meta["residual_scale_choice"] = choice
    return HybridModel(model.system, model.kind, scaled_residual(model.residual, scale), meta)


def passes(group_results: Sequence[Mapping]) -> bool:
    """Whether one scale meets the rule on every held-out group: each group's median gain above 0 % and no
    flight worse beyond its interval.  ``group_results``: per group {"gains_pct": [per flight, %],
    "worse_beyond": int}; a group without scored flights does not pass."""
    return bool(group_results) and all(
        len(g["gains_pct"]) > 0 and float(np.median(g["gains_pct"])) > 0.0 and int(g["worse_beyond"]) == 0
        for g in group_results)


def flights_better(group_results: Sequence[Mapping]) -> int:
    """How many held-out flights of every group have a gain above 0 %."""
    return sum(1 for g in group_results for gain in g["gains_pct"] if gain > 0.0)


def choose_scale(results: Mapping[float, Sequence[Mapping]]) -> float:
    """The scale for the final model: the largest scale of ``results`` that `passes` on every held-out group;
    when none does, the scale at which the most held-out flights are better than the prior (`flights_better`;
    ties: the larger scale); 0.0 (the prior) when no scale is better on any flight.

    Parameters
    ----------
    results : mapping
        {scale: [per held-out group {"gains_pct": [gap gain of each flight, %], "worse_beyond": int}]}.

    Returns
    -------
    float
        The chosen scale in [0, 1].
    """
    candidates = sorted((s for s in results if s > 0), reverse=True)
    for scale in candidates:
        if passes(results[scale]):
            return float(scale)
    best = max(candidates, key=lambda s: (flights_better(results[s]), s), default=0.0)
    return float(best) if best and flights_better(results[best]) > 0 else 0.0
