"""Settings that are facts of the method or the product, each written once.

The paper's network and training settings per task (Sec. V), the Crazyflie experiment's (Sec. V-C), the
MHE horizon, the Savitzky–Golay reference window, the estimator names and the alias the scheduler uses.
Everything else imports them from here; nothing imports torch here, so reading a default stays cheap.
"""
from __future__ import annotations

import numbers
from dataclasses import dataclass

from learnest.errors import InvalidInput

MHE_HORIZON = 20                 # MHE window N (paper Sec. V)
SG_WINDOW = 150                  # Savitzky–Golay reference window, samples (paper Sec. VI)
SG_WINDOW_RANGE = (3, 2001)      # windows a user may choose, samples (order 2 needs 3; 2001 = 20 s at 100 Hz)
METHODS = ("ukf", "mhe", "knode-ukf", "knode-mhe")   # the four estimators of the Crazyflie experiment
PRODUCTION_ALIAS = "production"  # the alias scheduled evaluations use
# the vehicle's own estimate, scored beside the estimators where the log carries it (estimators.yardsticks)
ONBOARD = "onboard"
EVALUATION_METHODS = (*METHODS, ONBOARD)   # what an evaluation scores by default
# the mocap-gap yardstick (estimators.yardsticks): the mocap position is hidden for GAP_S s every GAP_EVERY_S s,
# none before GAP_START_S s of the kept flight (the estimators' start-up)
GAP_S, GAP_EVERY_S, GAP_START_S = 0.5, 2.5, 5.0
# the bounds of a gap plan (`gap_plan_problem`): a gap, and the mocap between two gaps, last at least one sample of
# the flight's grid and never less than MIN_GAP_S (1 ms: one sample at 1 kHz, the Crazyflie's fastest loop, finer
# than any grid a flight is read on); at most MAX_GAPS gaps per flight (a 30-min flight at the defaults has 720)
MIN_GAP_S = 0.001
MAX_GAPS = 10_000
# the MHE's options (estimators.mhe.MHE): the valid choices, named in every error about them
MHE_HORIZON_RANGE = (1, 500)     # horizons a user may choose, samples (the API's bounds; the library needs >= 1)
MHE_SOLVERS = ("gauss-newton", "ipopt")
MHE_ARRIVALS = ("ekf", "fixed")
# Where the arrival cost's mean comes from when the window slides (`estimators.mhe.MHE`): "filtering", the
# prediction from the estimate at the window's first step, the mean the EKF-propagated covariance describes (a
# linear MHE then equals the Kalman filter); "smoothing", the last window's estimate of the new first step, the
# paper's eq. (2) (x̄_{k-N|k} <- x̂*_{k-N|k-1}, after Alessandri et al. 2008), which counts the window's
# measurements again at each shift.
MHE_ARRIVAL_UPDATES = ("filtering", "smoothing")
MHE_HESSIANS = ("cost", "exact")


def _whole(value) -> bool:
    """An integer (numpy's too) or a float with no fractional part; not a bool."""
    return not isinstance(value, bool) and (isinstance(value, numbers.Integral)
                                            or (isinstance(value, float) and value.is_integer()))


