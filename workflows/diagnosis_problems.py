"""The residual problems a diagnosis fits (the accelerometer channel against Savitzky-Golay references, the
dynamics on an observer's states), the split into fitting and scored data, and the summaries and repair
verdict every diagnosis report shares."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from learnest.estimators.headline import MEASURES
from learnest.estimators.metrics import better_beyond_interval, gain_interval_over_time, worse_beyond_interval
from learnest.estimators.noise_identification import with_identified_noise
from learnest.estimators.observers import pretraining_observer
from learnest.estimators.prepared import initial_state, model_params
from learnest.estimators.ukf import run_ukf
from learnest.estimators.yardsticks import GapPlan, gap_gain, gap_squared_errors
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
from learnest.records import ReportView

# The SG reference of the accelerometer channel: 0.41 s, order 4.  Its passband must stay flat over the
# manoeuvres: the reference is rotated into the body frame with the *unsmoothed* mocap attitude, and an
# attenuated acceleration leaves a tilt error in body x/y that a delay fit absorbs.  Order 4 over 0.41 s biases
# a known delay far less than order 3 over 0.31 s on simulated flights (benchmarks/results/timing_bias.md).
DIAGNOSIS_SG_WINDOW = 41
DIAGNOSIS_SG_ORDER = 4
# Both sides of the accelerometer residual pass this zero-phase low-pass (no relative shift): above it the
# reference is double-differentiated mocap noise and the reading vibration, which only add scatter to
# the delay.
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


# The held-out flights of a repair are scored as an evaluation scores them: the mocap hidden 0.5 s every 2.5 s
# after the first 5 s (`estimators.yardsticks.GapPlan`'s defaults, the evaluation's headline yardstick).
REPAIR_GAPS = GapPlan()


def repair_scores(scored_b: dict, scored_a: dict, methods: Sequence[str], flight: Flight) -> dict:
    """What one held-out ``flight`` says of a repair, on both yardsticks.

    ``scored_b``/``scored_a`` are `evaluate_flight` results of the model before and after the repair on
    ``flight``, run with ``gaps=REPAIR_GAPS`` and ``keep_estimates``.  Returns ``repair_gain_interval_pct``
    {method: the interval on the paper's SG yardstick (`repair_interval`)} and ``mocap_gaps`` {``rmse_before_m``,
    ``rmse_after_m`` {method: RMS of the 3-D position error inside the gaps, m}, ``gain_pct`` {method:
    100 (1 − Σ after / Σ before) of the squared gap errors, %}, ``gain_interval_pct`` {method: its 95 % interval
    over the gaps (`estimators.yardsticks.gap_gain`), or None for a flight of one gap}, ``gaps``, ``gap_s``,
    ``skipped``: why the flight has no gap score (too short for one gap), else None}.
    """
    sg = {m: repair_interval(scored_b, scored_a, m, flight.dt) for m in methods}
    before, after = scored_b["yardsticks"].mocap_gaps, scored_a["yardsticks"].mocap_gaps
    gaps: dict = {"rmse_before_m": {}, "rmse_after_m": {}, "gain_pct": {}, "gain_interval_pct": {},
                  "gaps": before.gaps, "gap_s": before.gap_s, "skipped": before.skipped}
    if before.skipped is None:
        windows = REPAIR_GAPS.windows(len(flight.p), flight.dt)
        for m in methods:
            err_b = gap_squared_errors(flight.p, scored_b["gap_estimates"][m], windows)
            err_a = gap_squared_errors(flight.p, scored_a["gap_estimates"][m], windows)
            gaps["rmse_before_m"][m], gaps["rmse_after_m"][m] = before.rmse_m[m], after.rmse_m[m]
            gaps["gain_pct"][m], gaps["gain_interval_pct"][m] = gap_gain(err_b, err_a, windows)
    return {"repair_gain_interval_pct": sg, "mocap_gaps": gaps}


def repair_yardsticks(per_flight: list[dict], methods: Sequence[str]) -> dict:
    """The report's ``mocap_gaps`` (medians over the held-out flights of `repair_scores`' gap RMSE before and
    after, m, and the flights each improved, "k/n"; None where a flight has no gap score, ``skipped`` naming
    them) and ``paper_sg`` (what the report's ``before``/``after`` MSE measure)."""
    skipped = [f"{p['flight']}: {p['mocap_gaps']['skipped']}" for p in per_flight if p["mocap_gaps"]["skipped"]]
    gaps: dict = {"measures": MEASURES["mocap_gaps"], "gap_s": REPAIR_GAPS.gap_s, "every_s": REPAIR_GAPS.every_s,
                  "start_s": REPAIR_GAPS.start_s, "skipped": skipped, "before_rmse_m": None, "after_rmse_m": None,
                  "improved_flights": None}
    if per_flight and not skipped:
        rmse = {side: {m: float(np.median([p["mocap_gaps"][f"rmse_{side}_m"][m] for p in per_flight]))
                       for m in methods} for side in ("before", "after")}
        gaps.update(before_rmse_m=rmse["before"], after_rmse_m=rmse["after"], improved_flights={
            m: f"{sum(p['mocap_gaps']['rmse_after_m'][m] < p['mocap_gaps']['rmse_before_m'][m] for p in per_flight)}"
               f"/{len(per_flight)}" for m in methods})
    return {"mocap_gaps": gaps, "paper_sg": {"measures": MEASURES["paper_sg"],
                                             "note": "the report's before, after and per-flight MSE"}}


def repair_verdict(report: ReportView, methods: Sequence[str]) -> dict:
    """Whether the repaired model is better on the held-out flights, by the evaluation's yardstick and rule.

    The yardstick is the evaluation's headline, the mocap gaps (`repair_scores`: position RMSE inside 0.5-s
    windows where the mocap was hidden); the paper's SG MSE decides only when a held-out flight is too short
    for one gap (the reason says so).  The deciding method is the first KNODE method asked for, else the first.
    The repair improves when its median held-out error is lower, no held-out flight is worse beyond its gain's
    95 % interval and at least one is better beyond it (`estimators.metrics`); a flight too short for an
    interval counts neither way, unless no flight has one: then it must be better on every flight.  Without an
    estimator: when the specific-force RMSE is lower on every held-out flight.  Returns {"improves": bool,
    "method", "reason", "yardstick": "mocap_gaps" | "paper_sg" | None, "paper_sg": the SG rule's own
    {"improves", "reason"}, where scored}.
    """
    per_flight = report["per_flight"]
    if not report["effects"] or not any(any(e.get("identified", {}).values()) for e in report["effects"]):
        return {"improves": False, "method": None, "yardstick": None,
                "reason": "no identified effect: the repaired prior is the prior"}
    if not methods:
        everywhere = all(p["after"]["specific_force_rmse"] < p["before"]["specific_force_rmse"] for p in per_flight)
        return {"improves": everywhere, "method": "specific_force_rmse", "yardstick": "specific_force_rmse",
                "reason": ("the specific force from the inputs is better on every held-out flight" if everywhere else
                           "the specific force from the inputs is not better on every held-out flight")}
    method = next((m for m in methods if m.startswith("knode")), methods[0])
    sg = _interval_rule(per_flight, method, "MSE on the paper's SG yardstick",
                        [(p["before"][method], p["after"][method], p["repair_gain_interval_pct"].get(method))
                         for p in per_flight], report["before"][method], report["after"][method])
    skipped = [f"{p['flight']} ({p['mocap_gaps']['skipped']})" for p in per_flight
               if (p.get("mocap_gaps") or {"skipped": "not scored with mocap gaps"})["skipped"]]
    if skipped:
        return {**sg, "method": method, "yardstick": "paper_sg", "paper_sg": dict(sg),
                "reason": f"decided on the paper's SG yardstick, as a held-out flight has no mocap gap: "
                          f"{'; '.join(skipped)}. {sg['reason']}"}
    gaps = [p["mocap_gaps"] for p in per_flight]
    verdict = _interval_rule(per_flight, method, "mocap-gap position RMSE (m)",
                             [(g["rmse_before_m"][method], g["rmse_after_m"][method], g["gain_interval_pct"][method])
                              for g in gaps], float(np.median([g["rmse_before_m"][method] for g in gaps])),
                             float(np.median([g["rmse_after_m"][method] for g in gaps])))
    return {**verdict, "method": method, "yardstick": "mocap_gaps", "paper_sg": sg}


def _interval_rule(per_flight: Sequence[ReportView], method: str, what: str, scores: list, median_before: float,
                   median_after: float) -> dict:
    """{"improves", "reason"} by the evaluation's counting over flights (`estimators.headline`): ``scores``
    [(before, after, gain interval or None)] per flight of ``per_flight``; better when the median is lower
    (``median_before`` → ``median_after``, in ``what``), no flight is worse beyond its gain's interval and one
    is better beyond it.  A flight without an interval (one gap; on the SG yardstick, fewer than 3 bootstrap
    blocks) cannot tell, and counts neither way, as the evaluation's undecided flights; only when no flight
    has one does each flight's error decide (better on every flight), else a short held-out set could never
    be judged."""
    names = [p["flight"] for p in per_flight]
    worse = [n + " (beyond its interval)" for n, (_, _, i) in zip(names, scores) if worse_beyond_interval(i)]
    better = [n + " (beyond its interval)" for n, (_, _, i) in zip(names, scores) if better_beyond_interval(i)]
    untold = [n for n, (_, _, i) in zip(names, scores) if i is None]
    if len(untold) == len(names):   # no flight can tell by an interval: each one's error decides
        worse = [n + " (by its error: no flight has an interval)" for n, (b, a, _) in zip(names, scores) if a >= b]
        better = [n + " (by its error: no flight has an interval)" for n, (b, a, _) in zip(names, scores) if a < b]
    change = f"median {method} {what} {median_before:.4g} → {median_after:.4g}"
    if median_after >= median_before:
        reason = f"held-out {change}: no improvement"
    elif worse:
        reason = f"{change}, but worse on {', '.join(worse)}"
    elif not better:
        reason = (f"{change}, but on no held-out flight is the gain's 95 % interval above 0: the change is within "
                  "the flights' own variability")
    else:
        reason = f"{change}, better on {', '.join(better)}, worse on none"
    if untold and len(untold) < len(names):
        reason += f" ({', '.join(untold)}: too short for an interval, counted neither way)"
    return {"improves": bool(median_after < median_before and not worse and better), "reason": reason}


def _residual_summary(fitting, fixed_fitting, accel, dynamics, knode):
    """(a) the KNODE's learned residual along the observed states, (b) UKF innovations per channel,
    (c) a_meas − a_ref, each before and after the effects were added (rms)."""
    flight, fixed = fitting[0], fixed_fitting[0]
    system = replace(knode.system, dt=flight.dt)
    zeta = pretraining_observer(system, flight.measurements(), np.zeros((len(flight.t), 0)), flight.dt)
    learned = knode.residual(zeta, np.zeros((len(zeta), 0))) if knode.residual else np.zeros_like(zeta)
    out = {"knode_residual_rms": dict(zip(system.state_names, np.sqrt((learned**2).mean(0)).round(5).tolist()))}
    for label, f in (("before", flight), ("after", fixed)):
        params = model_params(HybridModel(system, "prior"), initial_state(f), f.dt)
        innovations = run_ukf(params, f.measurements()).innovations
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


def tuned_alike(before: HybridModel, after: HybridModel, fitting: Sequence[Flight]) -> HybridModel:
    """The repaired model ``after`` with its noise identified on ``fitting`` when the analysed model ``before``
    runs with identified noise: a repair is judged like with like (an identified-noise model against an untuned
    repair would make every repair look worse); ``after`` as it is otherwise."""
    if before.noise is None or after.kind == "prior":
        return after
    return with_identified_noise(after, fitting)
