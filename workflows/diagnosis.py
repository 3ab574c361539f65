"""`learnest diagnose`: measure the residual, trace it to named effects, add them, report before/after.

Simulated systems (cartpole, robot): the true system gets the values given with --simulate; the
diagnosis sees only measurements y and inputs u (through the pre-training observer), never the truth.
Crazyflie flights, kinematic prior (system "quadrotor"): the accelerometer channel (measurement effects,
against Savitzky–Golay references) and the translational dynamics (dynamics effects, on the KF observer's
states) are traced separately.  Crazyflie flights, input-driven prior (system "crazyflie"): one channel,
the body-frame specific force the accelerometer reads against what motors, battery and mocap predict
(`models.crazyflie.crazyflie_residual`), traces the physical effects (mass, battery_thrust, rotor_drag,
ground_effect, motor_lag) and the accelerometer's together.
Everything is fitted on some data and scored on other data (flights or trajectories not used to fit).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from learnest.errors import InvalidInput, LearnestError
from learnest.estimators.algorithm1 import Algorithm1
from learnest.estimators.evaluate import evaluate_sequence
from learnest.estimators.flight_training import flight_inputs
from learnest.estimators.prepared import corrected_flight, model_params
from learnest.ingest.flight import Flight
from learnest.ingest.profile import flight_profile
from learnest.models.diagnosis import select_effects
from learnest.models.effects import LIBRARY, dynamics_params, effects_for
from learnest.models.knode import HybridModel
from learnest.models.presets import CRAZYFLIE_TRAINING, PAPER_TRAINING, diagnosis_fitting_count
from learnest.models.systems import make_system

from .diagnosis_crazyflie import crazyflie_prior_for, crazyflie_report
from .diagnosis_format import THRUST_SOURCE_TEXT, confounded_label, format_diagnosis, how_much, unchanged_prior_note
from .diagnosis_identifiability import thrust_map_fit
from .diagnosis_problems import (
    DIAGNOSIS_LOWPASS_HZ,
    DIAGNOSIS_SG_ORDER,
    DIAGNOSIS_SG_WINDOW,
    REPAIR_GAPS,
    _channel,
    _nominal,
    _public,
    _public_effects,
    _residual_summary,
    _split_for_fitting,
    accelerometer_problem,
    dynamics_problem,
    repair_interval,
    repair_scores,
    repair_verdict,
    repair_yardsticks,
    residual_series,
    tuned_alike,
)
from .diagnosis_stages import DiagnosisStages, StageCallback
from .flights import evaluate_flight
from .reports import DiagnosisEffect, DiagnosisFlight, DiagnosisReport, RepairVerdict

# the names callers import from here (the notebook's `diagnose`, the CLI, the service, the tests)
__all__ = ["DIAGNOSIS_LOWPASS_HZ", "DIAGNOSIS_SG_ORDER", "DIAGNOSIS_SG_WINDOW", "THRUST_SOURCE_TEXT",
           "accelerometer_problem", "confounded_label", "crazyflie_prior_for", "crazyflie_report", "diagnose",
           "diagnose_crazyflie", "diagnose_flights", "diagnose_simulated", "diagnosis_report", "dynamics_problem",
           "effects_for", "format_diagnosis", "how_much", "parse_simulate", "repair_interval", "repair_scores",
           "repair_verdict", "residual_series", "split_names", "thrust_map_fit", "unchanged_prior_note"]



# -- simulated systems -----------------------------------------------------------------------------
def parse_simulate(system_name: str, spec: str) -> dict:
    """"m_c=1.8,cart_friction=0.4" -> dynamics parameters of the true system.

    Names are effect parameter names or single-parameter effect ids; returns {dynamics key: value}.

    Raises
    ------
    InvalidInput
        If an item is not NAME=VALUE with a known name and a number.
    """
    effects = effects_for(system_name, "dynamics")
    by_name = {p.name: p for e in effects for p in e.params}
    by_effect = {e.id: e.params[0] for e in effects if len(e.params) == 1}
    out = {}
    for item in filter(None, (s.strip() for s in (spec or "").split(","))):
        name, sep, value = item.partition("=")
        param = by_name.get(name.strip()) or by_effect.get(name.strip())
        if not sep or param is None:
            known = sorted(set(by_name) | set(by_effect))
            raise InvalidInput(f"--simulate: {item!r} is not NAME=VALUE with NAME one of {', '.join(known)}")
        try:
            out[param.key] = float(value)
        except ValueError:
            raise InvalidInput(f"--simulate: {item!r}: {value!r} is not a number") from None
    return out


def diagnose_simulated(system_name: str, simulate: str = "", seed: int = 0,
                       methods: Sequence[str] = ("ukf", "knode-ukf"), epochs: int | None = None,
                       eval_samples: int | None = None) -> dict:
    """Diagnose a simulated cartpole or robot whose true system has the ``simulate`` parameters.

    Effects are selected on the observer's states of one simulated run (seed 10000 + ``seed``); a KNODE
    is trained on top of the original and of the repaired prior, and both are scored (MSE against the
    true states) on another run (seed 20000 + ``seed``, ``eval_samples`` samples).

    Returns
    -------
    dict
        ``system``, ``simulated_truth``, ``effects``, ``confounded``, ``channels``, ``before`` and
        ``after`` {method: MSE}, ``prior_params_after``.

    Raises
    ------
    InvalidInput
        If ``system_name`` is not cartpole or robot, or ``simulate`` does not parse.
    """
    if system_name not in ("cartpole", "robot"):
        raise InvalidInput("--simulate works for the paper's simulated systems: cartpole or robot")
    system = make_system(system_name)
    system = system.with_true_params(**parse_simulate(system_name, simulate))
    train, test = system.simulate(10_000 + seed), system.simulate(20_000 + seed, eval_samples)
    # retrain on top with a held-out block: once the prior is right there may be nothing left to learn,
    # and then the KNODE should stay the prior rather than fit the observer's noise
    config = replace(PAPER_TRAINING[system_name], validation_fraction=0.2)
    if epochs:
        config = replace(config, epochs=epochs)
    algorithm = Algorithm1(config=config)
    # one observation of the training run: the effects are selected on it and both KNODEs learn from it
    zeta = algorithm.observe(system, train.y, train.u, system.dt)
    problem = dynamics_problem(system, zeta, train.u, system.dt, effects_for(system_name, "dynamics"))
    selection = select_effects(problem)
    chosen = [LIBRARY[e["id"]] for e in selection["effects"]]
    repaired = replace(system, prior_params=dynamics_params(system, selection["values"], chosen))

    before = _score_simulated(algorithm, system, zeta, train, test, methods)
    # nothing chosen: the repaired prior is the prior, and training is seeded, so the scores would repeat
    after = _score_simulated(algorithm, repaired, zeta, train, test, methods) if chosen else dict(before)
    return {"system": system_name, "simulated_truth": {k: system.true_params[k] for k in system.true_params},
            **_public(selection), "before": before, "after": after,
            "prior_params_after": repaired.prior_params}


def _score_simulated(algorithm, system, zeta, train, test, methods):
    knode = algorithm.fit_states(system, zeta, train.u, system.dt).model
    prior = HybridModel(system, "prior")
    x0 = test.x_noisy[0]
    results = evaluate_sequence(methods, model_params(prior, x0, system.dt), model_params(knode, x0, system.dt),
                                test.y, test.u, test.x)
    return {m: r["mse"] for m, r in results.items()}


def diagnose_flights(flights: list[Flight], knode: HybridModel | None = None,
                     methods: Sequence[str] = ("ukf", "knode-ukf"), epochs: int = CRAZYFLIE_TRAINING.epochs,
                     return_model: bool = False, system: str | None = None, prior: dict | None = None,
                     mass_kg: float | None = None, on_stage: StageCallback | None = None):
    """`diagnosis_report` with the report as its JSON (the dict of `learnest diagnose --json`): ``report``, or
    ``(report, model)`` with ``return_model``."""
    report, model = diagnosis_report(flights, knode, methods, epochs, return_model=return_model, system=system,
                                     prior=prior, mass_kg=mass_kg, on_stage=on_stage)
    return (report.to_dict(), model) if return_model else report.to_dict()


def diagnosis_report(flights: list[Flight], knode: HybridModel | None = None,
                     methods: Sequence[str] = ("ukf", "knode-ukf"), epochs: int = CRAZYFLIE_TRAINING.epochs, *,
                     return_model: bool = False, system: str | None = None, prior: dict | None = None,
                     mass_kg: float | None = None,
                     on_stage: StageCallback | None = None) -> tuple[DiagnosisReport, HybridModel | None]:
    """The diagnosis as its report's type, and the repaired model (prior + dynamics effects, measurement effects
    in its meta, KNODE retrained on top) ready to be registered as a new version.

    Parameters
    ----------
    flights : list of Flight
        Flights failing the quality checks are left out unless all fail; the rest are split into fitting and
        scored ones (`split_names`).
    knode : HybridModel, optional
        The KNODE diagnosed; default: one trained on the fitting flight.
    methods : sequence of str
        Estimators scored before and after.
    epochs : int
        Training epochs of the KNODEs trained here.
    return_model : bool
        Also return the repaired model (the Crazyflie prior trains its KNODE only when asked or scored).
    system : {"quadrotor", "crazyflie"}, optional
        The prior diagnosed: "quadrotor" (kinematic) or "crazyflie" (input-driven, see `crazyflie_report`;
        ``prior`` its parameters; ``mass_kg`` a declared mass).  None: the given model's prior, else "quadrotor".
    prior : dict, optional
        The Crazyflie prior's parameters.
    mass_kg : float, optional
        The vehicle's declared mass, kg.
    on_stage : callable, optional
        ``on_stage(name, fraction)`` is told each named stage as it starts ("fitting effects on accelerometer
        (accel_bias, 2/5)", "training the KNODE on the repaired prior (epoch 3/20)", "scoring before/after
        (flight3, 1/2)") with the fraction of the diagnosis done (0..1, never lower than before;
        `diagnosis_stages.DiagnosisStages`).

    Returns
    -------
    (DiagnosisReport, HybridModel or None)
        The report (see `diagnose`) and the repaired model (None unless ``return_model``).
    """
    if system is None:
        system = knode.system.name if knode is not None else "quadrotor"
    if system == "crazyflie":
        report, model = crazyflie_report(flights, knode=knode, methods=methods, epochs=epochs,
                                         train_repaired=return_model, prior=prior, mass_kg=mass_kg, on_stage=on_stage)
    elif system != "quadrotor":
        raise InvalidInput(f"diagnosing flights needs system 'quadrotor' or 'crazyflie', not {system!r}")
    elif knode is not None and knode.system.name != "quadrotor":
        raise InvalidInput(f"model {knode.meta.get('name') or ''} has the {knode.system.name!r} prior: diagnose it "
                           f"with system {knode.system.name!r} (the default for a model is its own prior)")
    else:
        report, model = _diagnose_quadrotor(flights, knode, methods, epochs, on_stage)
    return report.updated(**split_names(flights, system)), model if return_model else None


def diagnose_crazyflie(flights: list[Flight], knode: HybridModel | None = None, methods: Sequence[str] = ("ukf",),
                       epochs: int = CRAZYFLIE_TRAINING.epochs, return_model: bool = False,
                       prior: dict | None = None, mass_kg: float | None = None,
                       on_stage: StageCallback | None = None):
    """`crazyflie_report` with the report as its JSON: ``report``, or ``(report, model)`` with ``return_model``."""
    report, model = crazyflie_report(flights, knode, methods, epochs, train_repaired=return_model, prior=prior,
                                     mass_kg=mass_kg, on_stage=on_stage)
    return (report.to_dict(), model) if return_model else report.to_dict()


def split_names(flights: list[Flight], system: str) -> dict:
    """``fitting_flights`` and ``scored_flights`` (names) as the diagnosis splits ``flights`` (`SPLIT_RULE`;
    one flight is in both: its first 60 % fitted, the rest scored)."""
    kept = [f for f in flights if f.quality["ok"]] or flights
    if len(kept) == 1:
        return {"fitting_flights": [kept[0].name], "scored_flights": [kept[0].name]}
    cut = diagnosis_fitting_count(len(kept), system)
    return {"fitting_flights": [f.name for f in kept[:cut]], "scored_flights": [f.name for f in kept[cut:]]}


# the parts of a kinematic-prior diagnosis and their rough relative costs (a KNODE training dominates)
QUADROTOR_PLAN = {"accelerometer": 1.0, "observer": 0.3, "dynamics": 1.0, "before": 3.0, "after": 3.0, "scoring": 2.0}


def _diagnose_quadrotor(flights: list[Flight], knode: HybridModel | None, methods: Sequence[str], epochs: int,
                        on_stage: StageCallback | None = None) -> tuple[DiagnosisReport, HybridModel]:
    """`diagnosis_report` with the kinematic prior: accelerometer channel, then translational dynamics; the report
    and the repaired model."""
    flights = [f for f in flights if f.quality["ok"]] or flights
    fitting, scoring, split = _split_for_fitting(flights)
    stages = DiagnosisStages(on_stage, QUADROTOR_PLAN if knode is None else {**QUADROTOR_PLAN, "before": 0.0})
    accel = select_effects(accelerometer_problem(fitting), on_stage=stages.part("accelerometer"))
    # only identified parameters repair (models.diagnosis.select_effects: a fit at a bound is no value)
    fixed_fitting = [corrected_flight(f, accel["values_identified"]) for f in fitting]
    # the fitting data is one flight (or the first 60 % of one): trace the jerk residual on its states
    fitting_flight = fixed_fitting[0]
    system, no_input, _ = flight_inputs(fitting_flight, "quadrotor")   # the kinematic prior: u has width 0
    config = replace(CRAZYFLIE_TRAINING, epochs=epochs)
    algorithm = Algorithm1(config=config)
    stages.report("observer", f"pre-training observer ({fitting_flight.name}, 1/2)")
    zeta = algorithm.observe(system, fitting_flight.measurements(), no_input, system.dt)
    dynamics = select_effects(dynamics_problem(system, zeta, no_input, system.dt, effects_for("quadrotor", "dynamics"),
                                               components=[6, 7, 8], name="translational dynamics"),
                              on_stage=stages.part("dynamics"))
    chosen_dyn = [LIBRARY[e["id"]] for e in dynamics["effects"]]
    new_prior = dynamics_params(system, {**_nominal(chosen_dyn), **dynamics["values_identified"]}, chosen_dyn)

    knode_before = knode or algorithm.fit_flights(fitting[:1], "quadrotor",
                                                  progress=stages.epochs("before", "the prior", epochs)).model
    repaired_system = replace(system, prior_params=new_prior)
    stages.report("after", f"pre-training observer ({fitting_flight.name}, 2/2)")
    knode_after = algorithm.fit(repaired_system, fitting_flight.measurements(), no_input, system.dt,
                                progress=stages.epochs("after", "the repaired prior", epochs)).model
    chosen_meas = [LIBRARY[e["id"]] for e in accel["effects"]]
    knode_after.meta.update({
        "measurement_effects": {p.name: accel["values_identified"][p.name] for e in chosen_meas for p in e.params
                                if p.name in accel["values_identified"]},
        "effects": [e["id"] for e in accel["effects"] + dynamics["effects"]],
        "training_flight": fitting[0].name,
        "training_flight_sha256": [s["sha256"] for s in fitting[0].meta.get("sources", [])],
        "training_profile": flight_profile(fitting[0]),
        "parent": knode_before.meta.get("name")})
    knode_after = tuned_alike(knode_before, knode_after, fitting[:1])
    before: dict[str, list[float]] = {m: [] for m in methods}
    after: dict[str, list[float]] = {m: [] for m in methods}
    per_flight: list[dict] = []
    mhe_cache: dict = {}  # keyed by model: before and after never share an MHE
    for k, flight in enumerate(scoring):
        stages.report("scoring", f"scoring before/after ({flight.name}, {k + 1}/{len(scoring)})", k / len(scoring))
        scored_b = evaluate_flight(knode_before, flight, methods, mhe_cache=mhe_cache, keep_estimates=True,
                                   gaps=REPAIR_GAPS)
        scored_a = evaluate_flight(knode_after, flight, methods, mhe_cache=mhe_cache, keep_estimates=True,
                                   gaps=REPAIR_GAPS)
        b, a = scored_b["results"], scored_a["results"]
        per_flight.append({"flight": flight.name, "before": {m: b[m]["mse"] for m in methods},
                           "after": {m: a[m]["mse"] for m in methods},
                           **repair_scores(scored_b, scored_a, methods, flight)})
        for m in methods:
            before[m].append(b[m]["mse"])
            after[m].append(a[m]["mse"])
    effects = sorted(_public_effects(accel) + _public_effects(dynamics), key=lambda e: -e["explained_fraction"])
    report = DiagnosisReport.of(
        system="quadrotor", effects=[DiagnosisEffect.of(**e) for e in effects],
        confounded=accel["confounded"] + dynamics["confounded"],
        before={m: float(np.median(v)) for m, v in before.items()},
        after={m: float(np.median(v)) for m, v in after.items()},
        per_flight=[DiagnosisFlight.of(**p) for p in per_flight], split=split,
        # a median can hide an effect that does not transfer: count the flights it helped
        improved_flights={m: f"{sum(p['after'][m] < p['before'][m] for p in per_flight)}/{len(per_flight)}"
                          for m in methods},
        residuals=_residual_summary(fitting, fixed_fitting, accel, dynamics, knode_before),
        channels={"accelerometer": _channel(accel), "translational dynamics": _channel(dynamics)},
        # the accelerometer residual on the first held-out flight, before and after its effects
        residual_series={"accelerometer": residual_series(accelerometer_problem(scoring[:1]),
                                                          accel["values_identified"], scoring[0].name)}
        if "acc_body" in scoring[0].channels else {},
        yardsticks=repair_yardsticks(per_flight, methods))
    # the same gate as the Crazyflie prior's: registered only when the held-out flights improve
    verdict = repair_verdict(report, methods) if methods else {
        "improves": False, "method": None, "reason": "no estimator scored the held-out flights"}
    return report.updated(repair=RepairVerdict.of(**verdict)), knode_after


def diagnose(flights: list[Flight], model: HybridModel | None = None, methods: Sequence[str] = ("ukf", "knode-ukf"),
             epochs: int = CRAZYFLIE_TRAINING.epochs, system: str | None = None, mass_kg: float | None = None) -> dict:
    """Trace what the model lacks on real flights, add it, and score before and after.

    Parameters
    ----------
    flights : list of Flight
        The first (clean) flight is fitted; the others are scored.  One flight: fitted on its first 60 %,
        scored on the rest.  With ``system="crazyflie"`` the first half of the flights is fitted.
    model : HybridModel, optional
        The KNODE to diagnose; default: one trained on the fitting flight.
    methods : sequence of str
        Estimators scored before and after.
    epochs : int
        Training epochs of the KNODEs trained here.
    system : {"quadrotor", "crazyflie"}, optional
        The prior diagnosed: the kinematic quadrotor or the input-driven Crazyflie (thrust from motor PWM and
        battery, rotor speed or thrust in N, whichever the flights carry).  Default: ``model``'s prior, else
        "quadrotor".
    mass_kg : float, optional
        The vehicle's declared mass, kg (Crazyflie prior; default the flights' own, e.g. crazyswarm2's
        info*.yaml).

    Returns
    -------
    dict
        ``effects`` (each with ``id``, ``target``, ``channel``, ``params`` and their ``units``, ``ci95``
        95 % intervals, ``determined``, ``identified``, ``at_bound``, ``claimed``, ``held_nominal``,
        ``explained_fraction`` and ``equation``), sorted by explained fraction; ``confounded``;
        ``before``/``after`` median MSE per method; ``per_flight``; ``split``; ``improved_flights``;
        ``residuals``; ``channels``; for the Crazyflie prior also ``thrust_source`` and
        ``vehicle_fits_prior`` (the JSON of `learnest diagnose --json`).

    Raises
    ------
    LearnestError
        `InvalidInput` (and its `models.inputs.MissingInputs`) for flights or a model this diagnosis cannot
        use, naming the flight and what is wrong.

    Examples
    --------
    >>> import learnest as le
    >>> flights = le.read_flights(["sample_logs/circle_rep1.csv", "sample_logs/circle_rep2.csv"])
    >>> report = le.diagnose(flights, epochs=20)
    >>> sorted(report["before"])
    ['knode-ukf', 'ukf']
    """
    try:
        return diagnose_flights(list(flights), knode=model, methods=methods, epochs=epochs, system=system,
                                mass_kg=mass_kg)
    except LearnestError:
        raise
    except ValueError as err:
        raise InvalidInput(f"diagnose: {err}") from err
