"""The paper's Crazyflie experiment (Sec. V-C) on canonical Flights: train a KNODE on one flight, run
UKF / MHE / KNODE-UKF / KNODE-MHE on others, score against Savitzky–Golay references."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from learnest.errors import InvalidInput
from learnest.estimators.estimates import FlightEstimates
from learnest.estimators.evaluate import (
    MSE_UNITS,
    evaluate_sequence,
    one_step_innovation_ms,
    prediction_check,
    summarize,
)
from learnest.estimators.mhe import MHE
from learnest.estimators.observers import pretraining_observer
from learnest.estimators.yardsticks import GapPlan, flight_yardsticks, learned_note, onboard_estimate
from learnest.ingest.baseline import centred_window, references
from learnest.ingest.flight import Flight
from learnest.ingest.profile import MASS_TOLERANCE, RATE_TOLERANCE, flight_profile, profile_mismatches
from learnest.models.crazyflie.thrust_gain import with_thrust_gain
from learnest.models.effects import correct_acc_body, world_from_body
from learnest.models.envelope import envelope_report
from learnest.models.inputs import (
    THRUST_GAIN_CALIBRATED,
    THRUST_THROUGH_ATTITUDE,
    calibrates_attitude,
    calibrates_thrust_gain,
    flight_thrust_axis,
    flight_thrust_gain,
    system_inputs,
    thrust_calibration,
    training_meta,
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
from learnest.models.systems import System, make_system
from learnest.models.training import TrainingRecord, TrainingResult, attitude_blind, train_knode, train_knode_pooled

# Systems a model of a real flight may use: the paper's kinematic chain, or the Crazyflie prior driven by
# the motors and the battery (needs those channels in the flight).
FLIGHT_SYSTEMS = ("quadrotor", "crazyflie")
# The measurements the prediction check compares (`estimators.evaluate.prediction_check`): the mocap position,
# which a model must predict through its dynamics.  The accelerometer reads the state a almost directly and its
# innovations are dominated by vibration: on the 16 NanoBench transfer flights (benchmarks/crazyflie_transfer.py)
# the position-innovation ratio is above 1 on both flights the Crazyflie KNODE loses on, the accelerometer's on neither.
PREDICTION_CHANNELS = ("px", "py", "pz")


def system_for(flight: Flight, name: str = "quadrotor") -> System:
    """The named flight system on this flight's grid; noise settings are the system's defaults."""
    if name not in FLIGHT_SYSTEMS:
        raise InvalidInput(f"system {name!r} does not model a flight; choose one of {', '.join(FLIGHT_SYSTEMS)}")
    return make_system(name, dt=flight.dt, n_samples=len(flight.t))


def model_system(model: HybridModel, flight: Flight) -> System:
    """``model``'s system on this flight's grid with the model's own prior parameters: a diagnosis may have
    extended them, and a model trained before the motors' heating has none (`models.crazyflie.motor_heating`)."""
    return replace(system_for(flight, model.system.name), prior_params=dict(model.system.prior_params))


def quadrotor_for(flight: Flight) -> System:
    """The paper's kinematic quadrotor on this flight's grid."""
    return system_for(flight, "quadrotor")


def initial_state(flight: Flight) -> np.ndarray:
    """First state estimate x0, shape (9,): p[0] (m), the mean velocity over the first (up to) 5 steps (m/s),
    a_meas[0] (m/s²)."""
    k = min(5, len(flight.t) - 1)
    velocity = (flight.p[k] - flight.p[0]) / (k * flight.dt)
    return np.concatenate([flight.p[0], velocity, flight.a_meas[0]])


