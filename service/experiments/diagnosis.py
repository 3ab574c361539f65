"""`learnest diagnose`: measure the residual, trace it to named effects, add them, report before/after.

Simulated systems (cartpole, robot): the true system gets the values given with --simulate; the
diagnosis sees only measurements y and inputs u (through the pre-training observer), never the truth.
Crazyflie flights, kinematic prior (system "quadrotor"): the accelerometer channel (measurement effects,
against Savitzky–Golay references) and the translational dynamics (dynamics effects, on the KF observer's
states) are traced separately.  Crazyflie flights, input-driven prior (system "crazyflie"): one channel,
the body-frame specific force the accelerometer reads against what motors, battery and mocap predict
(`models.crazyflie_residual`), traces the physical effects (mass, battery_thrust, rotor_drag,
ground_effect, motor_lag) and the accelerometer's together.
Everything is fitted on some data and scored on other data (flights or trajectories not used to fit).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from learnest.errors import InvalidInput, LearnestError
from learnest.estimators.evaluate import GAIN_BLOCK_S, evaluate_sequence, gain_interval
from learnest.estimators.observers import pretraining_observer
from learnest.estimators.ukf import run_ukf
from learnest.ingest.baseline import sg_references
from learnest.ingest.flight import Flight
from learnest.ingest.profile import flight_profile
from learnest.models import crazyflie as cf
from learnest.models.backend import rk4_step
from learnest.models.crazyflie_residual import CRAZYFLIE_MIN_CV_GAIN, crazyflie_problem, specific_force_rmse
from learnest.models.diagnosis import (
    AT_BOUND_FRACTION,
    MULTIPLE_SHARE,
    ResidualProblem,
    bootstrap_ci,
    fit,
    select_effects,
)
from learnest.models.effects import (
    LIBRARY,
    Effect,
    dynamics_params,
    effects_for,
    predict_acc_body,
    specific_force_body,
    unidentifiable_scales,
)
from learnest.models.identify import LOWPASS_HZ, lowpass
from learnest.models.inputs import (
    CHANNEL_SOURCES,
    SOURCE_CHANNELS,
    MissingInputs,
    flight_thrust_source,
    slice_keeping_heat,
    system_inputs,
    training_meta,
)
from learnest.models.knode import HybridModel
from learnest.models.presets import CRAZYFLIE_TRAINING, PAPER_TRAINING
from learnest.models.systems import System, make_system
from learnest.models.training import train_knode

from .flights import (
    corrected_flight,
    evaluate_flight,
    initial_state,
    quadrotor_for,
    system_for,
    train_on_flight,
)

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


def unchanged_prior_note(result: dict) -> str | None:
    """Why the error moved although no effect was found (``None`` if an effect was found or nothing moved).

    With no effect the prior is unchanged: what moves is the KNODE, trained again on top of the same prior
    (a different optimisation run, or a fresh one in place of the model given), so the change is training
    variability, not a missing effect.
    """
    if result["effects"]:
        return None
    moved = [m for m in result["after"] if m in result["before"]
             and not np.isclose(result["after"][m], result["before"][m], rtol=1e-9, atol=0.0)]
    if not moved:
        return None
    learned = [m for m in moved if m.startswith("knode")]
    why = ("the prior is unchanged, but the KNODE on top of it was trained again (another optimisation run, "
           "or a fresh one in place of the model given), so " + ", ".join(learned) + " reflect(s) training "
           "variability, not a missing effect") if learned else ""
    other = [m for m in moved if m not in learned]
    if other:
        why += ("; " if why else "") + (", ".join(other) + " moved with an unchanged prior: the estimator's "
                                        "run is not reproducible (e.g. an MHE warm start), not an effect")
    return "no effect found, yet the held-out error moved: " + why


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
    zeta = pretraining_observer(system, train.y, train.u, system.dt)
    problem = dynamics_problem(system, zeta, train.u, system.dt, effects_for(system_name, "dynamics"))
    selection = select_effects(problem)
    chosen = [LIBRARY[e["id"]] for e in selection["effects"]]
    repaired = replace(system, prior_params=dynamics_params(system, selection["values"], chosen))

    # retrain on top with a held-out block: once the prior is right there may be nothing left to learn,
    # and then the KNODE should stay the prior rather than fit the observer's noise
    config = replace(PAPER_TRAINING[system_name], validation_fraction=0.2)
    if epochs:
        config = replace(config, epochs=epochs)
    before = _score_simulated(system, zeta, train, test, methods, config)
    # nothing chosen: the repaired prior is the prior, and training is seeded, so the scores would repeat
    after = _score_simulated(repaired, zeta, train, test, methods, config) if chosen else dict(before)
    return {"system": system_name, "simulated_truth": {k: system.true_params[k] for k in system.true_params},
            **_public(selection), "before": before, "after": after,
            "prior_params_after": repaired.prior_params}


def _score_simulated(system, zeta, train, test, methods, config):
    knode = train_knode(system, zeta, train.u, system.dt, config).model
    prior = HybridModel(system, "prior")
    results = evaluate_sequence(methods, prior, knode, test.y, test.u, system.dt, system.Q, system.R,
                                test.x_noisy[0], system.P0, test.x)
    return {m: r["mse"] for m, r in results.items()}


# -- Crazyflie flights -----------------------------------------------------------------------------
# How the flights of a diagnosis are split (`_split_for_fitting`, `_split_crazyflie`), in the words every
# surface uses (the API schema, `learnest diagnose --help`); each report says its own split in ``split``,
# ``fitting_flights`` and ``scored_flights``.  Flights failing the quality checks are left out first.
# (models.presets.DIAGNOSIS_SPLIT_RULE: kept where the API schema can import it without numpy.)


def _split_for_fitting(flights: list[Flight]):
    """Fit on the first flight and score on the others; one flight: fit on its first 60 %, score the rest (its
    motors as warm as the flight's were there, `models.inputs.slice_keeping_heat`)."""
    if len(flights) > 1:
        return flights[:1], flights[1:], "fit on the first flight, scored on the others"
    cut = int(0.6 * len(flights[0].t))
    return [flights[0].slice(0, cut)], [slice_keeping_heat(flights[0], cut, len(flights[0].t))], \
        "one flight: fit on its first 60 %, scored on the last 40 %"


def diagnose_flights(flights: list[Flight], knode: HybridModel | None = None,
                     methods: Sequence[str] = ("ukf", "knode-ukf"), epochs: int = CRAZYFLIE_TRAINING.epochs,
                     return_model: bool = False, system: str | None = None, prior: dict | None = None,
                     mass_kg: float | None = None):
    """The diagnosis report; with return_model, also the repaired model (prior + dynamics effects,
    measurement effects in its meta, KNODE retrained on top) ready to be registered as a new version:
    ``report`` or ``(report, model)``.

    Flights failing the quality checks are left out unless all fail.  ``system`` is the prior diagnosed:
    "quadrotor" (kinematic) or "crazyflie" (input-driven, see `diagnose_crazyflie`; ``prior`` its
    parameters; ``mass_kg`` a declared mass).  None: the given model's prior, else "quadrotor".  See
    `diagnose` for the report.
    """
    if system is None:
        system = knode.system.name if knode is not None else "quadrotor"
    if system == "crazyflie":
        out = diagnose_crazyflie(flights, knode=knode, methods=methods, epochs=epochs, return_model=return_model,
                                 prior=prior, mass_kg=mass_kg)
    elif system != "quadrotor":
        raise InvalidInput(f"diagnosing flights needs system 'quadrotor' or 'crazyflie', not {system!r}")
    elif knode is not None and knode.system.name != "quadrotor":
        raise InvalidInput(f"model {knode.meta.get('name') or ''} has the {knode.system.name!r} prior: diagnose it "
                           f"with system {knode.system.name!r} (the default for a model is its own prior)")
    else:
        out = _diagnose_quadrotor(flights, knode, methods, epochs, return_model)
    report = out[0] if return_model else out
    report.update(split_names(flights, system))
    return out


def split_names(flights: list[Flight], system: str) -> dict:
    """``fitting_flights`` and ``scored_flights`` (names) as the diagnosis splits ``flights`` (`SPLIT_RULE`;
    one flight is in both: its first 60 % fitted, the rest scored)."""
    kept = [f for f in flights if f.quality["ok"]] or flights
    if len(kept) == 1:
        return {"fitting_flights": [kept[0].name], "scored_flights": [kept[0].name]}
    cut = (len(kept) + 1) // 2 if system == "crazyflie" else 1
    return {"fitting_flights": [f.name for f in kept[:cut]], "scored_flights": [f.name for f in kept[cut:]]}


def _diagnose_quadrotor(flights: list[Flight], knode: HybridModel | None, methods: Sequence[str], epochs: int,
                        return_model: bool):
    """`diagnose_flights` with the kinematic prior: accelerometer channel, then translational dynamics."""
    flights = [f for f in flights if f.quality["ok"]] or flights
    fitting, scoring, split = _split_for_fitting(flights)
    accel = select_effects(accelerometer_problem(fitting))
    # only identified parameters repair (models.diagnosis.select_effects: a fit at a bound is no value)
    fixed_fitting = [corrected_flight(f, accel["values_identified"]) for f in fitting]
    # the fitting data is one flight (or the first 60 % of one): trace the jerk residual on its states
    fitting_flight = fixed_fitting[0]
    system = quadrotor_for(fitting_flight)
    no_input = np.zeros((len(fitting_flight.t), 0))
    zeta = pretraining_observer(system, fitting_flight.measurements(), no_input, system.dt)
    dynamics = select_effects(dynamics_problem(system, zeta, no_input, system.dt, effects_for("quadrotor", "dynamics"),
                                               components=[6, 7, 8], name="translational dynamics"))
    chosen_dyn = [LIBRARY[e["id"]] for e in dynamics["effects"]]
    new_prior = dynamics_params(system, {**_nominal(chosen_dyn), **dynamics["values_identified"]}, chosen_dyn)

    config = replace(CRAZYFLIE_TRAINING, epochs=epochs)
    knode_before = knode or train_on_flight(fitting[0], config).model
    repaired_system = replace(system, prior_params=new_prior)
    zeta_after = pretraining_observer(repaired_system, fitting_flight.measurements(), no_input, system.dt)
    knode_after = train_knode(repaired_system, zeta_after, no_input, system.dt, config).model
    chosen_meas = [LIBRARY[e["id"]] for e in accel["effects"]]
    knode_after.meta.update({
        "measurement_effects": {p.name: accel["values_identified"][p.name] for e in chosen_meas for p in e.params
                                if p.name in accel["values_identified"]},
        "effects": [e["id"] for e in accel["effects"] + dynamics["effects"]],
        "training_flight": fitting[0].name,
        "training_flight_sha256": [s["sha256"] for s in fitting[0].meta.get("sources", [])],
        "training_profile": flight_profile(fitting[0]),
        "parent": knode_before.meta.get("name")})
    before: dict[str, list[float]] = {m: [] for m in methods}
    after: dict[str, list[float]] = {m: [] for m in methods}
    per_flight: list[dict] = []
    mhe_cache: dict = {}  # keyed by model: before and after never share an MHE
    for flight in scoring:
        scored_b = evaluate_flight(knode_before, flight, methods, mhe_cache=mhe_cache, keep_estimates=True)
        scored_a = evaluate_flight(knode_after, flight, methods, mhe_cache=mhe_cache, keep_estimates=True)
        b, a = scored_b["results"], scored_a["results"]
        per_flight.append({"flight": flight.name, "before": {m: b[m]["mse"] for m in methods},
                           "after": {m: a[m]["mse"] for m in methods},
                           "repair_gain_interval_pct": {m: repair_interval(scored_b, scored_a, m, flight.dt)
                                                        for m in methods}})
        for m in methods:
            before[m].append(b[m]["mse"])
            after[m].append(a[m]["mse"])
    effects = sorted(_public_effects(accel) + _public_effects(dynamics), key=lambda e: -e["explained_fraction"])
    report = {
        "system": "quadrotor", "effects": effects, "confounded": accel["confounded"] + dynamics["confounded"],
        "before": {m: float(np.median(v)) for m, v in before.items()},
        "after": {m: float(np.median(v)) for m, v in after.items()},
        "per_flight": per_flight, "split": split,
        # a median can hide an effect that does not transfer: count the flights it helped
        "improved_flights": {m: f"{sum(p['after'][m] < p['before'][m] for p in per_flight)}/{len(per_flight)}"
                             for m in methods},
        "residuals": _residual_summary(fitting, fixed_fitting, accel, dynamics, knode_before),
        "channels": {"accelerometer": _channel(accel), "translational dynamics": _channel(dynamics)},
        # the accelerometer residual on the first held-out flight, before and after its effects
        "residual_series": {"accelerometer": residual_series(accelerometer_problem(scoring[:1]),
                                                             accel["values_identified"], scoring[0].name)}
        if "acc_body" in scoring[0].channels else {}}
    return (report, knode_after) if return_model else report


def _nominal(effects) -> dict:
    return {k: v for e in effects for k, v in e.nominal().items()}


THRUST_SOURCE_TEXT = {"pwm": "motor PWM and battery voltage", "rpm": "rotor speed (rpm deck)",
                      "thrust_n": "the controller's thrust command in N"}


# -- Crazyflie flights, input-driven prior -------------------------------------------------------------
def _split_crazyflie(flights: list[Flight]):
    """Fit on the first half of the flights (rounded up; blocked CV by flight when that is several), score
    on the others; one flight: fit on its first 60 %, score the rest."""
    if len(flights) == 1:
        return _split_for_fitting(flights)
    cut = (len(flights) + 1) // 2
    return flights[:cut], flights[cut:], f"fit on the first {cut} flight(s), scored on the other {len(flights) - cut}"


def _crazyflie_model(flight: Flight, params: dict, train: bool, config) -> HybridModel:
    """The Crazyflie prior with ``params`` on ``flight``'s grid; with ``train``, a KNODE trained on top."""
    system = replace(system_for(flight, "crazyflie"), prior_params=dict(params))
    if not train:
        return HybridModel(system, "prior")
    u = system_inputs(flight, system)
    zeta = pretraining_observer(system, flight.measurements(), u, system.dt)
    model = train_knode(system, zeta, u, system.dt, config).model
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
            declared = float(masses.pop())
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
    """
    m_prior = float(prior["m_kg"])
    as_mass = source == "thrust_n" or declared is not None
    scale = (declared / m_prior) if (as_mass and source == "pwm" and declared) else 1.0

    def convert(value: float) -> float:
        return value * scale if as_mass else m_prior / value

    out = []
    for e in effects:
        if e["id"] != "mass":
            out.append(e)
            continue
        e = dict(e)
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
                    "units", "bounds")
            e.update({"id": "thrust_gain", "params": {"gain": convert(value)}, "nominal": {"gain": 1.0},
                      "ci95": {"gain": sorted([convert(interval[0]), convert(interval[1])])} if interval else {},
                      "equation": f"thrust_gain: gain = {convert(value):.4g} (thrust against the prior's map; "
                                  "a payload or another vehicle's motors)",
                      "note": "no mass is declared and the thrust is not known in N: only thrust over mass is "
                              "measured, reported as a gain on the prior's thrust map"})
            for key in keys:
                if key in e and isinstance(e[key], dict) and "m_kg" in e[key]:
                    v = e[key].pop("m_kg")
                    if key == "units":
                        v = ""
                    elif key == "bounds":
                        v = sorted([convert(v[1]), convert(v[0])])
                    e[key]["gain"] = v
        out.append(e)
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
            message += ("; with thrust in N this is the commanded thrust the motors do not make: an integrator "
                        "in the controller makes up the difference")
    return out, {"ok": ok, "thrust_gain": round(gain, 4), "message": message}


def diagnose_crazyflie(flights: list[Flight], knode: HybridModel | None = None, methods: Sequence[str] = ("ukf",),
                       epochs: int = CRAZYFLIE_TRAINING.epochs, return_model: bool = False,
                       prior: dict | None = None, mass_kg: float | None = None):
    """Trace what the input-driven Crazyflie prior lacks on real flights; score before and after on
    flights not used to fit.

    The thrust comes from what the flights carry (`crazyflie_prior_for`): motor PWM and battery voltage,
    rotor speed, or the controller's thrust in N.  The residual is the body-frame specific force
    (`models.crazyflie_residual.crazyflie_problem`, both sides low-passed at 5 Hz); effects are selected on
    the fitting flights (`_split_crazyflie`) and scored on the others: the RMSE of the specific force
    predicted from the inputs alone (``specific_force_rmse``, m/s²) and, for each of ``methods``, the
    estimator's MSE with the prior before and after (KNODE methods train a KNODE on the first fitting
    flight, ``epochs`` epochs, on each prior).  Only identified parameters repair the prior
    (`models.diagnosis.select_effects`).  ``prior`` holds the prior's parameters; by default ``knode``'s
    own, else the thrust source's.  ``mass_kg`` is a declared mass (kg), else the flights' own.

    Returns
    -------
    dict or (dict, HybridModel)
        `diagnose`'s report with ``system`` "crazyflie", ``prior`` {``system``, ``params``},
        ``thrust_source``, ``declared_mass_kg``, ``vehicle_fits_prior`` {``ok``, ``thrust_gain``,
        ``message``}, ``repair`` (`repair_verdict`), ``candidates`` (every candidate effect, fitted alone),
        ``lowpass_hz``; with ``return_model`` also the repaired model (a KNODE on the repaired prior,
        measurement effects in its meta).

    Raises
    ------
    models.inputs.MissingInputs
        If a flight carries no thrust source the prior can use.
    InvalidInput
        If ``knode`` is not a crazyflie model, or the flights hold too few usable samples.
    """
    if knode is not None and knode.system.name != "crazyflie":
        raise InvalidInput(f"model {knode.meta.get('name') or ''} has the {knode.system.name!r} prior: diagnosing "
                           "with --system crazyflie needs a model trained with the crazyflie prior")
    flights = [f for f in flights if f.quality["ok"]] or flights
    prior, source, declared = crazyflie_prior_for(flights, knode, mass_kg, prior)
    for flight in flights:
        system_inputs(flight, replace(system_for(flight, "crazyflie"), prior_params=dict(prior)))
    fitting, scoring, split = _split_crazyflie(flights)
    problem = crazyflie_problem(fitting, prior)
    selection = select_effects(problem, min_cv_gain=CRAZYFLIE_MIN_CV_GAIN)
    held_out_problems = [crazyflie_problem([flight], prior) for flight in scoring]
    values = _transferring(selection, held_out_problems, [f.name for f in scoring])
    chosen = [e for e in problem.candidates if e.id in {c["id"] for c in selection["effects"]}]
    repaired = {**prior, **{p.name: values[p.name] for e in chosen if e.target == "dynamics" for p in e.params
                            if p.name in values}}
    measurement = {p.name: values[p.name] for e in chosen if e.target == "measurement" for p in e.params
                   if p.name in values}

    config = replace(CRAZYFLIE_TRAINING, epochs=epochs)
    learn = any(m.startswith("knode") for m in methods)
    model_before = knode or _crazyflie_model(fitting[0], prior, learn, config)
    model_after = _crazyflie_model(fitting[0], repaired, learn or return_model, config)
    model_after.meta.update({"measurement_effects": measurement,
                             "effects": [e.id for e in chosen if any(p.name in values for p in e.params)],
                             "parent": model_before.meta.get("name"), "system": "crazyflie",
                             "thrust_source": source})
    keys = ["specific_force_rmse", *methods]
    before: dict[str, list[float]] = {k: [] for k in keys}
    after: dict[str, list[float]] = {k: [] for k in keys}
    per_flight: list[dict] = []
    mhe_cache: dict = {}
    series: dict = {}
    for flight, held_out in zip(scoring, held_out_problems):
        # the specific force predicted from the inputs on the first held-out flight, before and after
        series = series or {selection["channel"]: residual_series(held_out, values, flight.name)}
        b = {"specific_force_rmse": specific_force_rmse(held_out)}
        a = {"specific_force_rmse": specific_force_rmse(held_out, values)}
        intervals = {}
        if methods:
            # the diagnosis's priors see the thrust as the map predicts it: a per-flight thrust gain would
            # absorb the payload and battery effects it fits (a user's model keeps the inputs it was trained on)
            scored_b = evaluate_flight(model_before, flight, methods, mhe_cache=mhe_cache, keep_estimates=True,
                                       thrust_gain=None if model_before is knode else False)
            scored_a = evaluate_flight(model_after, flight, methods, mhe_cache=mhe_cache, keep_estimates=True,
                                       thrust_gain=False)
            b.update({m: scored_b["results"][m]["mse"] for m in methods})
            a.update({m: scored_a["results"][m]["mse"] for m in methods})
            intervals = {m: repair_interval(scored_b, scored_a, m, flight.dt) for m in methods}
        per_flight.append({"flight": flight.name, "before": b, "after": a, "repair_gain_interval_pct": intervals})
        for k in keys:
            before[k].append(b[k])
            after[k].append(a[k])
    effects, fits_prior = _name_thrust_scale([{**e, "channel": selection["channel"]} for e in selection["effects"]],
                                             selection["candidates"], prior, source, declared)
    report = {
        "system": "crazyflie", "prior": {"system": "crazyflie", "params": prior},
        "thrust_source": source, "declared_mass_kg": declared, "vehicle_fits_prior": fits_prior,
        "effects": effects, "confounded": selection["confounded"],
        "candidates": [{**c, "channel": selection["channel"]} for c in selection["candidates"]],
        "before": {k: float(np.median(v)) for k, v in before.items()},
        "after": {k: float(np.median(v)) for k, v in after.items()},
        "per_flight": per_flight, "split": split, "lowpass_hz": LOWPASS_HZ,
        "improved_flights": {k: f"{sum(p['after'][k] < p['before'][k] for p in per_flight)}/{len(per_flight)}"
                             for k in keys},
        "residuals": {"specific_force_rmse_fitting_before": specific_force_rmse(problem),
                      "specific_force_rmse_fitting_after": specific_force_rmse(problem, values)},
        "channels": {selection["channel"]: _channel(selection)}, "residual_series": series}
    report["repair"] = repair_verdict(report, methods)
    if source == "pwm":
        report["thrust_map_fit"] = thrust_map_fit(problem, prior, declared)
    return (report, model_after) if return_model else report


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


def thrust_map_fit(problem, prior: dict, declared: float | None) -> dict:
    """The thrust gain and battery exponent against the prior's PWM map, fitted together on the fitting
    flights with 95 % block-bootstrap intervals, whether or not the selection chose them: how far this
    vehicle's thrust is from the map.  ``gain`` = m_prior / m_fit (dimensionless), or ``m_kg`` scaled onto a
    declared mass; ``gamma`` the exponent of (V / V_ref); ``at_bound`` for each fitted parameter."""
    effects = [e for e in problem.candidates if e.id in ("mass", "battery_thrust")]
    fitted = fit(problem, effects)
    intervals = bootstrap_ci(problem, fitted)
    m_prior = float(prior["m_kg"])
    m_fit, (m_lo, m_hi) = fitted.values["m_kg"], intervals["m_kg"]
    params = {p.name: p for e in effects for p in e.params}
    out = {"gain": m_prior / m_fit, "gain_ci95": [m_prior / m_hi, m_prior / m_lo],
           "gamma": fitted.values["gamma"], "gamma_ci95": intervals["gamma"], "gamma_prior": float(prior["gamma"]),
           "at_bound": {k: bool(_at_bound_param(params[k], fitted.values[k])) for k in ("m_kg", "gamma")},
           "gamma_bounds": list(cf.BOUNDS["gamma"])}
    if declared is not None:
        out.update(m_kg=declared * m_fit / m_prior, m_kg_ci95=[declared * m_lo / m_prior, declared * m_hi / m_prior])
    return out


def _at_bound_param(param, value) -> bool:
    margin = AT_BOUND_FRACTION * (param.upper - param.lower)
    return value <= param.lower + margin or value >= param.upper - margin


def repair_interval(before: dict, after: dict, method: str, dt: float) -> list[float] | None:
    """95 % interval of the repair's gain on one flight, % (100 (1 − Σ after / Σ before) of the per-step
    squared error), by the evaluation's paired block bootstrap (`estimators.evaluate.gain_interval`).
    ``before``/``after`` are `evaluate_flight` results kept with their estimates."""
    reference = before["reference"]
    err_b = ((before["results"][method]["estimates"] - reference) ** 2).mean(axis=1)
    err_a = ((after["results"][method]["estimates"] - reference) ** 2).mean(axis=1)
    return gain_interval(err_b, err_a, round(GAIN_BLOCK_S / dt))


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
    worse: list[str] = [p["flight"] for p, i in zip(per_flight, intervals) if i and i[1] < 0]
    better: list[str] = [p["flight"] for p, i in zip(per_flight, intervals) if i and i[0] > 0]
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


def how_much(fraction: float) -> str:
    """A rival's share of the residual the chosen effect removes, in words (it can exceed 1: a rival with
    more parameters can remove more and still have the worse BIC_eff)."""
    if fraction >= MULTIPLE_SHARE:
        return f"removes {fraction:.1f}× as much"
    return f"explains {100 * fraction:.0f} % as much"


def confounded_label(pair: dict) -> str:
    """How a confounded pair is introduced: a close rival the data still rank lower, or a true tie."""
    return f"close rival (the data prefer {pair['data_prefer']})" if pair.get("data_prefer") else "cannot tell apart"


def format_diagnosis(result: dict) -> str:
    """The human-readable report: effects as equations, intervals, what could not be told apart, and
    the estimators' error before and after.  ``result`` is `diagnose`'s or `diagnose_simulated`'s dict."""
    lines = [f"diagnosis of {result['system']}"]
    if result.get("prior"):
        prior = result["prior"]["params"]
        lines.append("  prior: " + ", ".join(f"{k} = {v:.4g} {cf.UNITS.get(k, '')}".rstrip() for k, v in prior.items()
                                            if k in cf.UNITS))
    if result.get("thrust_source"):
        declared = result.get("declared_mass_kg")
        lines.append(f"  thrust from: {THRUST_SOURCE_TEXT[result['thrust_source']]}"
                     + (f"; declared mass {declared:g} kg" if declared else "; no declared mass"))
    if result.get("vehicle_fits_prior"):
        fits = result["vehicle_fits_prior"]
        verdict = "vehicle fits the prior" if fits["ok"] else "VEHICLE DOES NOT FIT THE PRIOR"
        lines.append(f"  {verdict}: {fits['message']}")
    if result.get("thrust_map_fit"):
        t = result["thrust_map_fit"]
        lines.append(f"  thrust against the prior's map, gain and battery exponent fitted together: gain "
                     f"{t['gain']:.4g} "
                     f"[{t['gain_ci95'][0]:.4g}, {t['gain_ci95'][1]:.4g}], gamma {t['gamma']:.3g} "
                     f"[{t['gamma_ci95'][0]:.3g}, {t['gamma_ci95'][1]:.3g}] (prior {t['gamma_prior']:.3g})"
                     + ("; at a bound: " + ", ".join(k for k, b in t["at_bound"].items() if b)
                        if any(t["at_bound"].values()) else ""))
    if result.get("simulated_truth"):
        lines.append(f"  (simulated; truth hidden from the diagnosis: {result['simulated_truth']})")
    if not result["effects"]:
        lines.append("  no effect explains the residual better than noise: the model is not missing anything "
                     "these candidates describe")
    for e in result["effects"]:
        units = e.get("units", {})
        cis = ", ".join(f"{k} in [{lo:.4g}, {hi:.4g}] {units.get(k, '')}".rstrip() for k, (lo, hi) in e["ci95"].items())
        shaky = [k for k, ok in e.get("determined", {}).items() if not ok]
        lines.append(f"  {e['equation']}  ({e['channel']}; explains {100 * e['explained_fraction']:.1f} % of the "
                     f"residual; 95 % CI {cis})")
        if "nominal" in e:
            lines.append("    prior's value: " + ", ".join(f"{k} = {v:.4g} {units.get(k, '')}".rstrip()
                                                          for k, v in e["nominal"].items()))
        for name, why in e.get("held_nominal", {}).items():
            lines.append(f"    {name}: {why}")
        at_bound = [k for k, b in e.get("at_bound", {}).items() if b]
        if at_bound:
            lines.append(f"    at a physical bound, so not identified: {', '.join(at_bound)}")
        for key in ("note", "held_out"):
            if e.get(key):
                lines.append(f"    {e[key]}")
        shaky = [k for k in shaky if k not in e.get("held_nominal", {})]
        if shaky:
            lines.append(f"    not pinned down by this data: {', '.join(shaky)}")
        unclaimed = [k for k, claimed in e.get("claimed", {}).items() if not claimed and k in e["ci95"]]
        if unclaimed:
            lines.append(f"    not claimed (the interval holds the prior's value): {', '.join(unclaimed)}")
        for alt in e.get("alternatives", []):
            values = ", ".join(f"{k} = {v:.4g} {alt['units'].get(k, '')}".rstrip() for k, v in alt["params"].items())
            lines.append(f"    alternative: {alt['id']} with {values} {how_much(alt['fraction_of_chosen'])} "
                         f"(ΔBIC_eff {alt['delta_bic']:+g})")
    for c in result["confounded"]:
        lines.append(f"  {confounded_label(c)}: {c['note']}")
    if result.get("repair"):
        r = result["repair"]
        does = "improves" if r["improves"] else "does not improve"
        lines.append(f"  repair {does} the held-out flights: {r['reason']}")
    note = unchanged_prior_note(result)
    if note:
        lines.append(f"  {note}")
    median = " (median over flights)" if result.get("per_flight") else ""
    if "specific_force_rmse" in result["before"]:
        before, after = result["before"]["specific_force_rmse"], result["after"]["specific_force_rmse"]
        helped = result.get("improved_flights", {}).get("specific_force_rmse")
        lines.append(f"  body-frame specific force from the inputs alone, RMSE on held-out data (m/s², both sides "
                     f"low-passed at {result.get('lowpass_hz', LOWPASS_HZ):g} Hz): before {before:.4g}, after "
                     f"{after:.4g}" + (f"; better on {helped} flights" if helped else ""))
    methods = [m for m in result["before"] if m != "specific_force_rmse"]
    if methods:
        lines.append(f"  MSE on held-out data{median}   before        after")
    for m in methods:
        helped = result.get("improved_flights", {}).get(m)
        lines.append(f"    {m:<20}{result['before'][m]:>10.4g}  {result['after'][m]:>10.4g}"
                     + (f"   better on {helped} flights" if helped else ""))
    return "\n".join(lines)


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
