"""Yardsticks that need no smoothed truth: mocap gaps and a fast reference, beside the paper's SG score.

Why three.  The paper scores every estimator by its MSE against a Savitzky–Golay fit of the mocap position (window
1.5 s).  That reference is smoother than the motion (a long window smooths fast motion away: its velocity peaks fall
short of a plain derivative of the same mocap, `docs/concepts/yardsticks.md`), so against it every method, the
vehicle's own onboard EKF included, scores alike.  Two yardsticks that need no smoothing tell them apart:

- *Mocap gaps* (`MocapGaps`): the mocap position is hidden in windows (default 0.5 s long, one every 2.5 s,
  after the first 5 s), each estimator runs on with the accelerometer and the inputs, and its position error
  inside the gaps is scored against the hidden mocap.  This is what a dynamics model is for in practice:
  carrying the estimate through occlusions.  The reference is the raw mocap, so nothing about it is assumed
  but its noise (~1 mm, small beside the centimetres an estimate drifts in half a second), and a constant
  offset of the mocap moves the estimates with it: the score does not change.
- *Fast reference* (`FastReference`): velocity (and acceleration) RMSE against a short Savitzky–Golay
  derivative of the raw mocap (0.05 s, 0.15 s), outside the gaps.  The vehicle's onboard estimate, where the
  log carries it, is scored here as the method ``onboard``.
- *The paper's SG score* (`PaperSG`): the MSE over [p, v, a] of Sec. VI, kept for Table I and the paper's
  protocol.

How the gaps are run.  A position measurement inside a gap must carry no information, and the compiled UKF
and MHE loops (`ukf.c`, `gn.c`) take a full measurement every step.  `PositionGapModel` makes the gap an
input instead: the model gets one more input, 1 where the mocap is present and 0 inside a gap, and its
position measurement is h_p(x) · mask.  Inside a gap the position row of h is the constant 0, its Jacobian
is zero and the measured position is set to 0 too, so the innovation is zero and carries no information:
the UKF's gain on those rows is exactly zero (their cross covariance vanishes), the MHE's position residual
and its arrival update are exactly zero.  That is skipping the position update, with the compiled functions
and the C loops unchanged (one more compilation per model architecture, cached like any other).

Which runs.  The unmasked run (the paper's protocol) gives the SG score and the fast reference; the
gap-masked run is one more run per method and gives the gap score.  Making the masked run the only run
would change the paper's score (its reference would be scored on estimates that just coasted through a
gap, and Table I would no longer be the paper's), and would mix the re-convergence after each gap into the
fast reference.  The masked runs reuse the batch's compiled functions (``mhe_cache``), so they cost about what
the unmasked runs cost, nothing more (the results page `docs/results/yardsticks.md`).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import numpy as np

from learnest.errors import InvalidInput
from learnest.models.presets import ONBOARD

from .evaluate import evaluate_sequence
from .gap_plan import GapPlan  # noqa: F401  (re-exported: where the gaps are)
from .headline import MEASURES, NOTHING_LEARNED, Headline, headline, learned_note  # noqa: F401  (re-exported)
from .metrics import gain_pct, rms_norm, unit_gain_interval, unit_interval_method
from .mocap_gaps import POSITION_ROWS, PositionGapModel, gap_mask, masked_measurements
from .params import EstimatorParams
from .yardstick_scores import (  # noqa: F401  (re-exported: the scores' types)
    FAST_ACCELERATION_WINDOW_S,
    FAST_VELOCITY_WINDOW_S,
    FastReference,
    FlightYardsticks,
    MocapGaps,
    PaperSG,
)

# the fast reference's polynomial order (its windows: `yardstick_scores`)
FAST_ORDER = 2
VELOCITY_COLS, ACCELERATION_COLS = slice(3, 6), slice(6, 9)
BASES = ("ukf", "mhe")


def run_with_gaps(methods: Sequence[str], prior: EstimatorParams, knode: EstimatorParams, y: np.ndarray,
                  u: np.ndarray, inside: np.ndarray, horizon: int, mhe_cache: dict | None = None,
                  on_stage: Callable[[str], object] | None = None) -> dict[str, dict]:
    """Each method run with the position measurements hidden where ``inside`` (T,) is True.

    Same estimators, tuning and caches as `evaluate_sequence` (it runs them), each bundle's model wrapped in
    `PositionGapModel`.  Returns ``{method: {"estimates": (T, n), "ms_per_step": float}}``.
    """
    y_gap, u_gap = masked_measurements(y, u, inside)
    prior_gap, knode_gap = (replace(p, model=PositionGapModel(p.model)) for p in (prior, knode))
    stage = None if on_stage is None else (lambda name: on_stage(f"{name} with mocap gaps"))
    # the reference only feeds evaluate_sequence's SG scores, unused here: the state itself keeps shapes valid
    results = evaluate_sequence(methods, prior_gap, knode_gap, y_gap, u_gap, np.zeros((len(y), len(prior.x0))),
                                horizon=horizon, keep_estimates=True, mhe_cache=mhe_cache, on_stage=stage)
    return {m: {"estimates": r["estimates"], "ms_per_step": r["ms_per_step"]} for m, r in results.items()}


# -- scores -----------------------------------------------------------------------------------------------
def fast_derivatives(p: np.ndarray, dt: float, velocity_window_s: float = FAST_VELOCITY_WINDOW_S,
                     acceleration_window_s: float = FAST_ACCELERATION_WINDOW_S) -> dict:
    """Velocity and acceleration of the raw mocap by short, centred Savitzky–Golay derivatives.

    Parameters
    ----------
    p : ndarray, shape (T, 3)
        Mocap position, m.
    dt : float
        Sample time, s.
    velocity_window_s, acceleration_window_s : float
        Window lengths, s (rounded to an odd number of samples, at least 3 and 5).

    Returns
    -------
    dict
        ``v`` (T, 3) m/s, ``a`` (T, 3) m/s², and the windows used, ``velocity_window_s`` and
        ``acceleration_window_s`` (s, odd samples × dt).
    """
    from scipy.signal import savgol_filter

    p = np.asarray(p, dtype=float)

    def odd(window_s: float, least: int) -> int:
        samples = max(least, int(round(window_s / dt)))
        return samples + 1 if samples % 2 == 0 else samples

    wv, wa = odd(velocity_window_s, 3), odd(acceleration_window_s, 5)
    if len(p) < wa:
        raise InvalidInput(f"a record of {len(p)} samples is shorter than the fast reference's window ({wa})")
    v = savgol_filter(p, wv, min(FAST_ORDER, wv - 1), deriv=1, delta=dt, axis=0, mode="interp")
    a = savgol_filter(p, wa, FAST_ORDER, deriv=2, delta=dt, axis=0, mode="interp")
    return {"v": v, "a": a, "velocity_window_s": wv * dt, "acceleration_window_s": wa * dt}


def gap_squared_errors(p_mocap: np.ndarray, estimates: np.ndarray, windows: Sequence[tuple[int, int]]) -> np.ndarray:
    """(K,) squared 3-D position error, m², of a gap-masked run's ``estimates`` (T, n) against the hidden mocap
    ``p_mocap`` (T, 3) at the K samples inside the gaps ``windows`` (`GapPlan.windows`)."""
    inside = gap_mask(len(p_mocap), windows)
    return np.sum((np.asarray(estimates)[inside][:, POSITION_ROWS] - np.asarray(p_mocap)[inside]) ** 2, axis=1)


def per_gap_sums(err2: np.ndarray, windows: Sequence[tuple[int, int]]) -> np.ndarray:
    """(G,) sum of the squared errors ``err2`` (K,) of `gap_squared_errors` within each of the G gaps
    ``windows``, m² (the samples of ``err2`` are the gaps' in order)."""
    lengths = [stop - first for first, stop in windows]
    return np.add.reduceat(np.asarray(err2, dtype=float), np.cumsum([0] + lengths[:-1])) if lengths else np.zeros(0)


def gap_gain(prior_err2: np.ndarray, knode_err2: np.ndarray,
             windows: Sequence[tuple[int, int]]) -> tuple[float | None, list[float] | None]:
    """(gain %, its 95 % interval or None) of the second run over the first on the same gap samples
    (`gap_squared_errors` of each, (K,) m²): 100 (1 − Σ knode / Σ prior), None where the first's error is zero.

    The interval treats the gaps as the independent units (the estimate re-converges on the mocap between
    two gaps; within one the error drifts, so its samples are far from independent): each gap's squared
    errors are summed per run and `estimators.metrics.unit_gain_interval` tells the interval from them, from
    two gaps on.  None for one gap or no prior error: the flight is then undecided (`headline`)."""
    prior, knode = per_gap_sums(prior_err2, windows), per_gap_sums(knode_err2, windows)
    gain = gain_pct(float(np.sum(prior)), float(np.sum(knode))) if np.sum(prior) > 0 else None
    return gain, unit_gain_interval(prior, knode)


def gap_scores(p_mocap: np.ndarray, gapped: Mapping[str, np.ndarray], windows: Sequence[tuple[int, int]],
               plan: GapPlan, ms_per_step: Mapping[str, float] | None = None) -> MocapGaps:
    """`MocapGaps` from the gap-masked runs' estimates {method: (T, n)} and the hidden mocap p (T, 3), m
    (``ms_per_step``: the runs' wall time per sample, ms)."""
    err2 = {m: gap_squared_errors(p_mocap, x, windows) for m, x in gapped.items()}
    rmse = {m: float(np.sqrt(np.mean(e))) for m, e in err2.items()}
    gains, intervals = {}, {}
    for base in BASES:
        if base in err2 and f"knode-{base}" in err2:
            key = f"knode-{base}_vs_{base}"
            gains[key], intervals[key] = gap_gain(err2[base], err2[f"knode-{base}"], windows)
    method = unit_interval_method(len(windows)) if any(i is not None for i in intervals.values()) else None
    return MocapGaps(rmse, gains, intervals, method, plan.gap_s, plan.every_s, plan.start_s, len(windows),
                     dict(ms_per_step or {}))


def fast_reference_scores(p_mocap: np.ndarray, dt: float, estimates: Mapping[str, np.ndarray],
                          outside: np.ndarray, onboard: Mapping[str, np.ndarray] | None = None) -> FastReference:
    """`FastReference` of the unmasked runs' estimates {method: (T, 9)} and of the onboard estimate
    (``onboard`` {"v": (T, 3) m/s[, "a": (T, 3) m/s²]}) on the samples where ``outside`` (T,) is True."""
    fast = fast_derivatives(p_mocap, dt)
    velocity = {m: rms_norm(np.asarray(x)[outside, VELOCITY_COLS] - fast["v"][outside]) for m, x in estimates.items()}
    acceleration = {m: rms_norm(np.asarray(x)[outside, ACCELERATION_COLS] - fast["a"][outside])
                    for m, x in estimates.items()}
    if onboard and onboard.get("v") is not None:
        velocity[ONBOARD] = rms_norm(np.asarray(onboard["v"])[outside] - fast["v"][outside])
        if onboard.get("a") is not None:
            acceleration[ONBOARD] = rms_norm(np.asarray(onboard["a"])[outside] - fast["a"][outside])
    return FastReference(velocity, acceleration, round(fast["velocity_window_s"], 6),
                         round(fast["acceleration_window_s"], 6), int(np.count_nonzero(outside)))


def flight_yardsticks(methods: Sequence[str], prior: EstimatorParams, knode: EstimatorParams,
                      y: np.ndarray, u: np.ndarray, p_mocap: np.ndarray, estimates: Mapping[str, np.ndarray],
                      paper_mse: Mapping[str, float], plan: GapPlan, horizon: int,
                      onboard: Mapping[str, np.ndarray] | None = None, sg_window_s: float | None = None,
                      mhe_cache: dict | None = None,
                      on_stage: Callable[[str], object] | None = None) -> tuple[FlightYardsticks, dict]:
    """The three yardsticks of one flight.

    Parameters
    ----------
    methods : sequence of str
        Estimators to run with gaps (``ukf``, ``mhe``, ``knode-ukf``, ``knode-mhe``).
    prior, knode, y, u, horizon, mhe_cache, on_stage
        As `evaluate_sequence` (each model's bundle with its own noise; the grid is theirs)
        (y (T, m) = [p, a_meas], u (T, p)).
    p_mocap : ndarray, shape (T, 3)
        The mocap position, m: hidden inside the gaps, the reference there; its derivatives are the fast
        reference.
    estimates : dict
        {method: (T, 9)} of the unmasked runs (fast reference).
    paper_mse : dict
        {method: MSE against the SG references} of the unmasked runs.
    plan : GapPlan
        Where the gaps are.
    onboard : dict, optional
        The vehicle's own estimate, {"v": (T, 3) m/s, "a": (T, 3) m/s² or None}: scored as ``onboard``.
    sg_window_s : float, optional
        The SG references' window, s (stated in ``paper_sg``).

    Returns
    -------
    (FlightYardsticks, dict)
        The yardsticks, and {method: (T, n)} estimates of the gap-masked runs (empty without gaps).
    """
    p_mocap, dt = np.asarray(p_mocap, dtype=float), prior.dt
    windows = plan.windows(len(p_mocap), dt)
    inside = gap_mask(len(p_mocap), windows)
    gapped: dict = {}
    if windows and methods:
        runs = run_with_gaps(methods, prior, knode, y, u, inside, horizon, mhe_cache, on_stage)
        gapped = {m: r["estimates"] for m, r in runs.items()}
        gaps = gap_scores(p_mocap, gapped, windows, plan, {m: r["ms_per_step"] for m, r in runs.items()})
    else:
        reason = plan.too_short(len(p_mocap), dt) or "no estimator was run"
        gaps = MocapGaps(gap_s=plan.gap_s, every_s=plan.every_s, start_s=plan.start_s, skipped=reason)
    fast = fast_reference_scores(p_mocap, dt, estimates, ~inside, onboard)
    window_s = None if sg_window_s is None else round(float(sg_window_s), 6)
    return FlightYardsticks(gaps, fast, PaperSG(dict(paper_mse), window_s)), gapped


def onboard_estimate(channels: Mapping[str, np.ndarray]) -> dict | None:
    """The vehicle's own estimate in a Flight's channels (`ingest.flight.OPTIONAL`): {"p", "v", "a"} arrays
    (T, 3) in m, m/s, m/s² (None where not logged), or None when the log carries no onboard velocity."""
    if channels.get("v_onboard") is None:
        return None
    return {"p": channels.get("p_onboard"), "v": channels["v_onboard"], "a": channels.get("acc_onboard")}