def train_on_flight(flight: Flight, config: TrainingConfig = CRAZYFLIE_TRAINING,
                    progress: Callable[[int, float], None] | None = None,
                    system: str = "quadrotor") -> TrainingResult:
    """Algorithm 1 on one flight with the named prior (`FLIGHT_SYSTEMS`): the KF pre-training observer on
    its measurements, then `train_knode`.  The model records the training flight (name and source sha256)
    in its meta.  ``progress`` is called as ``progress(epoch, mean_training_loss)``.  Raises
    `models.inputs.MissingInputs` when the prior needs inputs the flight lacks."""
    prior = system_for(flight, system)
    y, u = flight.measurements(), system_inputs(flight, prior, thrust_gain=True)
    zeta = pretraining_observer(prior, y, u, prior.dt)
    result = train_knode(prior, zeta, u, prior.dt, config, progress=progress)
    result.model.meta.update(training_meta(prior))   # evaluations check it: older models saw the raw attitude
    result.model.meta.update({"system": prior.name, "training_flight": flight.name,
                              "training_flight_sha256": [s["sha256"] for s in flight.meta.get("sources", [])],
                              "training_profile": flight_profile(flight)})
    return result


# Thrust gains (`models.crazyflie.thrust_gain`, against the prior's map with the battery voltage and the motors' heating
# already in it) of one vehicle's flights lie within 0.987-1.048 on the 29 shared NanoBench flights of CF_01
# (the high one flown by another controller): the battery and the warm motors are explained by the map.  A
# training set whose gains spread more than twice that (max/min above 1 + GAIN_SPREAD) is not one thrust map:
# another vehicle, motors or payload, which one residual cannot learn as one vehicle.
GAIN_SPREAD = 0.12
# By default one flight in VALIDATION_EVERY is held out whole (at least one when there are two or more).
VALIDATION_EVERY = 5


