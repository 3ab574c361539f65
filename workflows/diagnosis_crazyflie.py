"""The diagnosis of Crazyflie flights with the input-driven prior: one channel, the body-frame specific
force the accelerometer reads against what motors (or rotor speed, or the thrust command), battery and
mocap predict (`models.crazyflie.crazyflie_residual`), traces the physical effects and the accelerometer's together."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from learnest.errors import InvalidInput
from learnest.estimators.algorithm1 import Algorithm1
from learnest.estimators.flight_training import flight_inputs
from learnest.ingest.flight import Flight
from learnest.ingest.profile import flight_profile
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.crazyflie_residual import CRAZYFLIE_MIN_CV_GAIN, crazyflie_problem, specific_force_rmse
from learnest.models.crazyflie.identify import LOWPASS_HZ
from learnest.models.diagnosis import select_effects
from learnest.models.inputs import (
    CHANNEL_SOURCES,
    SOURCE_CHANNELS,
    MissingInputs,
    flight_thrust_source,
    training_meta,
)
from learnest.models.knode import HybridModel
from learnest.models.presets import CRAZYFLIE_TRAINING

from .diagnosis_identifiability import map_shape_check, thrust_map_fit, tie_words
from .diagnosis_problems import (
    REPAIR_GAPS,
    _channel,
    _split_for_fitting,
    repair_scores,
    repair_verdict,
    repair_yardsticks,
    residual_series,
    tuned_alike,
)
from .diagnosis_stages import DiagnosisStages, StageCallback
from .flights import evaluate_flight
from .reports import DiagnosisEffect, DiagnosisFlight, DiagnosisReport, RepairVerdict


# -- Crazyflie flights, input-driven prior -------------------------------------------------------------
def _crazyflie_model(flight: Flight, params: dict, train: bool, config, stages: DiagnosisStages | None = None,
                     part: str = "before") -> HybridModel:
    """The Crazyflie prior with ``params`` on ``flight``'s grid; with ``train``, a KNODE trained on top
    (its observer and epochs reported to ``stages`` as ``part``: "before", the prior, or "after", the repaired)."""
    # without the thrust gain: it would absorb the thrust and payload effects the diagnosis looks for
    system, u, _ = flight_inputs(flight, "crazyflie", params, thrust_gain=False)
    if not train:
        return HybridModel(system, "prior")
    stages = stages or DiagnosisStages(None, {})
    what = "the prior" if part == "before" else "the repaired prior"
    stages.report(part, f"pre-training observer ({flight.name}, for {what})")
    model = Algorithm1(config=config).fit(system, flight.measurements(), u, system.dt,
                                          progress=stages.epochs(part, what, config.epochs)).model
    model.meta.update({"system": "crazyflie", "training_flight": flight.name,
                       "training_flight_sha256": [s["sha256"] for s in flight.meta.get("sources", [])],
                       "training_profile": flight_profile(flight), **training_meta(system, thrust_gain=False)})
    return model


def crazyflie_prior_for(flights: list[Flight], knode: HybridModel | None = None, mass_kg: float | None = None,
                        prior: dict | None = None) -> tuple[dict, str, float | None]:
    """(prior parameters, thrust source, declared mass in kg or None) of a Crazyflie diagnosis.

    The thrust source is the prior's when a model or ``prior`` is given, else the first of "pwm", "rpm",
    "thrust_n" every flight carries (`models.inputs.flight_thrust_source`).  The declared mass is
    ``mass_kg``, else the flights' ``meta["mass_kg"]`` (crazyswarm2's info*.yaml) when they all agree.
    With thrust in N or rotor speed the declared mass is the prior's m_kg (`models.crazyflie.prior_for`).

    Raises
    ------
    models.inputs.MissingInputs
        If some flight carries no thrust source, or not the model's.
    InvalidInput
        If ``mass_kg`` is not a plausible Crazyflie mass.
    """
    if mass_kg is not None and not cf.BOUNDS["m_kg"][0] <= mass_kg <= cf.BOUNDS["m_kg"][1]:
        raise InvalidInput(f"--mass-kg {mass_kg:g}: a Crazyflie weighs between {cf.BOUNDS['m_kg'][0]:g} and "
                           f"{cf.BOUNDS['m_kg'][1]:g} kg")
    declared = mass_kg
    if declared is None:
        masses = {f.meta.get("mass_kg") for f in flights}
        if len(masses) == 1 and None not in masses:
            declared = float(next(m for m in masses if m is not None))
    if prior is None and knode is not None:
        prior = knode.system.prior_params
    if prior is not None:
        prior = dict(prior)
        source = cf.thrust_source_of(prior)
        if declared is not None and source != "pwm" and mass_kg is not None:
            prior["m_kg"] = float(mass_kg)
        return prior, source, declared
    sources = [flight_thrust_source(f) for f in flights]
    for source in ("pwm", "rpm", "thrust_n"):
        if all(source == s or (s is not None and _carries(f, source)) for f, s in zip(flights, sources)):
            return cf.prior_for(source, declared), source, declared
    lacking = next(f for f, s in zip(flights, sources) if s is None) if None in sources else flights[0]
    raise MissingInputs(f"{lacking.name}: the 'crazyflie' prior needs the thrust from the log, and the flights "
                        f"do not share one source ({'; '.join(CHANNEL_SOURCES[c] for c in ALL_THRUST_CHANNELS)}). "
                        "The kinematic prior (system 'quadrotor') works without them.")


ALL_THRUST_CHANNELS = ("motors", "vbat", "rotor_speed", "thrust_si")


def _carries(flight: Flight, source: str) -> bool:
    return all(name in flight.channels for name in SOURCE_CHANNELS[source])


# the thrust gain against the prior's map beyond which the vehicle is not the one the map describes
FITS_PRIOR_GAIN = (0.7, 1.4)


def _name_thrust_scale(effects: list[dict], candidates: list[dict], prior: dict, source: str,
                       declared: float | None) -> tuple[list[dict], dict]:
    """The mass effect under its true name, and whether the vehicle fits the prior's thrust map.

    What the data measure is thrust over mass.  With thrust in N (or rotor speed on Förster's map) and a mass
    in the prior, or with a declared mass, a change is a mass in kg: ``mass`` {m_kg}, scaled onto the declared
    mass for the PWM source (m = m_declared · m_fit / m_prior).  Otherwise it is a thrust gain against the
    prior's map, ``thrust_gain`` {gain = m_prior / m_fit} (1 = the map as it is), dimensionless.

    A mass in kg from thrust in N (or rotor speed) holds only if the command is the thrust made: position and
    accelerometer measure the thrust made over the mass, so a mass far from the declared one (or the prior's,
    outside `FITS_PRIOR_GAIN`) is no mass but a scale of the command.  It is then reported as ``thrust_gain``
    {gain = thrust made / thrust commanded, against that mass}, with ``implied_mass_kg``, the mass the data
    would give were the command exact, and a note saying why it is not claimed as one.
    """
    m_prior = float(prior["m_kg"])
    as_mass = source == "thrust_n" or declared is not None
    implied = None
    if as_mass and source != "pwm":
        m_fitted = next((e["params"]["m_kg"] for e in effects if e["id"] == "mass"), None)
        if m_fitted and not FITS_PRIOR_GAIN[0] <= m_prior / m_fitted <= FITS_PRIOR_GAIN[1]:
            implied, as_mass = float(m_fitted), False
    scale = (declared / m_prior) if (as_mass and source == "pwm" and declared) else 1.0

    def convert(value: float) -> float:
        return value * scale if as_mass else m_prior / value

    out = [e if e["id"] != "mass" else _mass_effect_named(dict(e), as_mass, convert, scale, declared, m_prior,
                                                          implied, source)
           for e in effects]
    return out, _vehicle_fits_prior(effects, candidates, m_prior, source, declared)


def _mass_effect_named(e: dict, as_mass: bool, convert, scale: float, declared: float | None, m_prior: float,
                      implied: float | None, source: str) -> dict:
    """One fitted mass effect under its true name (`_name_thrust_scale`): a mass in kg, or a thrust gain."""
    value = e["params"]["m_kg"]
    interval = e["ci95"].get("m_kg")
    if as_mass:
        e["params"] = {"m_kg": convert(value)}
        e["nominal"] = {"m_kg": convert(m_prior)}
        e["ci95"] = {"m_kg": [convert(interval[0]), convert(interval[1])]} if interval else {}
        e["equation"] = f"mass: m_kg = {convert(value):.4g} kg"
        if scale != 1.0:
            e["note"] = (f"the declared mass {declared:g} kg times the change the data see against the "
                         f"prior's thrust map ({value / m_prior:.3f})")
    else:
        keys = ("identified", "at_bound", "claimed", "determined", "explained_by_param", "held_nominal",
                "units", "bounds", "undetermined")
        e.update({"id": "thrust_gain", "params": {"gain": convert(value)}, "nominal": {"gain": 1.0},
                  "ci95": {"gain": sorted([convert(interval[0]), convert(interval[1])])} if interval else {},
                  "equation": f"thrust_gain: gain = {convert(value):.4g} (thrust against the prior's map; "
                              "a payload or another vehicle's motors)",
                  "note": "no mass is declared and the thrust is not known in N: only thrust over mass is "
                          "measured, reported as a gain on the prior's thrust map"})
        if implied is not None:
            e.update(_command_scale_text(convert(value), implied, interval, m_prior, source, declared))
        for key in keys:
            if key in e and isinstance(e[key], dict) and "m_kg" in e[key]:
                v = e[key].pop("m_kg")
                if key == "units":
                    v = ""
                elif key == "bounds":
                    v = sorted([convert(v[1]), convert(v[0])])
                e[key]["gain"] = v
    return e


def _vehicle_fits_prior(effects: list[dict], candidates: list[dict], m_prior: float, source: str,
                        declared: float | None) -> dict:
    """``vehicle_fits_prior``: the thrust made against the prior's map (or the declared mass), whether it is
    within `FITS_PRIOR_GAIN`, and what to do when it is not."""
    alone = next((c for c in candidates if c["id"] == "mass"), None)
    fitted = next((e for e in effects if e["id"] == "mass"), None)
    m_fit = (fitted or alone or {"params": {"m_kg": m_prior}})["params"]["m_kg"]
    m_ref = declared if (declared is not None and source != "pwm") else m_prior
    gain = float(m_ref / m_fit) if m_fit else 1.0
    ok = bool(FITS_PRIOR_GAIN[0] <= gain <= FITS_PRIOR_GAIN[1])
    what = {"pwm": "motor PWM and battery voltage", "rpm": "rotor speed", "thrust_n": "commanded thrust in N"}[source]
    if ok:
        message = (f"the vehicle's thrust is {gain:.2f}× what the prior's map predicts from the {what}: within "
                   f"×{FITS_PRIOR_GAIN[0]:g}–×{FITS_PRIOR_GAIN[1]:g}, the prior's map fits this vehicle")
    else:
        message = (f"the vehicle's thrust is {gain:.2f}× what the prior's map predicts from the {what} "
                   f"(outside ×{FITS_PRIOR_GAIN[0]:g}–×{FITS_PRIOR_GAIN[1]:g}): this vehicle does not match the "
                   "prior's thrust map (other motors or propellers, a brushless vehicle, a controller whose thrust "
                   "command is not the thrust made); effects fitted against this map describe the mismatch, not "
                   "the vehicle.  Fit a map for it: `learnest thrust-map --fit FLIGHTS --score FLIGHTS`, or give "
                   "a bench calibration, `learnest thrust-map --bench CSV` (thrust in N against PWM or rpm)")
        if source == "thrust_n":
            message += "; " + _command_scale_sentence(gain, m_ref, declared, "commanded thrust") \
                + "; the controller's integrator makes up the difference"
    return {"ok": ok, "thrust_gain": round(gain, 4), "message": message}


def _command_scale_text(gain: float, implied: float, interval, m_ref: float, source: str,
                        declared: float | None) -> dict:
    """The entries of a thrust-in-N (or rotor-speed) mass effect too far from ``m_ref`` (kg) to be a mass:
    ``gain`` the thrust made over the commanded, ``implied`` (kg) the mass were the command exact."""
    whose = "declared" if declared is not None else "prior's"
    what = {"thrust_n": "commanded thrust", "rpm": "thrust Förster's map gives the rotor speed"}.get(source, "thrust")
    return {
        "implied_mass_kg": implied,
        "implied_mass_ci95": list(interval) if interval else None,
        "equation": f"thrust_gain: gain = {gain:.4g} (the thrust made over the {what}, with the {whose} mass "
                    f"{m_ref * 1e3:.3g} g)",
        "note": (f"were the {what} the thrust made, the mass would be {implied * 1e3:.3g} g, ×{implied / m_ref:.2f} "
                 f"the {whose} {m_ref * 1e3:.3g} g: not a plausible mass for this vehicle.  "
                 + _sentence_start(_command_scale_sentence(gain, m_ref, declared, what)) + ".  No mass is claimed")}


def _sentence_start(text: str) -> str:
    """``text`` with its first letter capitalised (the rest as it is)."""
    return text[:1].upper() + text[1:]


def _command_scale_sentence(gain: float, m_ref: float, declared: float | None, what: str) -> str:
    """Why a thrust command's scale is reported and not a mass: what the data measure, and the scale with the
    declared (or the prior's) mass ``m_ref`` (kg)."""
    whose = "declared" if declared is not None else "prior's"
    return (f"position and accelerometer measure only the thrust made over the mass, so a mass and a scale of the "
            f"{what} cannot be told apart from these logs; with the {whose} mass {m_ref * 1e3:.3g} g, the thrust "
            f"made is ×{gain:.2f} of the {what} (the firmware's thrust map {'over' if gain < 1 else 'under'}-promises)")


# the parts of a Crazyflie-prior diagnosis and their rough relative costs (a KNODE training dominates)
CRAZYFLIE_PLAN = {"effects": 1.5, "before": 3.0, "after": 3.0, "scoring": 2.0}


def crazyflie_report(flights: list[Flight], knode: HybridModel | None = None, methods: Sequence[str] = ("ukf",),
                     epochs: int = CRAZYFLIE_TRAINING.epochs, train_repaired: bool = False,
                     prior: dict | None = None, mass_kg: float | None = None,
                     on_stage: StageCallback | None = None) -> tuple[DiagnosisReport, HybridModel]:
    """Trace what the input-driven Crazyflie prior lacks on real flights; score before and after on
    flights not used to fit.

    The thrust comes from what the flights carry (`crazyflie_prior_for`): motor PWM and battery voltage,
    rotor speed, or the controller's thrust in N.  The residual is the body-frame specific force
    (`models.crazyflie.crazyflie_residual.crazyflie_problem`, both sides low-passed at 5 Hz); effects are selected on
    the fitting flights (the first half, rounded up: `diagnosis_problems._split_for_fitting`) and scored on
    the others: the RMSE of the specific force predicted from the inputs alone (``specific_force_rmse``, m/s²)
    and, for each of ``methods``, the
    estimator's MSE with the prior before and after (KNODE methods train a KNODE on the first fitting
    flight, ``epochs`` epochs, on each prior).  Only identified parameters repair the prior
    (`models.diagnosis.select_effects`).  ``prior`` holds the prior's parameters; by default ``knode``'s
    own, else the thrust source's.  ``mass_kg`` is a declared mass (kg), else the flights' own.
    ``on_stage(name, fraction)``: the named stages as they start (`diagnosis.diagnosis_report`).

    Returns
    -------
    (DiagnosisReport, HybridModel)
        `diagnose`'s report with ``system`` "crazyflie", ``prior`` {``system``, ``params``}, ``prior_after``
        (the repaired prior, the same keys),
        ``thrust_source``, ``declared_mass_kg``, ``vehicle_fits_prior`` {``ok``, ``thrust_gain``,
        ``message``}, ``repair`` (`repair_verdict`), ``candidates`` (every candidate effect, fitted alone),
        ``lowpass_hz``, ``excitation``, ``undetermined`` and ``ties`` (`_determinable`), ``thrust_map_fit``
        (PWM logs, `diagnosis_identifiability.thrust_map_fit`); and the repaired model (a KNODE on the repaired
        prior, measurement effects in its meta, trained when a KNODE method is scored or ``train_repaired``).

    Raises
    ------
    models.inputs.MissingInputs
        If a flight carries no thrust source the prior can use.
    InvalidInput
        If ``knode`` is not a crazyflie model, or the flights hold too few usable samples.
    """
    flights, prior, source, declared = _diagnosable(flights, knode, mass_kg, prior)
    fitting, scoring, split = _split_for_fitting(flights, "crazyflie")
    stages = DiagnosisStages(on_stage, {**CRAZYFLIE_PLAN, "before": 0.0} if knode else CRAZYFLIE_PLAN)
    stages.report("effects", f"reading the specific force ({len(fitting)} fitting flight(s))")
    problem, shape = _fitting_problem(fitting, prior, source)
    selection = select_effects(problem, min_cv_gain=CRAZYFLIE_MIN_CV_GAIN, on_stage=stages.part("effects"))
    held_out_problems = [crazyflie_problem([flight], prior) for flight in scoring]
    values = _transferring(selection, held_out_problems, [f.name for f in scoring])
    chosen = [e for e in problem.candidates if e.id in {c["id"] for c in selection["effects"]}]
    repaired, measurement = _repaired_values(prior, chosen, values)

    config, learn = replace(CRAZYFLIE_TRAINING, epochs=epochs), any(m.startswith("knode") for m in methods)
    model_before = knode or _crazyflie_model(fitting[0], prior, learn, config, stages, "before")
    model_after = _crazyflie_model(fitting[0], repaired, learn or train_repaired, config, stages, "after")
    model_after.meta.update({"measurement_effects": measurement,
                             "effects": [e.id for e in chosen if any(p.name in values for p in e.params)],
                             "parent": model_before.meta.get("name"), "system": "crazyflie",
                             "thrust_source": source})
    model_after = tuned_alike(model_before, model_after, fitting[:1])
    keys = ["specific_force_rmse", *methods]
    before, after, per_flight, series = _score_repair(scoring, held_out_problems, selection["channel"], values,
                                                      methods, model_before, model_after, knode, stages)
    effects, fits_prior = _name_thrust_scale([{**e, "channel": selection["channel"]} for e in selection["effects"]],
                                             selection["candidates"], prior, source, declared)
    report = DiagnosisReport.of(
        system="crazyflie", prior={"system": "crazyflie", "params": prior},
        prior_after={"system": "crazyflie", "params": repaired},
        thrust_source=source, declared_mass_kg=declared, vehicle_fits_prior=fits_prior,
        effects=[DiagnosisEffect.of(**e) for e in effects], confounded=selection["confounded"],
        **_determinable(problem, selection, prior),
        candidates=[{**c, "channel": selection["channel"]} for c in selection["candidates"]],
        before={k: float(np.median(v)) for k, v in before.items()},
        after={k: float(np.median(v)) for k, v in after.items()},
        per_flight=[DiagnosisFlight.of(**p) for p in per_flight], split=split, lowpass_hz=LOWPASS_HZ,
        improved_flights={k: f"{sum(p['after'][k] < p['before'][k] for p in per_flight)}/{len(per_flight)}"
                          for k in keys},
        residuals={"specific_force_rmse_fitting_before": specific_force_rmse(problem),
                   "specific_force_rmse_fitting_after": specific_force_rmse(problem, values)},
        channels={selection["channel"]: _channel(selection)}, residual_series=series,
        # the evaluation's headline yardstick beside the paper's (``before``/``after``)
        **({"yardsticks": repair_yardsticks(per_flight, methods)} if methods else {}),
        **({"thrust_map_fit": thrust_map_fit(problem, prior, declared, shape)} if source == "pwm" else {}))
    return report.updated(repair=RepairVerdict.of(**repair_verdict(report, methods))), model_after


def _determinable(problem, selection: dict, prior: dict) -> dict:
    """The report's ``excitation`` (what the fitting flights span), ``undetermined`` {param: why never claimed}
    and ``ties`` (each with its combined observable in ``words``, `tie_words`)."""
    return {"excitation": problem.excitation, "undetermined": dict(problem.undetermined),
            "ties": [{**t, "words": tie_words(t, prior, problem.excitation, selection["candidates"])}
                     for t in selection["ties"]]}


def _fitting_problem(fitting: list[Flight], prior: dict, source: str) -> tuple:
    """(the specific-force problem of the fitting flights, `map_shape_check`'s answer): gamma is marked
    undetermined where the map's shape confounds it or differs from the prior's (PWM logs only)."""
    problem = crazyflie_problem(fitting, prior)
    shape = map_shape_check(problem, prior) if source == "pwm" else {"determined": True}
    if shape.get("reason"):
        problem.undetermined.setdefault("gamma", shape["reason"])
    return problem, shape


def _diagnosable(flights: list[Flight], knode: HybridModel | None, mass_kg: float | None,
                 prior: dict | None) -> tuple[list[Flight], dict, str, float | None]:
    """The flights to diagnose (the good ones, or all when none is), the prior's parameters, the thrust source
    and the declared mass (`crazyflie_prior_for`); refuses a model of another prior, or flights without the
    inputs the prior needs (`models.inputs.MissingInputs`, raised before any work)."""
    if knode is not None and knode.system.name != "crazyflie":
        raise InvalidInput(f"model {knode.meta.get('name') or ''} has the {knode.system.name!r} prior: diagnosing "
                           "with --system crazyflie needs a model trained with the crazyflie prior")
    flights = [f for f in flights if f.quality["ok"]] or flights
    params, source, declared = crazyflie_prior_for(flights, knode, mass_kg, prior)
    for flight in flights:
        flight_inputs(flight, "crazyflie", params, thrust_gain=False)
    return flights, params, source, declared


def _repaired_values(prior: dict, chosen: list, values: dict) -> tuple[dict, dict]:
    """(the repaired prior's parameters: ``prior`` with the chosen dynamics effects' ``values``, the chosen
    measurement effects' values)."""
    repaired = {**prior, **{p.name: values[p.name] for e in chosen if e.target == "dynamics" for p in e.params
                            if p.name in values}}
    measurement = {p.name: values[p.name] for e in chosen if e.target == "measurement" for p in e.params
                   if p.name in values}
    return repaired, measurement


def _score_repair(scoring: list[Flight], held_out_problems: list, channel: str, values: dict,
                  methods: Sequence[str], model_before: HybridModel, model_after: HybridModel,
                  knode: HybridModel | None, stages: DiagnosisStages | None = None):
    """`diagnose_crazyflie`'s scores on the held-out flights, before and after the repair: the specific-force
    RMSE (m/s²) predicted from the inputs and each method's MSE (the paper's SG yardstick), per flight and as
    lists per key, each flight also with `repair_scores` (its mocap-gap score, the repair's yardstick), with
    the residual series of the first held-out flight: ``(before, after, per_flight, series)``."""
    keys = ["specific_force_rmse", *methods]
    before: dict[str, list[float]] = {k: [] for k in keys}
    after: dict[str, list[float]] = {k: [] for k in keys}
    per_flight: list[dict] = []
    mhe_cache: dict = {}
    series: dict = {}
    stages = stages or DiagnosisStages(None, {})
    for k, (flight, held_out) in enumerate(zip(scoring, held_out_problems)):
        stages.report("scoring", f"scoring before/after ({flight.name}, {k + 1}/{len(scoring)})", k / len(scoring))
        # the specific force predicted from the inputs on the first held-out flight, before and after
        series = series or {channel: residual_series(held_out, values, flight.name)}
        b = {"specific_force_rmse": specific_force_rmse(held_out)}
        a = {"specific_force_rmse": specific_force_rmse(held_out, values)}
        scores: dict = {"repair_gain_interval_pct": {}}
        if methods:
            # the diagnosis's priors see the thrust as the map predicts it: a per-flight thrust gain would
            # absorb the payload and battery effects it fits (a user's model keeps the inputs it was trained on)
            scored_b = evaluate_flight(model_before, flight, methods, mhe_cache=mhe_cache, keep_estimates=True,
                                       thrust_gain=None if model_before is knode else False, gaps=REPAIR_GAPS)
            scored_a = evaluate_flight(model_after, flight, methods, mhe_cache=mhe_cache, keep_estimates=True,
                                       thrust_gain=False, gaps=REPAIR_GAPS)
            b.update({m: scored_b["results"][m]["mse"] for m in methods})
            a.update({m: scored_a["results"][m]["mse"] for m in methods})
            scores = repair_scores(scored_b, scored_a, methods, flight)
        per_flight.append({"flight": flight.name, "before": b, "after": a, **scores})
        for key in keys:
            before[key].append(b[key])
            after[key].append(a[key])
    return before, after, per_flight, series


def _transferring(selection: dict, held_out: list, names: list[str]) -> dict:
    """``selection``'s identified values without the effects that make the held-out flights worse.

    Each chosen effect with an identified parameter is scored on every held-out flight: the specific-force
    RMSE from the inputs with the identified values, against the same without that effect.  An effect that
    does not lower it on more than half the held-out flights does not transfer: its entries are marked not
    identified (``held_out`` says why) and the repair leaves it out.  Returns the values a repair uses."""
    values = dict(selection["values_identified"])
    for effect in selection["effects"]:
        names_ = [k for k, ok in effect["identified"].items() if ok and k in values]
        if not names_ or not held_out:
            continue
        without = {k: v for k, v in values.items() if k not in names_}
        better = [specific_force_rmse(p, values) < specific_force_rmse(p, without) for p in held_out]
        effect["held_out_better"] = f"{sum(better)}/{len(better)}"
        if 2 * sum(better) <= len(better):
            worse = [n for n, b in zip(names, better) if not b]
            effect["held_out"] = (f"does not transfer: the held-out specific force is not better with it on "
                                  f"{len(worse)} of {len(better)} flights ({', '.join(worse)}); not claimed, "
                                  "not repaired")
            for k in names_:
                effect["identified"][k] = effect["claimed"][k] = False
            values = without
    return values

