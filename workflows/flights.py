"""The paper's Crazyflie experiment (Sec. V-C) on canonical Flights: train a KNODE on one flight, run
UKF / MHE / KNODE-UKF / KNODE-MHE on others, score against Savitzky–Golay references."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial

import numpy as np

from learnest.estimators.algorithm1 import Algorithm1, TrainingResult
from learnest.estimators.estimates import FlightEstimates
from learnest.estimators.evaluate import (
    evaluate_sequence,
    one_step_innovation_ms,
    prediction_check,
    summarize,
)
from learnest.estimators.evaluation_report import EvaluationReport, FlightScore
from learnest.estimators.evaluation_settings import EvaluationSettings, Noise
from learnest.estimators.group_training import GROUP_BY, StageCallback, train_flights
from learnest.estimators.headline import flight_verdicts
from learnest.estimators.mhe import MHE
from learnest.estimators.observers import pretraining_observer
from learnest.estimators.prepared import PreparedFlight, prepare
from learnest.estimators.yardsticks import GapPlan, flight_yardsticks, onboard_estimate
from learnest.ingest.baseline import centred_window, references
from learnest.ingest.flight import Flight
from learnest.ingest.profile import flight_profile, profile_mismatches
from learnest.models.envelope import envelope_report
from learnest.models.inputs import (
    THRUST_GAIN_CALIBRATED,
    THRUST_THROUGH_ATTITUDE,
    calibrates_attitude,
    flight_thrust_axis,
    thrust_calibration,
)
from learnest.models.knode import HybridModel
from learnest.models.presets import (
    CRAZYFLIE_TRAINING,
    GAP_EVERY_S,
    GAP_S,
    MHE_HORIZON,
    ONBOARD,
    SG_WINDOW,
    TrainingConfig,
)

# The measurements the prediction check compares (`estimators.evaluate.prediction_check`): the mocap position,
# which a model must predict through its dynamics.  The accelerometer reads the state a almost directly and its
# innovations are dominated by vibration, so they cannot show a model that predicts worse; the position's can
# (docs/results/transfer.md, "The one-step check, as measured here").
PREDICTION_CHANNELS = ("px", "py", "pz")


def train_on_flight(flight: Flight, config: TrainingConfig = CRAZYFLIE_TRAINING,
                    progress: Callable[[int, float], None] | None = None,
                    system: str = "quadrotor") -> TrainingResult:
    """The paper's Algorithm 1 on one flight (`estimators.algorithm1.Algorithm1.fit_flights` with the filter
    observer: time blocks of the flight held out)."""
    return Algorithm1(config=config).fit_flights([flight], system, progress=progress)


def train_on_flights(flights: Sequence[Flight], config: TrainingConfig = CRAZYFLIE_TRAINING,
                     progress: Callable[[int, float], None] | None = None, system: str = "quadrotor",
                     validate: Sequence[str] | None = None, blind_attitude: bool = True,
                     blind_battery: bool = True, group_by: str = GROUP_BY,
                     on_stage: StageCallback | None = None, noise: str = "paper") -> TrainingResult:
    """Algorithm 1 on flights of one vehicle with the paper's filter observer, the residual's scale chosen on
    held-out groups of them (``group_by``: by trajectory family by default, ``"none"`` for the whole residual;
    `estimators.group_training.train_flights`: parameters, meta and errors there and in
    `estimators.algorithm1.Algorithm1.fit_flights`)."""
    return train_flights(flights, system, config, group_by, validate, progress, on_stage, noise=noise,
                         blind_attitude=blind_attitude, blind_battery=blind_battery)


def evaluate_flight(knode: HybridModel, flight: Flight, methods: Sequence[str], horizon: int = MHE_HORIZON,
                    sg_window: int = SG_WINDOW, keep_estimates: bool = False,
                    mhe_cache: dict[tuple, MHE] | None = None,
                    on_stage: Callable[[str], object] | None = None, check_prediction: bool = False,
                    thrust_gain: bool | None = None, gaps: GapPlan | None = None) -> dict:
    """`evaluate_prepared` of ``knode`` on ``flight`` (`estimators.prepared.prepare` with ``thrust_gain``: None
    decides by the model, the diagnosis passes False)."""
    return evaluate_prepared(prepare(knode, flight, thrust_gain), methods, horizon, sg_window, keep_estimates,
                             mhe_cache, on_stage, check_prediction, gaps)


def evaluate_prepared(prepared: PreparedFlight, methods: Sequence[str], horizon: int = MHE_HORIZON,
                      sg_window: int = SG_WINDOW, keep_estimates: bool = False,
                      mhe_cache: dict[tuple, MHE] | None = None,
                      on_stage: Callable[[str], object] | None = None, check_prediction: bool = False,
                      gaps: GapPlan | None = None) -> dict:
    """Scores of every method on one prepared flight, against SG references of its mocap position.

    The prior-only rows use the model's own prior (which a diagnosis may have extended), and a model
    that carries measurement effects sees the flight with them corrected (`estimators.prepared.prepare`); the
    references always come from the original mocap position.

    Returns
    -------
    dict
        ``results`` {method: `evaluate_sequence`'s entry}; ``reference`` (the SG references) and
        ``estimates`` (a `FlightEstimates` of every method) when ``keep_estimates``, else None;
        ``prediction_check`` (`flight_prediction_check`) when ``check_prediction`` and the model is a KNODE,
        else None.  ``yardsticks`` (`estimators.yardsticks.FlightYardsticks`: mocap gaps, fast reference, the
        paper's SG score) when ``gaps`` is given, else None; ``onboard`` in ``methods`` scores the log's own
        estimate there.  ``gap_estimates`` {method: (T, n)} of the gap-masked runs when ``gaps`` and
        ``keep_estimates`` (empty when no gap fits), else None: what compares two models on the same gaps.
    """
    flight, knode, prior = prepared.flight, prepared.params, prepared.prior_params
    y, u = prepared.y, prepared.u
    reference = references(flight, window=sg_window)
    mhe_cache = {} if mhe_cache is None else mhe_cache
    run = [m for m in methods if m != ONBOARD]   # the onboard estimate is read from the log, not run
    results = evaluate_sequence(run, prior, knode, y, u, reference,
                                horizon=horizon, keep_estimates=keep_estimates or gaps is not None,
                                mhe_cache=mhe_cache, on_stage=on_stage)
    yardsticks, gapped = None, None
    if gaps is not None:
        onboard = onboard_estimate(flight.channels) if ONBOARD in methods else None
        yardsticks, gapped = flight_yardsticks(run, prior, knode, y, u, flight.p,
                                               {m: r["estimates"] for m, r in results.items()},
                                               {m: r["mse"] for m, r in results.items()}, gaps, horizon,
                                               onboard=onboard, sg_window_s=centred_window(sg_window) * flight.dt,
                                               mhe_cache=mhe_cache, on_stage=on_stage)
        if not keep_estimates:
            for entry in results.values():
                entry.pop("estimates", None)
    check = flight_prediction_check(prepared, results, mhe_cache) \
        if check_prediction and prepared.model.kind == "knode" else None
    if not keep_estimates:
        return {"results": results, "reference": None, "estimates": None, "prediction_check": check,
                "yardsticks": yardsticks, "gap_estimates": None}
    estimates = FlightEstimates(flight.name, flight.t, reference, y, flight.quat,
                                {m: r["estimates"] for m, r in results.items()}, log_start_ns(flight))
    return {"results": results, "reference": reference, "estimates": estimates, "prediction_check": check,
            "yardsticks": yardsticks, "gap_estimates": gapped}


def flight_prediction_check(prepared: PreparedFlight, results: dict, cache: dict | None = None) -> dict:
    """`estimators.evaluate.prediction_check` of a KNODE on the mocap position (`PREDICTION_CHANNELS`) of one
    prepared flight: reuses the UKF rows' innovations in ``results`` (`evaluate_sequence`'s) and runs the
    (untimed) UKF of a model whose row was not asked for."""
    ms = {}
    for method, params in (("ukf", prepared.prior_params), ("knode-ukf", prepared.params)):
        ms[method] = results[method]["innovation_ms"] if method in results else \
            one_step_innovation_ms(params, prepared.y, prepared.u, cache=cache)
    names = list(prepared.system.meas_names)
    return prediction_check(ms["ukf"], ms["knode-ukf"], [names.index(c) for c in PREDICTION_CHANNELS], names)


def log_start_ns(flight: Flight) -> int:
    """Time of the flight's t = 0 on its log's own clock, ns (never negative): an MCAP recording's origin
    (``meta["time_origin_ns"]``) plus where the grid started (``t0_source_s``) and the take-off cut
    (``flying_window.start_s``); 0 when the adapter recorded none of them."""
    meta = flight.meta
    seconds = float(meta.get("t0_source_s") or 0.0) + float((meta.get("flying_window") or {}).get("start_s") or 0.0)
    return max(0, int(meta.get("time_origin_ns") or 0) + round(seconds * 1e9))


def flight_envelope(prepared: PreparedFlight) -> dict | None:
    """How much of the prepared flight lies outside the region its model was trained on (`models.envelope`), or
    None for a model trained before envelopes were stored.

    The flight's states are estimated by the same pre-training observer that made the training data, so
    both sides of the comparison carry the same observer (on the model's system and corrected measurements, with
    its inputs, as in training).
    """
    knode, system = prepared.model, prepared.system
    envelope = knode.meta.get("envelope")
    if not envelope:
        return None
    return envelope_report(envelope, pretraining_observer(system, prepared.y, prepared.u, system.dt), prepared.u,
                           residual=knode.residual)


def _is_training_flight(knode: HybridModel, flight: Flight) -> bool:
    """By content (sha256 of the source files) when the model recorded it, else by name; a model trained on
    several flights excludes every one of them."""
    trained_on = set(knode.meta.get("training_flight_sha256") or [])
    sources = {s.get("sha256") for s in flight.meta.get("sources", [])}
    names = {knode.meta.get("training_flight")} | {f.get("name") for f in knode.meta.get("training_flights") or []}
    return bool(trained_on & sources) or flight.name in names


def _trained_on_other_attitude(knode: HybridModel) -> bool:
    """A KNODE of a thrust-through-attitude prior trained on an attitude input evaluations no longer make:
    before the thrust-axis calibration (the raw mocap attitude) or before the heading was removed.  One
    trained before the per-flight thrust gain is fed its own inputs (`calibrates_thrust_gain`)."""
    return (knode.kind == "knode" and knode.system.name in THRUST_THROUGH_ATTITUDE
            and not calibrates_attitude(knode.meta))


def evaluate_flights(knode: HybridModel, flights: list[Flight], methods: Sequence[str], include_bad: bool = False,
                     horizon: int = MHE_HORIZON, progress: Callable[[dict], None] | None = None,
                     on_estimates: Callable[[int, FlightEstimates], None] | None = None,
                     on_stage: Callable[[str], object] | None = None, sg_window: int = SG_WINDOW,
                     gap_s: float = GAP_S, gap_every_s: float = GAP_EVERY_S, noise: Noise = "identified") -> dict:
    """`score_flights` with its settings given one by one (`EvaluationSettings`: checked before any flight runs),
    the report as its JSON: the dict of `learnest evaluate --json`.  ``progress`` is called with each flight's
    entry as a dict."""
    settings = EvaluationSettings(tuple(methods), horizon, include_bad, sg_window, gap_s, gap_every_s, noise)
    told = None if progress is None else (lambda score: progress(score.to_dict()))
    return score_flights(knode, flights, settings, progress=told, on_estimates=on_estimates,
                         on_stage=on_stage).to_dict()


def score_flights(knode: HybridModel, flights: Sequence[Flight], settings: EvaluationSettings, *,
                  progress: Callable[[FlightScore], None] | None = None,
                  on_estimates: Callable[[int, FlightEstimates], None] | None = None,
                  on_stage: Callable[[str], object] | None = None) -> EvaluationReport:
    """The evaluation of ``knode`` on ``flights``: per flight, median, improvement %, ``units`` of the numbers.

    Flights that fail the quality checks (unless ``settings.include_bad``) and the model's own training flight
    are listed as excluded, with the reason, and not scored.  Each scored flight's ``envelope`` says how much
    of it lies outside what the model saw in training (`flight_envelope`); such flights are still scored,
    and listed in ``outside_training_envelope``.  Each scored flight's ``verdict``
    (`estimators.headline.flight_verdict`) is the one measure the headline counts and the recommended estimate
    follows; ``one_step_innovation_ratio`` (`estimators.evaluate.prediction_check`) a diagnostic beside it;
    ``gain_interval_pct`` the 95 % intervals of the KNODE's gains on the paper's score
    (`estimators.metrics.gain_interval`).  Each scored flight's ``warnings`` say how it differs from the
    training flight in vehicle, sensor rates, attitude source, mass or controller
    (`ingest.profile.profile_mismatches`; none for a model that recorded no ``training_profile``).
    A prior that turns thrust into acceleration through the attitude (the Crazyflie's) gets the mocap
    attitude calibrated onto each flight's thrust axis; ``thrust_axis_offset_deg`` [x, y] says by how much;
    its thrust map scaled by the motors' heating where its prior has it (the largest loss over the flight in
    ``heating_thrust_loss_pct``, `models.crazyflie.motor_heating`) and, unless the model was trained before it, by
    the flight's ``thrust_gain`` (`models.crazyflie.thrust_gain`).

    Parameters
    ----------
    knode : HybridModel
        The model evaluated (its prior runs the "ukf"/"mhe" rows).
    flights : sequence of Flight
        Each gets an entry, in order.
    settings : EvaluationSettings
        The methods, MHE horizon, SG window of the references, the gaps (each scored flight's ``yardsticks``
        hold the mocap-gap score, the mocap hidden ``gap_s`` s every ``gap_every_s`` s after the first 5 s, a
        flight too short for one gap saying why; the fast reference, ``onboard`` beside the estimators where
        the methods name it and the log carries it; the paper's SG score) and the noise of both models
        (`estimators.prepared.prepare`; each scored flight's ``noise`` and the report's say which noise each
        method ran with).
    progress : callable, optional
        Called with each flight's `FlightScore` as it is done.
    on_estimates : callable, optional
        ``on_estimates(index, FlightEstimates)`` with the per-step estimates of each scored flight (index into
        ``flights``).
    on_stage : callable, optional
        Called with each method's name before it runs and "MHE build (...)" before an MHE is built
        (`estimators.evaluate.evaluate_sequence`).

    Returns
    -------
    EvaluationReport
        Built by `estimators.evaluate.summarize`; its ``headline`` sums up the gap score over the flights,
        ``learned`` and ``learned_note`` say whether the model learned anything (None when it does not say).
    """
    scores: list[FlightScore] = []
    mhe_cache: dict[tuple, MHE] = {}
    for index, flight in enumerate(flights):
        scores.append(_flight_score(knode, flight, settings, mhe_cache,
                                    None if on_estimates is None else partial(on_estimates, index),
                                    on_stage))
        if progress:
            progress(scores[-1])
    return summarize(scores, model=knode.meta.get("name"), model_meta=knode.meta, system=knode.system.name)


def _flight_score(knode: HybridModel, flight: Flight, settings: EvaluationSettings, mhe_cache: dict,
                  on_estimates: Callable[[FlightEstimates], None] | None,
                  on_stage: Callable[[str], object] | None) -> FlightScore:
    """One flight's `FlightScore` (`score_flights`): excluded with the reason, or scored."""
    values: dict = {"flight": flight.name, "excluded": False, "reason": None, "mse": {}, "groups": {}}
    if not flight.quality["ok"] and not settings.include_bad:
        values.update(excluded=True, reason="quality: " + "; ".join(flight.quality["issues"]))
    elif _is_training_flight(knode, flight):
        values.update(excluded=True, reason="training flight (never scored on its own training data)")
    else:
        values.update(_scored(knode, flight, settings, mhe_cache, on_estimates, on_stage))
    # a flight from another vehicle, sensor rate or attitude source: scored, with a warning
    warnings = profile_mismatches(knode.meta.get("training_profile"), flight_profile(flight))
    if not values["excluded"] and _trained_on_other_attitude(knode):
        trained_on = knode.meta.get("attitude_input") or "the mocap attitude as logged"
        warnings.append(f"the model was trained on another attitude input ({trained_on}) than evaluations now "
                        f"use ({THRUST_GAIN_CALIBRATED}): retrain it for consistent inputs")
    return FlightScore.of(**values, warnings=warnings)


def _scored(knode: HybridModel, flight: Flight, settings: EvaluationSettings, mhe_cache: dict,
            on_estimates: Callable[[FlightEstimates], None] | None, on_stage: Callable[[str], object] | None) -> dict:
    """The values of a scored flight's `FlightScore`: every method's scores, the yardsticks on the settings'
    gaps, the verdicts and what the prior's inputs were calibrated by."""
    prepared = prepare(knode, flight, noise=settings.noise)
    out = evaluate_prepared(prepared, settings.methods, settings.horizon, sg_window=settings.sg_window,
                            keep_estimates=on_estimates is not None, mhe_cache=mhe_cache, on_stage=on_stage,
                            check_prediction=True, gaps=settings.gaps)
    results = out["results"]
    if on_estimates is not None:
        on_estimates(out["estimates"])
    values: dict = {key: {m: r[key] for m, r in results.items()} for key in ("mse", "groups", "ms_per_step")}
    values["noise"] = {m: prepared.noise["knode" if m[:6] == "knode-" else "prior"] for m in results}
    values["gain_interval_pct"] = {f"{m}_vs_{m.removeprefix('knode-')}": r["gain_interval_pct"]
                                   for m, r in results.items() if "gain_interval_pct" in r}
    values["envelope"] = flight_envelope(prepared)
    if out["prediction_check"] is not None:   # a diagnostic number; the verdict is the gaps' (below)
        values["one_step_innovation_ratio"] = out["prediction_check"]["innovation_ratio"]
    values["yardsticks"] = out["yardsticks"].to_dict()
    values["verdict"] = flight_verdicts(values)
    if knode.system.name in THRUST_THROUGH_ATTITUDE:   # the calibration the prior's attitude input got
        values["thrust_axis_offset_deg"] = [round(float(np.degrees(d)), 3) for d in flight_thrust_axis(flight)]
        # and what its prior's thrust carried: the motors' heating, the flight's thrust gain
        thrust = thrust_calibration(flight, prepared.system, prepared.thrust_gain)
        values.update({name: round(value, 5) for name, value in thrust.items()})
    return values