def _choice(name: str, value, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise InvalidInput(f"{name} must be one of {', '.join(choices)}, got {value!r}")


def check_mhe_options(horizon, solver: str = "gauss-newton", arrival: str = "ekf", hessian: str = "cost",
                      max_iter=None, arrival_update: str = "filtering") -> None:
    """The MHE's options, checked once where they enter (`estimators.mhe.MHE`, the API's request models).

    Raises
    ------
    InvalidInput
        Naming the option, the valid choices (`MHE_SOLVERS`, `MHE_ARRIVALS`, `MHE_ARRIVAL_UPDATES`,
        `MHE_HESSIANS`) or range (a horizon N >= 1 samples; the API allows up to ``MHE_HORIZON_RANGE[1]``), and the
        value given.
    """
    if not _whole(horizon) or horizon < MHE_HORIZON_RANGE[0]:
        raise InvalidInput(f"horizon must be a whole number of samples, at least {MHE_HORIZON_RANGE[0]} (the service "
                           f"allows {MHE_HORIZON_RANGE[0]}-{MHE_HORIZON_RANGE[1]}), got {horizon!r}")
    _choice("solver", solver, MHE_SOLVERS)
    _choice("arrival", arrival, MHE_ARRIVALS)
    _choice("arrival_update", arrival_update, MHE_ARRIVAL_UPDATES)
    _choice("hessian", hessian, MHE_HESSIANS)
    if max_iter is not None and (not _whole(max_iter) or max_iter < 1):
        raise InvalidInput(f"max_iter must be a positive integer or None, got {max_iter!r}")


def gap_plan_problem(gap_s, gap_every_s, start_s=GAP_START_S, *, dt: float | None = None,
                     n_samples: int | None = None) -> tuple[str, str] | None:
    """What is wrong with a mocap-gap plan, before any gap is laid: (the field at fault, why), or None.

    Parameters
    ----------
    gap_s, gap_every_s, start_s : float
        The gaps' length (0: no gaps), the time from one gap's start to the next's and the first gap's
        earliest start, s (`estimators.yardsticks.GapPlan`).
    dt : float, optional
        The flight's sample period, s: a gap and the mocap between two gaps must last one sample at least.
    n_samples : int, optional
        The flight's samples (with ``dt``): it may hold at most `MAX_GAPS` gaps.

    Returns
    -------
    (field, why) or None
        ``field`` is "gap_s" or "gap_every_s" (the request's names; the CLI's --gap-s, --gap-every-s); ``why``
        says what the value must be and what it was.
    """
    for name, value in (("gap_s", gap_s), ("gap_every_s", gap_every_s), ("start_s", start_s)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not (0 <= float(value) < float("inf")):
            return name, f"must be a non-negative number of seconds, got {value!r}"
    if gap_s == 0:
        return None   # the gap yardstick is off: no window is ever laid
    least = max(MIN_GAP_S, dt or 0.0) * (1 - 1e-9)   # one sample: a grid step computed as 1/rate may round
    sample = f"one sample ({dt:.3g} s)" if dt and dt > MIN_GAP_S else f"{MIN_GAP_S:g} s"
    if gap_s < least:
        return "gap_s", f"must be 0 (no gaps) or at least {sample}, got {gap_s!r}"
    if not gap_every_s - gap_s >= least:
        return "gap_every_s", (f"must be longer than the gap (gap_s {gap_s:g} s) by at least {sample}: the "
                               f"estimators need mocap between gaps; got {gap_every_s!r}")
    if dt is not None and n_samples is not None:
        room = n_samples * dt - start_s - gap_s
        count = 0 if room < 0 else int(room // gap_every_s) + 1
        if count > MAX_GAPS:
            return "gap_every_s", (f"{gap_every_s:g} s gives {count} gaps on this {n_samples * dt:.0f}-s flight: at "
                                   f"most {MAX_GAPS}; space them wider")
    return None


def parse_methods(text: str, allowed: tuple[str, ...] = METHODS) -> list[str]:
    """Comma-separated method names (case and spaces ignored) -> list of names from ``allowed`` (the
    estimators, ``METHODS``; an evaluation also takes ``onboard``: ``EVALUATION_METHODS``).

    Raises
    ------
    InvalidInput
        If a name is unknown or none is given.
    """
    methods = [m.strip().lower() for m in text.split(",") if m.strip()]
    unknown = sorted(set(methods) - set(allowed))
    if unknown or not methods:
        raise InvalidInput(f"unknown method(s) {unknown or text!r}; choose from {', '.join(allowed)}")
    return methods


@dataclass
class TrainingConfig:
    """Hyperparameters of Algorithm 1's training (`models.training.train_knode`).

    Attributes
    ----------
    hidden : int
        Neurons of the residual's one hidden tanh layer.
    epochs : int
        Adam epochs.
    lr : float
        Adam learning rate.
    batch_size : int
        One-step pairs per Adam step; 0 = full batch (one step per epoch).
    seed : int
        Seed of the initial weights and of the mini-batch order.
    validation_fraction : float
        Share of the one-step pairs held out (in time blocks); the weights of the epoch with the lowest
        held-out loss are kept.  Ignored (nothing held out) for fewer than 10 pairs.
    validation_layout : {"spread", "tail"}
        Two blocks at about 30-40 % and 80-90 % of the record, or the last part.
    residual_frame : {"", "state", "body"}
        What the residual reads and where it acts (`models.residual_frame`); "" the system's own
        (`System.residual_frame`).
    ensemble : int
        Residuals trained alike from different seeds on several flights (`models.ensemble`): their mean is the
        model's residual and their spread its process noise; 1 trains one.  One flight always trains one.
    """

    hidden: int = 8            # neurons between the two layers (paper: 8 cartpole/robot, 16 quadrotor)
    epochs: int = 250
    lr: float = 1e-2
    batch_size: int = 0        # 0 = full batch (one Adam step per epoch)
    seed: int = 0
    # hold out part of the record (time blocks, never random samples of one series) and keep the
    # weights of the epoch that predicted it best: an observer's artefacts are what a long run
    # overfits, and they do not repeat in the held-out blocks
    validation_fraction: float = 0.2
    # where the held-out time lies: "spread" (two blocks, at 30-40 % and 80-90 % of the record) or "tail"
    # (the last part). Spread is the default: one block covers one stretch of the motion (a flight's final
    # hover, one part of a lap), and artefacts learned there pass its test (docs/results/table1.md, robot)
    validation_layout: str = "spread"
    residual_frame: str = ""
    ensemble: int = 1

    def as_dict(self) -> dict:
        """The fields as a plain dict (stored in a trained model's meta)."""
        return dict(self.__dict__)


PAPER_TRAINING = {  # Sec. V: 2 layers x 8 tanh; 250 epochs (cartpole), 10000 epochs (robot)
    # 250 full-batch epochs cannot overfit the cartpole record, so it trains on all of it, as the paper;
    # 10000 epochs on the robot fit the range observer's artefacts unless a held-out block stops them.
    # Two held-out blocks, not one tail block (chosen on fresh seeds 15-29, docs/results/table1.md):
    # one block covers one stretch of the lap, whose artefacts the network may share
    "cartpole": TrainingConfig(hidden=8, epochs=250, lr=2e-2, validation_fraction=0.0),
    "robot": TrainingConfig(hidden=8, epochs=10000, lr=5e-3, validation_fraction=0.2, validation_layout="spread"),
}

# Pre-training observer of Table I per task: (first observer, observer -> train rounds), see
# estimators.algorithm1; the evidence for each choice is on docs/results/table1.md ("How the KNODE is trained").
# - cartpole: the record's states and Δθ fitted jointly from the filter's estimates ("joint",
#   estimators.joint_training): the states the network learns from must also follow the learned model, which
#   undoes more of the model-free KF's lag than re-smoothing the record with the learned model and retraining.
#   A model-based smoother with the prior as the first observer is worse than the paper's model-free KF + RTS:
#   the prior's wrong cart mass biases the rates the network learns from.  What takes the cartpole to its
#   targets is not the observer: its Δθ corrects the accelerations only and is blind to the cart's position
#   (`Cartpole`'s masks).
# - robot: the unscented RTS pass on the precursory UKF (a smoother instead of the filter) helps more than
#   re-smoothing rounds on the seeds it was tried on (not all 15), and the joint fit is worse there.  What helps
#   the robot most is not the observer: its Δθ is blind to x, y, ψ (`GroundRobot.residual_blind`).
PAPER_OBSERVER = {"cartpole": ("joint", 0), "robot": ("smoother", 0)}

# Sec. V-C: 2 layers x 16 tanh, 150 epochs, KF pre-training observer
CRAZYFLIE_TRAINING = TrainingConfig(hidden=16, epochs=150, lr=1e-3, validation_fraction=0.2,
                                    validation_layout="spread")

# How a diagnosis splits its flights into fitting and scored ones (workflows.diagnosis), in the
# words every surface uses: the API schema, `learnest diagnose --help`, the report page.
DIAGNOSIS_SPLIT_RULE = ("the kinematic prior (quadrotor) fits its effects on the first flight and scores them on the "
                        "others; the Crazyflie prior fits on the first half of the flights (rounded up) and scores "
                        "on the rest; a single flight is fitted on its first 60 % and scored on the last 40 %; "
                        "flights failing the quality checks are left out first")


def diagnosis_fitting_count(n_flights: int, system: str) -> int:
    """How many of a diagnosis's ``n_flights`` usable flights, in order, it fits on (the rest are scored), by
    `DIAGNOSIS_SPLIT_RULE`: the first half, rounded up, with the input-driven prior (``system`` "crazyflie"),
    the first with the kinematic one.  One flight: 1 (its first 60 % is fitted, the rest scored)."""
    return (n_flights + 1) // 2 if system == "crazyflie" else min(n_flights, 1)
