"""Run the four estimators of the Crazyflie experiment on one flight and score them (plain data out).

MSE is over the translational states x = [p, v, a] against references (Sec. VI: Savitzky–Golay of the
mocap position), overall and per state group; `summarize` gives the median over flights and the
improvement of each KNODE estimator over its prior-only counterpart (the quantity the paper reports).
"""
from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from learnest.models.presets import MHE_HORIZON
from learnest.records import ReportView

from .evaluation_report import EvaluationReport, FlightScore
from .headline import MEASURES, flight_verdict, flight_verdicts, headline, learned_note
from .metrics import VERDICTS, gain_interval_over_time, gain_pct, group_scores, squared_errors
from .mhe import MHE
from .params import EstimatorParams
from .ukf import compiled_sigma_functions, run_ukf

# the units of an evaluation report's numbers (the report's "units"); the overall MSE averages the squared
# errors of all nine states, each in its own squared SI unit
MSE_UNITS = {"mse": "mean of squared errors of p (m^2), v (m^2/s^2) and a (m^2/s^4)",
             "median": "as mse", "groups": {"p": "m^2", "v": "m^2/s^2", "a": "m^2/s^4"},
             "ms_per_step": "ms of wall time per sample", "improvement_pct": "% (100 (1 - knode / prior-only))"}


def _model_key(model, dt, cache: dict) -> tuple:
    """What tells the models of one cache apart.  The cache holds each residual it keys by id, so no residual
    is freed while the cache lives and no other can take over its id (and its compiled functions)."""
    system = model.system
    cache.setdefault(("residual held by its key", id(model.residual)), model.residual)
    return (model.kind, id(model.residual), system.name, tuple(sorted(system.prior_params.items())),
            tuple(sorted(system.true_params.items())), float(dt))


def _mhe_for(cache: dict, params: EstimatorParams, horizon: int) -> MHE:
    """One MHE per model and tuning, built before any timing: a batch of flights reuses it (compiling the
    Gauss–Newton functions or building the IPOPT problems costs seconds); each flight runs it from its own x0."""
    key = ("mhe", *_model_key(params.model, params.dt, cache), horizon, params.Q.tobytes(), params.R.tobytes(),
           params.P0.tobytes())
    if key not in cache:
        cache[key] = MHE(params, horizon=horizon).prepare()
    return cache[key]


def _ukf_functions_for(cache: dict, model, dt) -> tuple | None:
    """The UKF's compiled sigma-point functions of a model, built once per batch before any timing
    (generating and loading the code, let alone a first compile, is not the filter's work: neither belongs in
    ms_per_step); None, so numpy, for a model that does not take CasADi symbols (no ``parametric``)."""
    key = ("ukf", *_model_key(model, dt, cache))
    if key not in cache:
        cache[key] = compiled_sigma_functions(model, dt) if hasattr(model, "parametric") else None
    return cache[key]


def evaluate_sequence(methods: Sequence[str], prior: EstimatorParams, knode: EstimatorParams,
                      y: np.ndarray, u: np.ndarray, reference: np.ndarray, horizon: int = MHE_HORIZON,
                      keep_estimates: bool = False, mhe_cache: dict | None = None,
                      on_stage: Callable[[str], object] | None = None) -> dict:
    """{method: {"mse", "groups", "ms_per_step"[, "innovation_ms"][, "estimates"]}} for one record; pass one `mhe_cache`
    dict for all records of a batch so each MHE (and each UKF's compiled model) is built once, untimed.
    ``on_stage`` is told each method before it runs ("knode-ukf") and an MHE build before it starts
    ("MHE build (knode-mhe)").

    ``knode-*`` methods run with the bundle ``knode``, the others with ``prior`` (each model with its own
    noise, like against like; the two share dt and x0, `estimators.prepared.PreparedFlight.params`).
    y (T, m), u (T, p), reference (T, n); ``ms_per_step`` is wall time per sample, ms;
    ``innovation_ms`` (UKF methods) is the mean square of the one-step innovations per measurement channel,
    (m,) in the measurements' squared units (`prediction_check`); ``gain_interval_pct`` (a ``knode-*`` method
    run beside its base) is `estimators.metrics.gain_interval` of its gain over the base method, %, or None for a
    record too short to tell.
    """
    mhe_cache = {} if mhe_cache is None else mhe_cache
    results, step_errors = {}, {}
    for method in methods:
        params = knode if method.startswith("knode-") else prior
        if on_stage and not method.endswith("ukf"):
            on_stage(f"MHE build ({method})")
        mhe = None if method.endswith("ukf") else _mhe_for(mhe_cache, params, horizon)
        # compiled sigma-point model: an evaluation runs thousands of steps on one model (see make_ukf)
        functions = _ukf_functions_for(mhe_cache, params.model, params.dt) if mhe is None else None
        if on_stage:
            on_stage(method)
        started = time.perf_counter()
        if mhe is None:
            filtered = run_ukf(params, y, u, sigma_functions=functions)
            estimates = filtered.means
        else:
            filtered, estimates = None, mhe.run(y, u, params.x0).means
        elapsed = time.perf_counter() - started
        err2 = squared_errors(estimates, reference)
        step_errors[method] = err2.mean(axis=1)          # per step, for the gain's interval below
        results[method] = {**group_scores(err2), "ms_per_step": 1e3 * elapsed / len(y)}
        if filtered is not None:
            results[method]["innovation_ms"] = np.mean(filtered.innovations**2, axis=0).tolist()
        if keep_estimates:
            results[method]["estimates"] = estimates
    for method in results:
        base = method.removeprefix("knode-")
        if method != base and base in step_errors:
            results[method]["gain_interval_pct"] = gain_interval_over_time(step_errors[base], step_errors[method],
                                                                           prior.dt)
    return results


