"""The residual problems a diagnosis fits (the accelerometer channel against Savitzky-Golay references, the
dynamics on an observer's states), the split into fitting and scored data, and the summaries and repair
verdict every diagnosis report shares."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from learnest.estimators.metrics import better_beyond_interval, gain_interval_over_time, worse_beyond_interval
from learnest.estimators.observers import pretraining_observer
from learnest.estimators.prepared import initial_state
from learnest.estimators.ukf import run_ukf
from learnest.ingest.baseline import sg_references
from learnest.ingest.flight import Flight
from learnest.models.backend import rk4_step
from learnest.models.crazyflie.identify import lowpass
from learnest.models.effects import (
    Effect,
    dynamics_params,
    effects_for,
    predict_acc_body,
    specific_force_body,
    unidentifiable_scales,
)
from learnest.models.inputs import slice_keeping_heat
from learnest.models.knode import HybridModel
from learnest.models.presets import diagnosis_fitting_count
from learnest.models.residual_problem import ResidualProblem
from learnest.models.systems import System

# The SG reference of the accelerometer channel: 0.41 s, order 4.  Its passband must stay flat over the
# manoeuvres: the reference is rotated into the body frame with the *unsmoothed* mocap attitude, and an
# attenuated acceleration leaves a tilt error in body x/y that a delay fit absorbs.  Order 3 over 0.31 s
# moved a known 40 ms delay by +2 to +14 ms on noise-free simulated flights; order 4 over 0.41 s by
# at most +2 ms (benchmarks/results/timing_bias.md).
DIAGNOSIS_SG_WINDOW = 41
DIAGNOSIS_SG_ORDER = 4
# Both sides of the accelerometer residual pass this zero-phase low-pass (no relative shift): above it the
# reference is double-differentiated mocap noise and the reading vibration, which only add scatter to
# the delay (±10 ms on 15-s simulated flights without it, a few ms with it).
DIAGNOSIS_LOWPASS_HZ = 8.0
EDGE_S = 0.5               # SG references are least reliable at the ends of a record
# The residual time series kept in the report for its plot: bin means down to at most this many points
# per channel (3 axes before and after: ~60 kB of JSON), enough to see a bias or a drift leave.
SERIES_POINTS = 1000


# -- building the residual problems ------------------------------------------------------------------
def dynamics_problem(system: System, zeta: np.ndarray, u: np.ndarray, dt: float, candidates: list[Effect],
                     components: list[int] | None = None, blocks: list[np.ndarray] | None = None,
                     name: str = "dynamics") -> ResidualProblem:
    """One-step prediction residual of the observer's states (eq. 7), whitened per state component.

    Rows are the T-1 steps of ζ (T, n) with inputs u (T, p) and step ``dt`` (s); a row is
    (ζ_{k+1} - RK4(ζ_k)) / dt for the chosen ``components`` (default all), divided by that component's
    standard deviation at the candidates' nominal values.
    """
    components = list(range(system.n)) if components is None else components
    x_now, x_next, u_now = zeta[:-1], zeta[1:], u[:-1]

    def raw(values, rows):
        params = dynamics_params(system, values, candidates)
        step = rk4_step(lambda x, uu: system.dynamics(x, uu, params), x_now[rows], u_now[rows], dt)
        return ((x_next[rows] - step) / dt)[:, components]

    scale = raw({k: v for e in candidates for k, v in e.nominal().items()}, np.arange(len(x_now))).std(axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    return ResidualProblem(name, candidates, lambda values, rows: raw(values, rows) / scale, len(x_now),
                           blocks or [])


def accelerometer_problem(flights: list[Flight], window: int = DIAGNOSIS_SG_WINDOW) -> ResidualProblem:
    """acc_body − predicted IMU reading of the SG-reference specific force, over the flights' middles.

    Rows are the samples of every flight without its first and last ``EDGE_S`` s, k = 3 columns (m/s²,
    body frame); the flights are the cross-validation blocks when there are several.  The x/y scale
    factors are frozen at 1 when that axis' specific force is below ``effects.MIN_HORIZONTAL_FORCE_MS2`` rms.
    Needs the ``acc_body`` channel.  ``window`` is the SG window, samples.
    """
    pieces = []
    for flight in flights:
        edge = int(EDGE_S / flight.dt)
        a_ref = sg_references(flight.p, flight.dt, window=window, order=DIAGNOSIS_SG_ORDER)["a"]
        f_body = lowpass(specific_force_body(a_ref, flight.quat), flight.dt, DIAGNOSIS_LOWPASS_HZ)
        acc_body = lowpass(flight.channels["acc_body"], flight.dt, DIAGNOSIS_LOWPASS_HZ)
        pieces.append((flight.t, f_body, acc_body, slice(edge, len(flight.t) - edge)))
    lengths = [len(p[0][p[3]]) for p in pieces]
    offsets = np.cumsum([0] + lengths)

    def residual(values, rows):
        parts = [(acc - predict_acc_body(f, t, values))[keep] for t, f, acc, keep in pieces]
        return np.concatenate(parts)[rows]

    blocks = [np.arange(offsets[i], offsets[i + 1]) for i in range(len(pieces))] if len(pieces) > 1 else []
    frozen = unidentifiable_scales(np.concatenate([f[keep] for _, f, _, keep in pieces]))
    times = np.concatenate([t[keep] for t, _, _, keep in pieces])
    return ResidualProblem("accelerometer", effects_for("quadrotor", "measurement"), residual,
                           int(offsets[-1]), blocks, frozen, times)


def residual_series(problem: ResidualProblem, values: dict, flight: str, points: int = SERIES_POINTS) -> dict:
    """The residual of a one-flight problem over time, with the prior (before) and with the fitted effects
    (after), for the report's plot.

    Parameters
    ----------
    problem : ResidualProblem
        One flight's problem with ``times``; its first 3 columns are plotted (body x, y, z, m/s²).
    values : dict
        The fitted parameter values {name: value}; parameters absent stay nominal.
    flight : str
        The flight's name, reported.
    points : int
        At most this many points: consecutive rows are averaged in equal bins (a mean, not a pick, so that
        decimating a long flight does not alias the residual).

    Returns
    -------
    dict
        ``flight``, ``units`` "m/s²", ``axes`` ["x", "y", "z"], ``t`` (P,) s since the first row,
        ``before`` and ``after`` (P, 3) lists, rounded to 0.1 mm/s².
    """
    if problem.times is None:
        raise ValueError(f"residual_series: the {problem.name} problem has no row times")
    nominal = {k: v for e in problem.candidates for k, v in e.nominal().items()}
    rows = np.arange(problem.n_rows)
    before = problem.residual(nominal, rows)[:, :3]
    after = problem.residual({**nominal, **values}, rows)[:, :3]
    step = -(-problem.n_rows // points)   # ceil: at most `points` bins
    usable = problem.n_rows // step * step

    def binned(a):
        return a[:usable].reshape(usable // step, step, *a.shape[1:]).mean(axis=1)

    t = problem.times - problem.times[0]
    return {"flight": flight, "units": "m/s²", "axes": ["x", "y", "z"], "t": binned(t).round(3).tolist(),
            "before": binned(before).round(4).tolist(), "after": binned(after).round(4).tolist()}


# -- Crazyflie flights -----------------------------------------------------------------------------
# How the flights of a diagnosis are split (`_split_for_fitting`, `_split_crazyflie`), in the words every
# surface uses (the API schema, `learnest diagnose --help`); each report says its own split in ``split``,
# ``fitting_flights`` and ``scored_flights``.  Flights failing the quality checks are left out first.
# (models.presets.DIAGNOSIS_SPLIT_RULE: kept where the API schema can import it without numpy.)


def _split_for_fitting(flights: list[Flight], system: str = "quadrotor"):
    """(fitting, scored, how) by `models.presets.diagnosis_fitting_count`: the first flight (kinematic prior)
    or the first half, rounded up (``system`` "crazyflie"), fitted, the others scored; one flight: fit on its
    first 60 %, score the rest (its motors as warm as the flight's were there, `models.inputs.slice_keeping_heat`)."""
    if len(flights) > 1:
        cut = diagnosis_fitting_count(len(flights), system)
        return flights[:cut], flights[cut:], (f"fit on the first {cut} flight(s), scored on the other "
                                              f"{len(flights) - cut}")
    cut = int(0.6 * len(flights[0].t))
    return [flights[0].slice(0, cut)], [slice_keeping_heat(flights[0], cut, len(flights[0].t))], \
        "one flight: fit on its first 60 %, scored on the last 40 %"


def _nominal(effects) -> dict:
    return {k: v for e in effects for k, v in e.nominal().items()}


def repair_interval(before: dict, after: dict, method: str, dt: float) -> list[float] | None:
    """95 % interval of the repair's gain on one flight, % (100 (1 − Σ after / Σ before) of the per-step
    squared error), by the evaluation's paired block bootstrap (`estimators.metrics.gain_interval`).
    ``before``/``after`` are `evaluate_flight` results kept with their estimates."""
    reference = before["reference"]
    err_b = ((before["results"][method]["estimates"] - reference) ** 2).mean(axis=1)
    err_a = ((after["results"][method]["estimates"] - reference) ** 2).mean(axis=1)
    return gain_interval_over_time(err_b, err_a, dt)


def repair_verdict(report: dict, methods: Sequence[str]) -> dict:
    """Whether the repaired model is better on the held-out flights, by the evaluation's interval rule.

    The deciding method is the first KNODE method asked for, else the first.  The repair improves when its
    median held-out MSE is lower, no held-out flight is clearly worse (its gain interval wholly below 0) and
    at least one is clearly better (wholly above 0); without an estimator, when the specific-force RMSE is
    lower on every held-out flight.  A flight too short for an interval counts as better or worse by its MSE
    alone.  Returns {"improves": bool, "method", "reason"}.
    """
    per_flight = report["per_flight"]
    if not report["effects"] or not any(any(e.get("identified", {}).values()) for e in report["effects"]):
        return {"improves": False, "method": None, "reason": "no identified effect: the repaired prior is the prior"}
    if not methods:
        everywhere = all(p["after"]["specific_force_rmse"] < p["before"]["specific_force_rmse"] for p in per_flight)
        return {"improves": everywhere, "method": "specific_force_rmse",
                "reason": ("the specific force from the inputs is better on every held-out flight" if everywhere else
                           "the specific force from the inputs is not better on every held-out flight")}
    method = next((m for m in methods if m.startswith("knode")), methods[0])
    b, a = report["before"][method], report["after"][method]
    intervals = [p["repair_gain_interval_pct"].get(method) for p in per_flight]
    worse: list[str] = [p["flight"] for p, i in zip(per_flight, intervals) if worse_beyond_interval(i)]
    better: list[str] = [p["flight"] for p, i in zip(per_flight, intervals) if better_beyond_interval(i)]
    # a flight too short for an interval (fewer than 3 bootstrap blocks) counts by its MSE alone
    untold = [p for p, i in zip(per_flight, intervals) if i is None]
    worse += [p["flight"] for p in untold if p["after"][method] >= p["before"][method]]
    better += [p["flight"] + " (too short for an interval: by its MSE)" for p in untold
               if p["after"][method] < p["before"][method]]
    if a >= b:
        reason = f"held-out median {method} MSE does not improve ({b:.4g} → {a:.4g})"
    elif worse:
        reason = f"clearly worse (gain interval below 0) on {', '.join(worse)}"
    elif not better:
        reason = (f"median {method} MSE {b:.4g} → {a:.4g}, but on no held-out flight is the gain's 95 % interval "
                  "above 0: the change is within the flights' own variability")
    else:
        reason = f"median {method} MSE {b:.4g} → {a:.4g}, clearly better on {', '.join(better)}, worse on none"
    return {"improves": bool(a < b and not worse and better), "method": method, "reason": reason}


def _residual_summary(fitting, fixed_fitting, accel, dynamics, knode):
    """(a) the KNODE's learned residual along the observed states, (b) UKF innovations per channel,
    (c) a_meas − a_ref, each before and after the effects were added (rms)."""
    flight, fixed = fitting[0], fixed_fitting[0]
    system = replace(knode.system, dt=flight.dt)
    zeta = pretraining_observer(system, flight.measurements(), np.zeros((len(flight.t), 0)), flight.dt)
    learned = knode.residual(zeta, np.zeros((len(zeta), 0))) if knode.residual else np.zeros_like(zeta)
    out = {"knode_residual_rms": dict(zip(system.state_names, np.sqrt((learned**2).mean(0)).round(5).tolist()))}
    for label, f in (("before", flight), ("after", fixed)):
        innovations = run_ukf(HybridModel(system, "prior"), f.measurements(), dt=f.dt, Q=system.Q, R=system.R,
                              x0=initial_state(f), P0=system.P0).innovations
        a_ref = sg_references(f.p, f.dt, window=DIAGNOSIS_SG_WINDOW, order=DIAGNOSIS_SG_ORDER)["a"]
        rms = np.sqrt((innovations**2).mean(0)).round(5).tolist()
        out[f"innovation_rms_{label}"] = dict(zip(system.meas_names, rms))
        out[f"a_meas_minus_a_ref_rms_{label}"] = np.sqrt(((f.a_meas - a_ref) ** 2).mean(0)).round(4).tolist()
        out[f"a_meas_minus_a_ref_mean_{label}"] = (f.a_meas - a_ref).mean(0).round(4).tolist()
    return out


def _channel(selection):
    return {"rss_before": selection["rss_before"], "rss_after": selection["rss_after"], "trace": selection["trace"]}


def _public_effects(selection):
    """The chosen effects as reported, each tagged with the residual channel it explains."""
    return [{**e, "channel": selection["channel"]} for e in selection["effects"]]


def _public(selection):
    return {"effects": _public_effects(selection), "confounded": selection["confounded"],
            "channels": {selection["channel"]: _channel(selection)}}
