"""Algorithm 1 with a choice of pre-training observer, and the observer -> train -> observer iteration.

The network learns whatever the observer's estimates of the unmeasured states contain, artefacts
included.  Two ways to make those estimates better (measured in
benchmarks/results/table1_observer_study.md):

* ``observer="smoother"``: a fixed-interval smoother instead of a filter where the paper's observer is a
  filter (the robot's precursory UKF gets its unscented RTS pass; the cartpole's observer is an unscented
  RTS smoother with the prior instead of the model-free kinematic KF + RTS);
* ``rounds > 0``: after training, smooth the record again with the learned model (`model_smoother`) and
  train on those estimates; stop when the learned model explains the measurements no better than the
  previous round's (mean squared forward innovation, whitened by R: it needs no ground truth);
* ``observer="joint"``: the filter's estimates only start a joint fit of the record's states and Δθ
  (`estimators.joint_training.train_jointly`, the full-record MHE with the network free), so the states the
  network learns from must also follow the learned model.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from learnest.errors import InvalidInput
from learnest.models.presets import TrainingConfig
from learnest.models.systems import System
from learnest.models.training import TrainingResult, train_knode

from .observers import model_smoother, observe_robot, pretraining_observer

OBSERVER_KINDS = ("filter", "smoother", "joint")


def first_observation(system: System, y: np.ndarray, u: np.ndarray, dt: float, observer: str) -> np.ndarray:
    """ζ (T, n) of the chosen observer before any learning: ``"filter"`` is `pretraining_observer` (the
    paper's), ``"smoother"`` the smoothing variant described in the module docstring; ``"joint"`` starts from
    the filter's.

    Raises
    ------
    InvalidInput
        If ``observer`` is not one of ``OBSERVER_KINDS``.
    """
    if observer not in OBSERVER_KINDS:
        raise InvalidInput(f"observer must be one of {', '.join(OBSERVER_KINDS)}, got {observer!r}")
    if observer in ("filter", "joint") or system.name not in ("cartpole", "robot"):
        return pretraining_observer(system, y, u, dt)   # quadrotor/crazyflie: already KF + RTS
    if system.name == "robot":
        return observe_robot(system, y, u, dt, smooth=True)
    from learnest.models.knode import HybridModel

    kinematic = pretraining_observer(system, y, u, dt)  # its first state starts the model's smoother
    return model_smoother(HybridModel(system, "prior"), y, u, dt, kinematic[0]).means


def _misfit(innovations: np.ndarray, R: np.ndarray) -> float:
    """Mean squared forward innovation per measurement, in units of its noise variance (1 = noise)."""
    return float(np.mean(innovations**2 / np.diag(R)))


def train_with_observer(system: System, y: ArrayLike, u: ArrayLike, dt: float, config: TrainingConfig,
                        observer: str = "filter", rounds: int = 0,
                        progress: Callable[[int, float], None] | None = None) -> TrainingResult:
    """Observer, training, then up to ``rounds`` rounds of smoothing with the learned model and retraining.

    Parameters
    ----------
    system : System
        The prior (and the estimators' Q, R, P0 used by the smoother).
    y : array_like, shape (T, m)
        Measurements of the training record.
    u : array_like, shape (T, p)
        Inputs.
    dt : float
        Sample period, s.
    config : TrainingConfig
        Training settings, the same in every round (each round trains from the config's seed).
    observer : {"filter", "smoother", "joint"}
        First observer (`first_observation`); "joint" starts `estimators.joint_training.train_jointly` from the
        filter's estimates instead of training on them.
    rounds : int
        Extra observer -> train rounds at most; 0 is Algorithm 1 as printed (ignored with "joint").
    progress : callable, optional
        ``progress(epoch, loss)`` of every round's training.

    Returns
    -------
    TrainingResult
        The kept round's result; its model's meta ``"observer"`` holds ``kind``, ``rounds`` (asked),
        ``kept_round`` and ``misfit`` per round run (mean whitened squared innovation of the learned
        model's smoother on the training record; only computed when ``rounds > 0``).

    Raises
    ------
    InvalidInput
        On an unknown observer or ``rounds < 0`` (and whatever `train_knode` rejects).
    """
    if rounds < 0:
        raise InvalidInput(f"rounds must be at least 0, got {rounds}")
    y, u = np.asarray(y, dtype=float), np.asarray(u, dtype=float).reshape(len(y), -1)
    zeta = first_observation(system, y, u, dt, observer)
    if observer == "joint":   # the observer's states start the joint fit; no rounds after it
        from learnest.estimators.joint_training import train_jointly

        result = train_jointly(system, y, u, dt, zeta, config, progress=progress)
        result.model.meta["observer"] = {"kind": observer, "rounds": rounds, "kept_round": 0, "misfit": []}
        return result
    results = [train_knode(system, zeta, u, dt, config, progress=progress)]
    misfits: list[float] = []
    for round_ in range(rounds + 1 if rounds else 0):
        # score the model of round `round_` by how well its smoother explains y; its estimates train the next
        smoothed = model_smoother(results[round_].model, y, u, dt, zeta[0])
        misfits.append(_misfit(smoothed.innovations, system.R))
        if (round_ and misfits[-1] >= misfits[-2]) or round_ == rounds:
            break                                       # no better than the round before it, or the last
        results.append(train_knode(system, smoothed.means, u, dt, config, progress=progress))
    kept = int(np.argmin(misfits)) if misfits else 0
    result = results[kept]
    result.model.meta["observer"] = {"kind": observer, "rounds": rounds, "kept_round": kept, "misfit": misfits}
    return result