def default_validation(n_flights: int) -> list[int]:
    """Indices of the flights held out by default: round(n / `VALIDATION_EVERY`) of n (at least one when
    n >= 2, none for one flight), spread evenly through the given order and ending with the last, so a
    folder listed family by family has its held-out flights in several families."""
    if n_flights < 2:
        return []
    held = max(1, round(n_flights / VALIDATION_EVERY))
    return sorted({(k + 1) * n_flights // held - 1 for k in range(held)})


def check_one_vehicle(flights: Sequence[Flight], systems: Sequence[System], gains: Sequence[float | None]) -> None:
    """Refuse a training set whose flights are not one vehicle: different prior parameters, different declared
    vehicles or masses (`ingest.profile`), or thrust gains that spread more than `GAIN_SPREAD` (a different
    thrust map).  One residual is one vehicle's; the message names the flights on each side so the user can
    split the set.

    Raises
    ------
    InvalidInput
        Naming the disagreeing flights and what differs.
    """
    first = flights[0]
    for flight, system in zip(flights[1:], systems[1:]):
        if system.name != systems[0].name or system.prior_params != systems[0].prior_params:
            differing = sorted(k for k in {*system.prior_params, *systems[0].prior_params}
                               if system.prior_params.get(k) != systems[0].prior_params.get(k))
            raise InvalidInput(f"{flight.name} and {first.name} have different prior parameters "
                               f"({', '.join(differing) or system.name}): one model is trained on one vehicle; "
                               "train a model per vehicle")

    def groups(key) -> dict:
        by: dict = {}
        for flight in flights:
            value = key(flight)
            if value is not None:
                by.setdefault(value, []).append(flight.name)
        return by

    vehicles = groups(lambda f: (str(f.meta["vehicle"]) if f.meta.get("vehicle") else None))
    if len(vehicles) > 1:
        listed = "; ".join(f"{v}: {', '.join(names)}" for v, names in vehicles.items())
        raise InvalidInput(f"the training flights come from different vehicles ({listed}): one model is trained on "
                           "one vehicle; train a model per vehicle")
    masses = groups(lambda f: f.meta.get("mass_kg"))
    if masses and max(masses) > (1 + MASS_TOLERANCE) * min(masses):
        listed = "; ".join(f"{1000 * m:.1f} g: {', '.join(names)}" for m, names in sorted(masses.items()))
        raise InvalidInput(f"the training flights declare different masses ({listed}): another vehicle or payload; "
                           "train a model per vehicle")
    known = [(g, f.name) for g, f in zip(gains, flights) if g is not None]
    if known:
        low, high = min(known), max(known)
        if high[0] > (1 + GAIN_SPREAD) * low[0]:
            raise InvalidInput(f"the training flights disagree on the thrust map: thrust gain {high[0]:.3f} on "
                               f"{high[1]} against {low[0]:.3f} on {low[1]} (battery and motor heating accounted "
                               f"for; one vehicle's flights lie within {100 * GAIN_SPREAD:.0f} %): another vehicle, "
                               "motors or payload; train a model per vehicle")


def flight_training_data(flight: Flight, system: str) -> tuple[System, np.ndarray, np.ndarray, float | None]:
    """Algorithm 1's data of one flight with the named prior: (its system on the flight's grid, ζ (T, n) of the
    pre-training observer, u (T, p) = `system_inputs(..., thrust_gain=True)`, the flight's thrust gain for a
    prior with a thrust map, else None: split out for `check_one_vehicle`)."""
    prior = system_for(flight, system)
    gain = None
    if prior.name in THRUST_THROUGH_ATTITUDE:
        u = system_inputs(flight, prior)
        gain = flight_thrust_gain(flight, prior, u)
        u = with_thrust_gain(u, gain, prior.prior_params["gamma"])
    else:
        u = system_inputs(flight, prior, thrust_gain=True)
    return prior, pretraining_observer(prior, flight.measurements(), u, prior.dt), u, gain


def pooled_profile(flights: Sequence[Flight]) -> dict:
    """The vehicle and sensor profile (`ingest.profile.flight_profile`) a model trained on ``flights`` records:
    the first flight's, with each sensor rate the median of the flights' when they all lie within
    `ingest.profile.RATE_TOLERANCE` of it, else None (the model saw several rates: none is "another" one),
    and the controller None when the flights name different ones.  An evaluation warns against it as against
    one flight's profile."""
    profiles = [flight_profile(f) for f in flights]
    merged = {**profiles[0], "rates_hz": dict(profiles[0]["rates_hz"])}
    for stream in merged["rates_hz"]:
        rates = [p["rates_hz"].get(stream) for p in profiles]
        if any(r is None for r in rates):
            merged["rates_hz"][stream] = None
            continue
        median = float(np.median(rates))
        merged["rates_hz"][stream] = round(median, 1) if all(abs(r - median) <= RATE_TOLERANCE * median
                                                             for r in rates) else None
    if len({p.get("controller") for p in profiles}) > 1:
        merged["controller"] = None
    return merged


def _flight_lineage(flight: Flight, gain: float | None) -> dict:
    return {"name": flight.name, "sha256": [s["sha256"] for s in flight.meta.get("sources", [])],
            "samples": len(flight.t), "dt": flight.dt, **({"thrust_gain": round(gain, 5)} if gain else {})}


def train_on_flights(flights: Sequence[Flight], config: TrainingConfig = CRAZYFLIE_TRAINING,
                     progress: Callable[[int, float], None] | None = None, system: str = "quadrotor",
                     validate: Sequence[str] | None = None, blind_attitude: bool = True,
                     blind_battery: bool = True) -> TrainingResult:
    """Algorithm 1 on several flights of one vehicle, one KNODE: the pre-training observer on each flight's own
    measurements and inputs (each with its own thrust gain, battery and length), one pooled loss over every
    training flight (`models.training.train_knode_pooled`), whole flights held out for validation.

    One flight (and no ``validate``) is the paper's protocol exactly (`train_on_flight`: time blocks of the
    flight held out).

    Parameters
    ----------
    flights : sequence of Flight
        The flights, distinct names.
    config : TrainingConfig
        Training settings; with several flights ``validation_fraction``/``validation_layout`` are unused.
    progress : callable, optional
        ``progress(epoch, mean_training_loss)`` after every epoch.
    system : {"quadrotor", "crazyflie"}
        The prior (`FLIGHT_SYSTEMS`).
    validate : sequence of str, optional
        Names of the flights held out; default `default_validation` (one in five, at least one of two or more).
    blind_attitude : bool
        Several flights: the residual is also blind to the attitude inputs (`models.training.attitude_blind`; the
        default, why there).  Ignored for one flight, which keeps the paper's protocol and the system's masks.
    blind_battery : bool
        Several flights, with ``blind_attitude``: blind to the battery voltage too (`models.training.BATTERY_INPUTS`;
        the default).

    Returns
    -------
    TrainingResult
        Its model's meta holds ``training_flights`` and ``validation_flights`` (each {"name", "sha256" (the
        source files'), "samples", "dt" (s), "thrust_gain" where the prior has one}), ``learned`` (False when no
        epoch beat the prior on the held-out flights: the model equals its prior), ``training_flight`` and
        ``training_flight_sha256`` (the first training flight's name; every training flight's sha256, so an
        evaluation excludes all of them), ``system`` and ``training_profile`` (`pooled_profile` of the training
        flights); ``residual_blind`` (with several flights: every state and input the residual does not read).

    Raises
    ------
    InvalidInput
        No flight, a name given twice, a ``validate`` name not among the flights, every flight held out, or
        flights of different vehicles (`check_one_vehicle`); `models.inputs.MissingInputs` when the prior needs
        inputs a flight lacks.
    """
    flights = list(flights)
    if not flights:
        raise InvalidInput("training needs at least one flight")
    names = [f.name for f in flights]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise InvalidInput(f"flight(s) given more than once: {', '.join(twice)}")
    if len(flights) == 1 and not validate:
        return _train_on_one(flights[0], config, progress, system)
    if validate:
        unknown = [n for n in validate if n not in names]
        if unknown:
            raise InvalidInput(f"validation flight(s) {', '.join(unknown)} are not among the training set's flights "
                               f"({', '.join(names)})")
        held = [n in set(validate) for n in names]
    else:
        chosen = set(default_validation(len(flights)))
        held = [i in chosen for i in range(len(flights))]
    if all(held):
        raise InvalidInput(f"every flight is held out for validation ({', '.join(names)}): keep one to train on")
    data = [flight_training_data(flight, system) for flight in flights]
    systems = [d[0] for d in data]
    check_one_vehicle(flights, systems, [d[3] for d in data])
    records = [TrainingRecord(f.name, zeta, u, prior.dt) for f, (prior, zeta, u, _) in zip(flights, data)]
    trained = [i for i, h in enumerate(held) if not h]
    prior = attitude_blind(systems[trained[0]], blind_battery) if blind_attitude else systems[trained[0]]
    result = train_knode_pooled(prior, records, held, config, progress=progress)
    result.model.meta["residual_blind"] = list(prior.residual_blind)
    lineage = [_flight_lineage(f, d[3]) for f, d in zip(flights, data)]
    result.model.meta.update(training_meta(prior))
    result.model.meta.update({
        "system": prior.name, "training_flight": names[trained[0]],
        "training_flight_sha256": [sha for i in trained for sha in lineage[i]["sha256"]],
        "training_profile": pooled_profile([flights[i] for i in trained]),
        "training_flights": [lineage[i] for i in trained],
        "validation_flights": [lineage[i] for i, h in enumerate(held) if h],
        "validation": "held-out flights"})
    return result


def _train_on_one(flight: Flight, config, progress, system) -> TrainingResult:
    """`train_on_flights` with one flight and no validation flights: validated on held-out time blocks of it."""
    result = train_on_flight(flight, config, progress=progress, system=system)
    lineage = [_flight_lineage(flight, None)]
    result.model.meta.update({"training_flights": lineage, "validation_flights": [],
                              "validation": "held-out time blocks of the flight"})
    return result


def corrected_flight(flight: Flight, values: dict) -> Flight:
    """The flight with accelerometer effects (bias, scale, delay, misalignment) removed: the measurement
    model a diagnosis repaired, applied to the data."""
    acc_body = correct_acc_body(flight.channels["acc_body"], flight.t, values)
    return Flight(flight.t, flight.p, world_from_body(acc_body, flight.quat), flight.quat,
                  {**flight.channels, "acc_body": acc_body}, dict(flight.meta))


def evaluate_flight(knode: HybridModel, flight: Flight, methods: Sequence[str], horizon: int = MHE_HORIZON,
                    sg_window: int = SG_WINDOW, keep_estimates: bool = False,
                    mhe_cache: dict[tuple, MHE] | None = None,
                    on_stage: Callable[[str], object] | None = None, check_prediction: bool = False,
                    thrust_gain: bool | None = None, gaps: GapPlan | None = None) -> dict:
    """Scores of every method on one flight, against SG references of its mocap position.

    The prior-only rows use the model's own prior (which a diagnosis may have extended), and a model
    that carries measurement effects sees the flight with them corrected; the references always come
    from the original mocap position.  ``thrust_gain`` says whether the prior's thrust is scaled by the
    flight's thrust gain (`models.inputs.system_inputs`); None decides by the model
    (`models.inputs.calibrates_thrust_gain`), the diagnosis passes False.

    Returns
    -------
    dict
        ``results`` {method: `evaluate_sequence`'s entry}; ``reference`` (the SG references) and
        ``estimates`` (a `FlightEstimates` of every method) when ``keep_estimates``, else None;
        ``prediction_check`` (`estimators.evaluate.prediction_check` on the mocap position) when
        ``check_prediction`` and the model is a KNODE, else None.  It reuses the UKF rows' innovations and
        runs the (untimed) UKF of a model whose row was not asked for.  ``yardsticks``
        (`estimators.yardsticks.FlightYardsticks`: mocap gaps, fast reference, the paper's SG score) when
        ``gaps`` is given, else None; ``onboard`` in ``methods`` scores the log's own estimate there.
    """
    system = model_system(knode, flight)
    knode = HybridModel(replace(knode.system, dt=flight.dt), knode.kind, knode.residual, knode.meta)
    prior = HybridModel(system, "prior")
    reference = references(flight, window=sg_window)
    measured = flight
    if knode.meta.get("measurement_effects"):
        measured = corrected_flight(flight, knode.meta["measurement_effects"])
    if thrust_gain is None:
        thrust_gain = calibrates_thrust_gain(knode.meta, knode.kind)
    u = system_inputs(flight, system, thrust_gain=thrust_gain)
    y, x0 = measured.measurements(), initial_state(measured)
    mhe_cache = {} if mhe_cache is None else mhe_cache
    run = [m for m in methods if m != ONBOARD]   # the onboard estimate is read from the log, not run
    results = evaluate_sequence(run, prior, knode, y, u, flight.dt, system.Q, system.R, x0, system.P0, reference,
                                horizon=horizon, keep_estimates=keep_estimates or gaps is not None,
                                mhe_cache=mhe_cache, on_stage=on_stage)
    yardsticks = None
    if gaps is not None:
        onboard = onboard_estimate(flight.channels) if ONBOARD in methods else None
        yardsticks, _ = flight_yardsticks(run, prior, knode, y, u, flight.dt, system.Q, system.R, x0, system.P0,
                                          flight.p, {m: r["estimates"] for m, r in results.items()},
                                          {m: r["mse"] for m, r in results.items()}, gaps, horizon, onboard=onboard,
                                          sg_window_s=centred_window(sg_window) * flight.dt, mhe_cache=mhe_cache,
                                          on_stage=on_stage)
        if not keep_estimates:
            for entry in results.values():
                entry.pop("estimates", None)
    check = None
    if check_prediction and knode.kind == "knode":
        ms = {}
        for method, model in (("ukf", prior), ("knode-ukf", knode)):
            ms[method] = results[method]["innovation_ms"] if method in results else \
                one_step_innovation_ms(model, y, u, flight.dt, system.Q, system.R, x0, system.P0, cache=mhe_cache)
        names = list(system.meas_names)
        check = prediction_check(ms["ukf"], ms["knode-ukf"], [names.index(c) for c in PREDICTION_CHANNELS], names)
    if not keep_estimates:
        return {"results": results, "reference": None, "estimates": None, "prediction_check": check,
                "yardsticks": yardsticks}
    estimates = FlightEstimates(flight.name, flight.t, reference, y, flight.quat,
                                {m: r["estimates"] for m, r in results.items()}, log_start_ns(flight))
    return {"results": results, "reference": reference, "estimates": estimates, "prediction_check": check,
            "yardsticks": yardsticks}


def log_start_ns(flight: Flight) -> int:
    """Time of the flight's t = 0 on its log's own clock, ns (never negative): an MCAP recording's origin
    (``meta["time_origin_ns"]``) plus where the grid started (``t0_source_s``) and the take-off cut
    (``flying_window.start_s``); 0 when the adapter recorded none of them."""
    meta = flight.meta
    seconds = float(meta.get("t0_source_s") or 0.0) + float((meta.get("flying_window") or {}).get("start_s") or 0.0)
    return max(0, int(meta.get("time_origin_ns") or 0) + round(seconds * 1e9))


def flight_envelope(knode: HybridModel, flight: Flight) -> dict | None:
    """How much of ``flight`` lies outside the region the model was trained on (`models.envelope`), or None
    for a model trained before envelopes were stored.

    The flight's states are estimated by the same pre-training observer that made the training data, so
    both sides of the comparison carry the same observer.
    """
    envelope = knode.meta.get("envelope")
    if not envelope:
        return None
    system = model_system(knode, flight)   # as in training: its parameters drive the observer and the heating
    measured = corrected_flight(flight, knode.meta["measurement_effects"]) \
        if knode.meta.get("measurement_effects") else flight
    u = system_inputs(flight, system, thrust_gain=calibrates_thrust_gain(knode.meta, knode.kind))
    return envelope_report(envelope, pretraining_observer(system, measured.measurements(), u, system.dt), u,
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
                     gap_s: float = GAP_S, gap_every_s: float = GAP_EVERY_S) -> dict:
    """The report of `learnest evaluate --json`: per flight, median, improvement %, ``units`` of the numbers.

    Flights that fail the quality checks (unless ``include_bad``) and the model's own training flight are
    listed as excluded, with the reason, and not scored.  Each scored flight's ``envelope`` says how much
    of it lies outside what the model saw in training (`flight_envelope`); such flights are still scored,
    and listed in ``outside_training_envelope``.  Each scored flight's ``prediction_check`` says whether the
    KNODE predicts its mocap position one step ahead worse than the prior does (no ground truth needed: a
    flight where the learned model should not be trusted); such flights are listed in ``knode_predicts_worse``.
    Each scored flight's ``gain_interval_pct`` {"knode-ukf_vs_ukf": [low, high], ...} is the 95 % interval of
    the KNODE's gain over its prior (`estimators.evaluate.gain_interval`; None for a flight too short to tell);
    flights whose interval lies below 0 are listed in ``knode_clearly_worse``.
    Each scored flight's ``warnings`` say how it differs from
    the training flight in vehicle, sensor rates, attitude source, mass or controller
    (`ingest.profile.profile_mismatches`; none for a model that recorded no ``training_profile``).
    A prior that turns thrust into acceleration through the attitude (the Crazyflie's) gets the mocap
    attitude calibrated onto each flight's thrust axis; ``thrust_axis_offset_deg`` [x, y] says by how much;
    its thrust map scaled by the motors' heating where its prior has it (the largest loss over the flight in
    ``heating_thrust_loss_pct``, `models.crazyflie.motor_heating`) and, unless the model was trained before it, by the
    flight's ``thrust_gain`` (`models.crazyflie.thrust_gain`).
    ``progress`` is called with each flight's entry;
    ``on_estimates(index, FlightEstimates)`` with the per-step estimates of each scored flight (index into
    ``flights``), when given; ``on_stage`` with each method's name before it runs and "MHE build (...)"
    before an MHE is built (`estimators.evaluate.evaluate_sequence`).  ``sg_window`` is the Savitzky–Golay
    window of the references, samples.
    Each scored flight's ``yardsticks`` (`estimators.yardsticks`) hold the mocap-gap score (the mocap hidden
    ``gap_s`` s every ``gap_every_s`` s after the first 5 s; a flight too short for one gap says why), the
    fast reference (``onboard`` beside the estimators where ``methods`` name it and the log carries it) and
    the paper's SG score; the report's ``headline`` sums up the gap score over the flights, ``learned`` and
    ``learned_note`` say whether the model learned anything (its ``learned`` flag; None when it has none).
    """
    plan = GapPlan(gap_s, gap_every_s)   # checked before any flight runs
    reports: list[dict] = []
    mhe_cache: dict[tuple, MHE] = {}
    for index, flight in enumerate(flights):
        entry = {"flight": flight.name, "excluded": False, "reason": None, "mse": {}, "groups": {}}
        quality = flight.quality
        if not quality["ok"] and not include_bad:
            entry.update(excluded=True, reason="quality: " + "; ".join(quality["issues"]))
        elif _is_training_flight(knode, flight):
            entry.update(excluded=True, reason="training flight (never scored on its own training data)")
        else:
            out = evaluate_flight(knode, flight, methods, horizon, sg_window=sg_window,
                                  keep_estimates=on_estimates is not None, mhe_cache=mhe_cache, on_stage=on_stage,
                                  check_prediction=True, gaps=plan)
            results = out["results"]
            if on_estimates is not None:
                on_estimates(index, out["estimates"])
            entry["mse"] = {m: r["mse"] for m, r in results.items()}
            entry["groups"] = {m: r["groups"] for m, r in results.items()}
            entry["ms_per_step"] = {m: r["ms_per_step"] for m, r in results.items()}
            entry["gain_interval_pct"] = {f"{m}_vs_{m.removeprefix('knode-')}": r["gain_interval_pct"]
                                          for m, r in results.items() if "gain_interval_pct" in r}
            entry["envelope"] = flight_envelope(knode, flight)
            entry["prediction_check"] = out["prediction_check"]
            entry["yardsticks"] = out["yardsticks"].to_dict()
            if knode.system.name in THRUST_THROUGH_ATTITUDE:   # the calibration the prior's attitude input got
                entry["thrust_axis_offset_deg"] = [round(float(np.degrees(d)), 3) for d in flight_thrust_axis(flight)]
                # and what its prior's thrust carried: the motors' heating, the flight's thrust gain
                thrust = thrust_calibration(flight, model_system(knode, flight),
                                            calibrates_thrust_gain(knode.meta, knode.kind))
                entry.update({name: round(value, 5) for name, value in thrust.items()})
        # a flight from another vehicle, sensor rate or attitude source: scored, with a warning
        warnings = profile_mismatches(knode.meta.get("training_profile"), flight_profile(flight))
        if not entry["excluded"] and _trained_on_other_attitude(knode):
            trained_on = knode.meta.get("attitude_input") or "the mocap attitude as logged"
            warnings.append(f"the model was trained on another attitude input ({trained_on}) than evaluations now "
                            f"use ({THRUST_GAIN_CALIBRATED}): retrain it for consistent inputs")
        entry["warnings"] = warnings
        reports.append(entry)
        if progress:
            progress(entry)
    return {"model": knode.meta.get("name"), "system": knode.system.name, "flights": reports, **summarize(reports),
            "units": MSE_UNITS, **learned_note(knode.meta)}
