"""Identify a model's noise (Q and R per block) from flights by maximising its UKF's likelihood.

For a filter whose model and noise are right, the innovations y_k − ŷ_k|k−1 are zero-mean with the
covariance S_k the filter predicts; the log-likelihood Σ log N(v_k; 0, S_k) measures how well they agree,
and its maximiser over Q and R is the maximum-likelihood noise (the classic approach to filter tuning;
dynamax fits a filter's noise the same way).  A model that misses physics needs more process noise to
follow the flight; a good residual needs less: each model gets the noise its own errors call for, which is
what makes comparing a KNODE with its prior fair.

Which likelihood.  The innovations' alone judge one step ahead, 10 ms, where the noise must also tell how far
the estimate may drift while the mocap is hidden.  So on flights the records hide the mocap in the yardstick's
gaps (`noise_records` with a `GapPlan`), and the objective adds, per step of each, the innovation likelihood
of what the filter saw and the log-likelihood of each hidden mocap position under its prediction there,
N(p; p̂, P_pp + R_p): a composite likelihood whose two parts the true noise of a right model maximises alike.
The innovations pin the acceleration noise (the accelerometer measures it; the hidden mocap hardly does), the
hidden mocap the velocity noise.

Noise is searched as one scale per block (`models.noise.blocks`: position, velocity, acceleration states;
mocap and accelerometer measurements) on the log scale, by Nelder–Mead from the paper's noise, each
evaluation one compiled UKF run over every flight.  The flights of one evaluation run on threads, one per
core: the compiled filter loop (`ukf.c`, called through ctypes) releases the interpreter's lock, and each
flight's model has its own compiled functions and scratch memory.  The position block of Q stays fixed:
ṗ = v is a definition, and its noise trades off against the mocap's R with almost no effect on the likelihood.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.models.cores import usable_cores
from learnest.models.knode import HybridModel
from learnest.models.noise import IDENTIFIED, PAPER, STD_BOUNDS, NoiseModel, blocks

from .mocap_gaps import POSITION_ROWS as ROWS
from .mocap_gaps import PositionGapModel, gap_mask, masked_measurements
from .params import EstimatorParams
from .prepared import prepare
from .ukf import SigmaFunctions, compiled_sigma_functions, run_ukf
from .yardsticks import GapPlan

# The blocks searched by default: velocity and acceleration process noise, both measurements (module docstring).
PROCESS_BLOCKS = ("v", "a")
MEASUREMENT_BLOCKS = ("p", "a")
# On real flights the sensors' noise stays the system's: the logged accelerometer is low-pass filtered on board,
# so its errors are not white, and the likelihood drives its standard deviation to ~1 mm/s² (NanoBench circles
# and figure-eights), below any MEMS accelerometer's noise floor: a number no vehicle can have.
FLIGHT_MEASUREMENT_BLOCKS: tuple[str, ...] = ()
# The first second of each record is the filter settling from x0 and P0: it says little about Q and R.
WARMUP_S = 1.0
# How far a block's standard deviation may move from the paper's, each way (a factor).
MAX_FACTOR = 1e3
# Nelder–Mead's budget and tolerance: one evaluation is one filter over every record; a scale known to
# 2 % is far below what changes an estimate.
MAX_EVALUATIONS = 160
TOLERANCE_LOG = 0.02
# The first simplex's width (a factor per block): from the paper's noise, which may be off by decades, 3; from
# a neighbour's identified noise (a KNODE's search starts from its prior's), 1.3: a residual changes what the
# filter must absorb by tens of per cent, not by factors, and a narrow simplex needs about half the evaluations.
COLD_STEP, WARM_STEP = 3.0, 1.3


@dataclass(frozen=True)
class NoiseRecord:
    """One flight as the filter of one model sees it (built by `estimators.prepared.prepare`).

    Attributes
    ----------
    name : str
        The flight's name.
    model : HybridModel or PositionGapModel
        The model whose noise is identified, on this flight's grid (wrapped when the mocap is hidden in gaps).
    y : ndarray, shape (T, m)
        Measurements.
    u : ndarray, shape (T, p)
        Inputs.
    x0 : ndarray, shape (n,)
        First state estimate.
    dt : float
        Sample period, s.
    hidden : ndarray, shape (T, 3), optional
        The mocap position (m) where ``inside``: with it, the log-likelihood of those positions under the
        filter's prediction joins the objective (module docstring).
    inside : ndarray of bool, shape (T,), optional
        Where the mocap is hidden from the filter (``y``'s position rows are 0 there).
    """

    name: str
    model: HybridModel | PositionGapModel
    y: np.ndarray
    u: np.ndarray
    x0: np.ndarray
    dt: float
    hidden: np.ndarray | None = None
    inside: np.ndarray | None = None


def _indices(names: tuple[str, ...], wanted: Sequence[str], what: str) -> dict[str, list[int]]:
    grouped = blocks(names)
    unknown = [b for b in wanted if b not in grouped]
    if unknown:
        raise InvalidInput(f"no {what} block named {', '.join(unknown)}; blocks are {', '.join(grouped)}")
    return {b: grouped[b] for b in wanted}


class _Likelihood:
    """The mean log-likelihood per step over the records (innovations after each one's warm-up, plus the hidden
    mocap's per hidden step where records hide it), as a function of
    the log-scales θ of the searched blocks (Q blocks first, then R blocks); -inf where a filter fails."""

    def __init__(self, records: Sequence[NoiseRecord], start: NoiseModel, q_idx: dict[str, list[int]],
                 r_idx: dict[str, list[int]], on_evaluation: Callable[[int, float], object] | None) -> None:
        self.records, self.start, self.q_idx, self.r_idx = records, start, q_idx, r_idx
        self.on_evaluation, self.evaluations = on_evaluation, 0
        self.names = [f"Q:{b}" for b in q_idx] + [f"R:{b}" for b in r_idx]
        self.functions: dict[tuple[int, float], SigmaFunctions | None] = {}
        for record in records:   # compiled once per model and dt, before the search
            key = (id(record.model), record.dt)
            if key not in self.functions:
                self.functions[key] = compiled_sigma_functions(record.model, record.dt)
        # records sharing compiled functions (and so their scratch memory) run on one thread, one after another
        by_functions: dict[tuple[int, float], list[NoiseRecord]] = {}
        for record in records:
            by_functions.setdefault((id(record.model), record.dt), []).append(record)
        self.groups = list(by_functions.values())
        self.pool = ThreadPoolExecutor(max_workers=max(1, min(len(self.groups), usable_cores())))
        self.steps = sum(max(0, len(r.y) - round(WARMUP_S / r.dt)) for r in records)
        self.hidden_steps = sum(int(np.sum(r.inside)) for r in records if r.inside is not None)
        if self.steps == 0:
            raise InvalidInput(f"every flight is shorter than the filter's {WARMUP_S:g}-s warm-up: no noise to "
                               "identify")

    def noise_at(self, theta: np.ndarray) -> NoiseModel:
        """The noise at log-scales θ, each standard deviation kept within `STD_BOUNDS`."""
        base_q, base_r = np.asarray(self.start.process_std), np.asarray(self.start.meas_std)
        q, r = base_q.copy(), base_r.copy()
        for value, idx in zip(theta[:len(self.q_idx)], self.q_idx.values()):
            q[idx] = np.clip(base_q[idx] * math.exp(value), *STD_BOUNDS)
        for value, idx in zip(theta[len(self.q_idx):], self.r_idx.values()):
            r[idx] = np.clip(base_r[idx] * math.exp(value), *STD_BOUNDS)
        return NoiseModel(tuple(q), tuple(r), self.start.initial_std, IDENTIFIED)

    def theta_of(self, noise: NoiseModel) -> np.ndarray:
        """The log-scales θ of ``noise`` on the start's noise, per searched block (its first row's ratio), within
        the search's bounds."""
        q0, r0 = np.asarray(self.start.process_std), np.asarray(self.start.meas_std)
        q, r = np.asarray(noise.process_std), np.asarray(noise.meas_std)
        theta = [math.log(q[idx[0]] / q0[idx[0]]) for idx in self.q_idx.values()] + \
            [math.log(r[idx[0]] / r0[idx[0]]) for idx in self.r_idx.values()]
        bound = math.log(MAX_FACTOR)
        return np.clip(np.array(theta, dtype=float), -bound, bound)

    def _log_likelihood(self, records: Sequence[NoiseRecord], noise: NoiseModel) -> tuple[float, float]:
        """(Σ innovation log-likelihood after the warm-up, Σ log-likelihood of the hidden mocap) over ``records``
        (which share no compiled functions with any other thread's); -inf where a filter fails."""
        innovations = hidden = 0.0
        for record in records:
            try:
                params = EstimatorParams.from_noise(record.model, record.dt, noise, record.x0)
                result = run_ukf(params, record.y, record.u,
                                 sigma_functions=self.functions[(id(record.model), record.dt)])
            except (np.linalg.LinAlgError, InvalidInput, FloatingPointError):
                return -math.inf, -math.inf
            ll = result.log_likelihoods
            if ll is None or not np.all(np.isfinite(ll[round(WARMUP_S / record.dt):])):
                return -math.inf, -math.inf
            innovations += float(np.sum(ll[round(WARMUP_S / record.dt):]))
            if record.hidden is not None and record.inside is not None:
                hidden += hidden_log_likelihood(result, record.hidden, record.inside, noise.R[np.ix_(ROWS, ROWS)])
        return innovations, hidden

    def __call__(self, theta: np.ndarray) -> float:
        noise = self.noise_at(theta)
        totals = list(self.pool.map(lambda group: self._log_likelihood(group, noise), self.groups))
        self.evaluations += 1
        value = sum(t[0] for t in totals) / self.steps
        if self.hidden_steps:   # each likelihood per step of its own, so neither outweighs the other by its count
            value += sum(t[1] for t in totals) / self.hidden_steps
        if not math.isfinite(value):
            value = -math.inf
        if self.on_evaluation:
            self.on_evaluation(self.evaluations, value)
        return value


def hidden_log_likelihood(result, hidden: np.ndarray, inside: np.ndarray, R_p: np.ndarray) -> float:
    """Σ over the hidden steps of log N(p_k; p̂_k, P_pp,k + R_p) (nats): how likely the filter found the mocap
    position it did not see.

    Parameters
    ----------
    result : FilterResult
        The filter's run with the mocap hidden where ``inside``.
    hidden : ndarray, shape (T, 3)
        The mocap position, m.
    inside : ndarray of bool, shape (T,)
        Where it was hidden.
    R_p : ndarray, shape (3, 3)
        The mocap's noise covariance, m².

    Returns
    -------
    float
        The log-likelihood, nats; -inf where a predicted covariance is not positive definite.
    """
    d = (hidden - result.means[:, list(ROWS)])[inside]
    S = result.covariances[inside][:, list(ROWS)][:, :, list(ROWS)] + R_p
    sign, logdet = np.linalg.slogdet(2 * np.pi * S)
    if not np.all(sign > 0):
        return -math.inf
    mahalanobis = np.einsum("ti,ti->t", d, np.linalg.solve(S, d[..., None])[..., 0])
    return float(np.sum(-0.5 * (mahalanobis + logdet)))


def identify_noise(records: Sequence[NoiseRecord], start: NoiseModel, *,
                   process_blocks: Sequence[str] = PROCESS_BLOCKS,
                   measurement_blocks: Sequence[str] = MEASUREMENT_BLOCKS,
                   max_evaluations: int = MAX_EVALUATIONS,
                   on_evaluation: Callable[[int, float], object] | None = None,
                   initial: NoiseModel | None = None) -> NoiseModel:
    """The noise that maximises the UKF's likelihood over ``records``: of the innovations, plus that of the hidden
    mocap where records hide it (`NoiseRecord.hidden`; module docstring).

    Parameters
    ----------
    records : sequence of NoiseRecord
        The flights, each with the model whose noise is identified (all of one system).
    start : NoiseModel
        Where the search starts, and the noise of every block not searched (usually `NoiseModel.paper`).
    process_blocks, measurement_blocks : sequence of str
        The blocks whose scale is searched (`models.noise.blocks` of the state and measurement names).
    max_evaluations : int
        Filter runs over all records at most.
    on_evaluation : callable, optional
        ``on_evaluation(count, mean_log_likelihood)`` after each evaluation (progress).
    initial : NoiseModel, optional
        Where the search begins, when not at ``start`` (a KNODE's from its prior's identified noise): a narrower
        first simplex (`WARM_STEP`).  The result is kept only where it beats ``start`` too.

    Returns
    -------
    NoiseModel
        Source ``"identified"``; ``detail`` holds the flights, the mean log-likelihood per step (nats) at the
        start and at the end, each searched block's factor on ``start``'s standard deviation, the blocks held
        at ``start``, blocks ending within 1 % of their bound, evaluations and seconds.

    Raises
    ------
    InvalidInput
        Without records, with unknown block names, or when no record is longer than the warm-up.
    """
    if not records:
        raise InvalidInput("noise identification needs at least one flight")
    system = records[0].model.system
    if system is None:   # a wrapped model passes its system through; a bare one must have it
        raise InvalidInput("noise identification needs models with a system (their state and measurement names)")
    objective = _Likelihood(records, start, _indices(system.state_names, process_blocks, "state"),
                            _indices(system.meas_names, measurement_blocks, "measurement"), on_evaluation)
    names, mean_log_likelihood, noise_at = objective.names, objective, objective.noise_at
    started = time.perf_counter()
    bound = math.log(MAX_FACTOR)
    x0 = np.zeros(len(names))
    begin, step = (x0, COLD_STEP) if initial is None else (objective.theta_of(initial), WARM_STEP)
    with objective.pool:
        before = mean_log_likelihood(x0)
        # Nelder–Mead expands a simplex that is too narrow, as needed
        simplex = np.vstack([begin] + [begin + math.log(step) * e for e in np.eye(len(names))])
        fit = minimize(lambda th: -mean_log_likelihood(th), begin, method="Nelder-Mead",
                       bounds=[(-bound, bound)] * len(names),
                       options={"maxfev": max_evaluations, "xatol": TOLERANCE_LOG, "fatol": 1e-5,
                                "initial_simplex": simplex})
    theta = fit.x if -fit.fun >= before else x0
    factors = {name: float(math.exp(v)) for name, v in zip(names, theta)}
    noise = noise_at(theta)
    held = [f"Q:{b}" for b in blocks(system.state_names) if b not in process_blocks] + \
        [f"R:{b}" for b in blocks(system.meas_names) if b not in measurement_blocks]
    detail = {"flights": [r.name for r in records], "steps": int(objective.steps),
              "log_likelihood_per_step": {"start": round(before, 6), "identified": round(max(-fit.fun, before), 6)},
              "factors": {k: round(v, 4) for k, v in factors.items()}, "held": held,
              "at_bound": [k for k, v in zip(names, theta) if abs(abs(v) - bound) < 0.01],
              "evaluations": objective.evaluations, "seconds": round(time.perf_counter() - started, 2),
              "method": ("maximum innovation likelihood of the UKF"
                         + (" plus the likelihood of the mocap hidden in gaps under its prediction"
                            if objective.hidden_steps else "") + " (Nelder-Mead on the log scale per block)")}
    return NoiseModel(noise.process_std, noise.meas_std, noise.initial_std, IDENTIFIED, detail)


def noise_records(model: HybridModel, flights: Sequence[Flight], which: str,
                  gaps: GapPlan | None = None) -> list[NoiseRecord]:
    """The records of ``flights`` for identifying the noise of ``model`` (``which="model"``) or of its prior
    (``which="prior"``), each prepared as an evaluation prepares it (`estimators.prepared.prepare`, with the
    system's fixed noise as the start).

    With ``gaps``, the mocap position is hidden in the gaps of the plan (`estimators.mocap_gaps.PositionGapModel`)
    and each record with a gap adds the likelihood of the hidden positions (`hidden_log_likelihood`): how well
    the filter predicts the position across each gap, which the mocap-gap yardstick scores.  A flight too short
    for one gap keeps its whole sequence and its innovations.
    """
    records = []
    for flight in flights:
        prepared = prepare(model, flight, noise=PAPER)
        chosen: HybridModel | PositionGapModel = prepared.model if which == "model" else prepared.prior
        y, u = prepared.y, prepared.u
        windows = gaps.windows(len(y), prepared.dt) if gaps is not None else []
        if not windows:
            records.append(NoiseRecord(flight.name, chosen, y, u, prepared.x0, prepared.dt))
            continue
        inside = gap_mask(len(y), windows)
        y_gap, u_gap = masked_measurements(y, u, inside)
        records.append(NoiseRecord(flight.name, PositionGapModel(chosen), y_gap, u_gap, prepared.x0, prepared.dt,
                                   hidden=y[:, list(ROWS)].copy(), inside=inside))
    return records


def with_identified_noise(model: HybridModel, flights: Sequence[Flight],
                          on_stage: Callable[[str], object] | None = None) -> HybridModel:
    """``model`` with its noise and its prior's identified on ``flights`` (its training flights), each by
    `identify_noise` from the system's fixed noise (the model's search beginning at its prior's result), the
    process noise only (`FLIGHT_MEASUREMENT_BLOCKS`), scored by the mocap hidden in the yardstick's gaps
    (`noise_records` with `GapPlan()`, module docstring): the two filters of every later comparison are tuned the
    same way on the same flights.

    Parameters
    ----------
    model : HybridModel
        A flight model (prior-only or KNODE).
    flights : sequence of Flight
        The flights it was trained on.
    on_stage : callable, optional
        ``on_stage(name)`` before each identification ("noise of the prior", "noise of the KNODE").

    Returns
    -------
    HybridModel
        The same dynamics with ``noise`` and ``prior_noise`` set (one identification for a prior-only model).
    """
    start = NoiseModel.paper(model.system)
    if on_stage:
        on_stage("noise of the prior")
    prior_noise = identify_noise(noise_records(model, flights, "prior", GapPlan()), start,
                                 measurement_blocks=FLIGHT_MEASUREMENT_BLOCKS)
    own = prior_noise
    if model.kind != "prior":
        if on_stage:
            on_stage(f"noise of the {model.kind.upper()}")
        own = identify_noise(noise_records(model, flights, "model", GapPlan()), start,
                             measurement_blocks=FLIGHT_MEASUREMENT_BLOCKS, initial=prior_noise)
    return HybridModel(model.system, model.kind, model.residual, model.meta, own, prior_noise)