def one_step_innovation_ms(params: EstimatorParams, y: np.ndarray, u: np.ndarray,
                           cache: dict | None = None) -> np.ndarray:
    """Mean square of the UKF's one-step innovations y_k − h(f(x̂_{k−1})) per measurement channel, (m,): how
    well ``params.model`` predicts the next measurement of this record, with the bundle's noise.
    ``cache`` as `evaluate_sequence`'s."""
    functions = _ukf_functions_for({} if cache is None else cache, params.model, params.dt)
    filtered = run_ukf(params, y, u, sigma_functions=functions)
    return np.mean(filtered.innovations**2, axis=0)


def prediction_check(prior_ms: ArrayLike, knode_ms: ArrayLike, channels: Sequence[int],
                     names: Sequence[str]) -> dict:
    """How the KNODE predicts this record's next measurements against its prior: a diagnostic, not a verdict.

    The ratio of the two filters' mean squared one-step innovations, summed over ``channels``: above 1, the
    learned model predicts the next measurement (10 ms ahead on NanoBench) worse than the physics alone.  A
    report carries it per flight as ``one_step_innovation_ratio``; its verdict is the mocap gaps'
    (`estimators.headline.flight_verdict`), which judge the prediction across an occlusion.

    Parameters
    ----------
    prior_ms, knode_ms : array_like, (m,)
        `one_step_innovation_ms` of the prior-only and the KNODE model on the same record.
    channels : sequence of int
        Measurement channels compared (for flights: the mocap position; see `evaluate_flight`).
    names : sequence of str
        Names of all m channels.

    Returns
    -------
    dict
        ``channels`` (names), ``innovation_ratio`` (KNODE / prior), ``knode_predicts_worse`` (ratio > 1 + 1e-9).
    """
    prior = float(np.sum(np.asarray(prior_ms, dtype=float)[list(channels)]))
    knode = float(np.sum(np.asarray(knode_ms, dtype=float)[list(channels)]))
    ratio = knode / prior if prior > 0 else float("nan")
    # equal up to rounding (a residual that is zero on this record) is not worse
    return {"channels": [names[c] for c in channels], "innovation_ratio": ratio,
            "knode_predicts_worse": bool(ratio > 1.0 + 1e-9)}


def recommended_model(flight_report: ReportView, base: str) -> str | None:
    """The estimate learnest recommends on one scored flight for the base estimator ``base`` ("ukf", "mhe"):
    "prior" where the flight's verdict on KNODE-``base`` is "worse" (`estimators.headline.flight_verdict`: its
    gain in the mocap gaps is below 0 beyond its 95 % interval), else "knode"; None when the two did not both run.

    The same measure as the headline's, so the two agree by construction: the prior's estimate is recommended
    on exactly the flights the headline counts as worse beyond their interval.  The KNODE stays recommended
    where the flight cannot tell the two apart; an ensemble's doubt already pulls it towards the prior there.

    Parameters
    ----------
    flight_report : dict
        A scored flight's report entry (its ``mse`` names the methods that ran, its yardsticks the gaps).
    base : {"ukf", "mhe"}
        The base estimator.

    Returns
    -------
    str or None
        "knode" or "prior"; None when the KNODE and its prior did not both run.
    """
    key = f"knode-{base}_vs_{base}"
    if not {base, f"knode-{base}"} <= set(flight_report.get("mse") or {}):
        return None
    return "prior" if flight_verdict(flight_report, key) == "worse" else "knode"


RECOMMENDATION_RULE = ("per flight, the KNODE's estimate, or its prior's where the KNODE is worse in the mocap gaps "
                       "beyond the flight's 95 % interval")


def _recommended_summary(scored: Sequence[ReportView]) -> dict | None:
    """Per base estimator: the flights where the KNODE's and where the prior's estimate is recommended
    (`recommended_model`), the median gap RMSE of the recommended estimate (m) and of the prior alone."""
    summary: dict = {"rule": RECOMMENDATION_RULE, "knode_on": {}, "prior_on": {}, "median_gap_rmse_m": {},
                     "prior_median_gap_rmse_m": {}}
    for base in ("ukf", "mhe"):
        chosen = [(f, recommended_model(f, base)) for f in scored]
        chosen = [(f, model) for f, model in chosen if model is not None]
        if not chosen:
            continue
        summary["knode_on"][base] = [f["flight"] for f, model in chosen if model == "knode"]
        summary["prior_on"][base] = [f["flight"] for f, model in chosen if model == "prior"]
        rmse = [(f["yardsticks"]["mocap_gaps"]["rmse_m"], model) for f, model in chosen
                if {base, f"knode-{base}"} <= set((f.get("yardsticks") or {}).get("mocap_gaps", {}).get("rmse_m", {}))]
        if rmse:
            summary["median_gap_rmse_m"][base] = float(np.median(
                [r[f"knode-{base}" if model == "knode" else base] for r, model in rmse]))
            summary["prior_median_gap_rmse_m"][base] = float(np.median([r[base] for r, _ in rmse]))
    return summary if summary["knode_on"] else None


def summarize(flights: Sequence[FlightScore], model: str | None = None, model_meta: Mapping | None = None,
              **extra: Any) -> EvaluationReport:
    """The evaluation's report over its flights: median MSE over the scored flights, the KNODE improvements on
    those medians, and one verdict per flight.

    Parameters
    ----------
    flights : sequence of FlightScore
        Every flight's score, excluded ones too, in the report's order.
    model : str, optional
        The model evaluated, as the report names it.
    model_meta : mapping, optional
        The model's meta: whether it learned anything (`estimators.headline.learned_note`).
    **extra
        Further keys of the report (e.g. ``system``).

    Returns
    -------
    EvaluationReport
        ``flights``, ``units`` (`MSE_UNITS`), ``learned`` and ``learned_note``; ``median`` {method: MSE},
        ``improvement_pct`` {"knode-ukf_vs_ukf": 100 (1 - knode/base), ...}, ``flights_scored``,
        ``outside_training_envelope`` (names of the scored flights whose ``envelope`` entry flags them: their
        scores judge the model outside what it was trained on); ``verdicts`` {"knode-ukf_vs_ukf": {"better":
        [names], "worse": [...], "within": [...], "undecided": [...]}, ...}: each scored flight once per
        comparison, by `estimators.headline.flight_verdict` (the 95 % interval of its gain in the mocap gaps);
        ``headline`` (`estimators.headline.headline`: the same verdicts counted, with the median gain);
        ``recommended`` (None when no KNODE ran beside its prior): the estimate learnest recommends per flight
        by the same verdicts (`recommended_model`): ``rule``, ``knode_on`` and ``prior_on`` {"ukf": [names],
        ...}, ``median_gap_rmse_m`` {"ukf": m, ...} of the recommended estimate and ``prior_median_gap_rmse_m``
        of the prior's on the same flights; ``yardstick_definitions`` {yardstick: what it measures, one
        sentence}; ``noise`` {method: "identified" | "paper"}, the noise each method ran with (the flights'
        ``noise`` entries).
    """
    scored = [f for f in flights if not f.get("excluded")]
    methods = sorted({m for f in scored for m in f["mse"]})
    noise: dict[str, str] = {}
    for entry in scored:   # one model, one choice: every scored flight says the same
        noise.update(entry.get("noise") or {})
    median = {m: float(np.median([f["mse"][m] for f in scored if m in f["mse"]])) for m in methods}
    improvement = {}
    for base in ("ukf", "mhe"):
        if base in median and f"knode-{base}" in median:
            improvement[f"knode-{base}_vs_{base}"] = gain_pct(median[base], median[f"knode-{base}"])
    outside = [f["flight"] for f in scored if (f.get("envelope") or {}).get("outside_training_envelope")]
    with_yardsticks = [f for f in scored if f.get("yardsticks")]
    verdicts: dict[str, dict[str, list[str]]] = {}
    for entry in with_yardsticks:
        for key, verdict in flight_verdicts(entry).items():
            verdicts.setdefault(key, {v: [] for v in VERDICTS})[verdict].append(entry["flight"])
    return EvaluationReport.of(
        model=model, **extra, flights=list(flights), median=median, improvement_pct=improvement,
        flights_scored=len(scored), outside_training_envelope=outside, verdicts=verdicts,
        recommended=_recommended_summary(with_yardsticks),
        headline={**headline(scored).to_dict(), "noise": dict(noise)}, yardstick_definitions=dict(MEASURES),
        noise=noise, units=MSE_UNITS, **learned_note(model_meta or {}))
