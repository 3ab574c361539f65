"""Training on several flights with the residual's scale chosen on held-out groups of them: the one decision every
surface (`learnest train`, ``POST /models``, the web form, ``le.KNODE().fit(flights)``) calls (`train_flights`).

Why.  A residual pooled over several trajectory families of one vehicle learns the vehicle and, with it, regularities
of the trajectories it saw: on the shared NanoBench flights the whole residual carries the estimate through the mocap
gaps of a new family worse than its prior, while a fraction of it carries well (`models.residual_scale`; the results
page `docs/results/family-holdout.md`).  So the flights are put in groups (by default the trajectory family the log
declares), each group is held out in turn, a KNODE pooled over the other groups is scored in the held-out group's
mocap gaps (KNODE-UKF against its prior UKF) at each candidate scale, and the final KNODE, pooled over every flight,
gets the scale `models.residual_scale.choose_scale` picks.
Why groups and not single flights: flights of one family share their trajectory, so a held-out flight of a
trained family cannot show what the residual extrapolates to a new kind of flight (a held-out circle does not test
a helix).  With fewer than two groups there is nothing to hold out: the whole residual is trained (scale 1), and
the model says why (``residual_scale_note``).

Groups (``group_by``, `flight_groups`):

- ``"family"`` (the default): the trajectory family the log declares (NanoBench's ``trajectory_type``: circle,
  figure8, helix, ramp...); flights that declare none form one group, ``"undeclared"``;
- ``"name:REGEX"``: the first capture group of REGEX searched in each flight's name (``name:^(B\\d+)_`` groups
  NanoBench flights by their benchmark number); a flight whose name does not match is refused, named.  REGEX is
  Python's syntax, run by the `regex` package with a time limit (`PATTERN_TIMEOUT_S` per name): a pattern that
  backtracks without end (``^((a|aa)+)$``) is refused instead of holding a worker for hours;
- ``"none"``: no groups, the whole residual (the paper's pooled training).

Validation.  The flights held out whole from the epochs (``validate``; by default one in five of all the flights,
`estimators.flight_training.default_validation` in the given order) are decided once, before any training
(`held_out_names`): each inner training keeps those among its flights, the final one keeps them all.  A stored
training decides them the same way when its job is created (its version lists them), so a training in a notebook
and one through the registry hold out the same flights in every inner training, and give the same model.

The inner scores use the UKF only (the MHE costs minutes per flight set; its gains followed the UKF's on every
family on the shared flights) and the default gap plan (`models.presets.GAP_S`, `GAP_EVERY_S`).  Only training
flights take part: the flights the model is later scored on never do.
"""
from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import replace

import numpy as np
import regex

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.models.knode import HybridModel
from learnest.models.noise import IDENTIFIED, NOISE_SOURCES, PAPER
from learnest.models.presets import CRAZYFLIE_TRAINING, MHE_HORIZON, TrainingConfig
from learnest.models.residual_scale import RESIDUAL_SCALES, choose_scale, passes, scaled_model
from learnest.models.training import TrainingResult

from .algorithm1 import Algorithm1
from .flight_training import default_validation
from .metrics import worse_beyond_interval
from .mocap_gaps import gap_mask
from .noise_identification import with_identified_noise
from .prepared import prepare
from .yardsticks import GapPlan, gap_scores, run_with_gaps

PAIR = "knode-ukf_vs_ukf"
PATTERN_TIMEOUT_S = 0.5        # a name:REGEX search on one flight name (names are at most ~100 characters)
GROUP_BY = "family"            # the default grouping
UNDECLARED = "undeclared"      # the group of flights whose log declares no trajectory family
# What a model says when no scale passed on the held-out groups.
NO_SCALE = ("no residual scale was better than the prior in the mocap gaps on any held-out flight of the "
            "training groups; this version equals its prior")
RULE = ("largest scale whose inner KNODE-UKF beats its prior UKF in the mocap gaps on the median of every held-out "
        "group with no flight worse beyond its 95 % interval; else the scale better than the prior on the most "
        "held-out flights")
# A stage callback: (stage in words, its index from 0, how many stages).
StageCallback = Callable[[str, int, int], object]


# -- groups ---------------------------------------------------------------------------------------------------
def group_rule(group_by: str) -> regex.Pattern | None:
    """The name pattern of a ``"name:REGEX"`` grouping, None for ``"family"`` and ``"none"``.

    Raises
    ------
    InvalidInput
        For any other value, a REGEX that does not compile, or one without exactly one capture group.
    """
    if group_by in (GROUP_BY, "none"):
        return None
    if not isinstance(group_by, str) or not group_by.startswith("name:"):
        raise InvalidInput(f"group_by must be 'family', 'none' or 'name:REGEX' (one capture group naming the "
                           f"group), got {group_by!r}")
    try:
        pattern = regex.compile(group_by.removeprefix("name:"))
    except regex.error as err:
        raise InvalidInput(f"group_by {group_by!r}: the pattern does not compile ({err})") from None
    if pattern.groups != 1:
        raise InvalidInput(f"group_by {group_by!r}: the pattern needs exactly one capture group (it names the "
                           f"group), it has {pattern.groups}")
    return pattern


def declared_family(meta: Mapping) -> str | None:
    """The trajectory family a flight's log declares (NanoBench ``trajectory_type`` in its meta), or None."""
    family = (meta.get("nanobench") or {}).get("trajectory_type")
    return str(family) if family else None


def flight_groups(flights: Sequence[Flight], group_by: str = GROUP_BY) -> dict[str, list[Flight]]:
    """{group name: its flights, in the given order} under ``group_by`` (the module docstring's rules).

    Raises
    ------
    InvalidInput
        A bad ``group_by`` (`group_rule`), or a flight whose name the ``name:REGEX`` pattern does not match.
    """
    names = group_names([(flight.name, flight.meta) for flight in flights], group_by)
    groups: dict[str, list[Flight]] = {}
    for flight, name in zip(flights, names):
        groups.setdefault(name, []).append(flight)
    return groups


def group_names(flights: Sequence[tuple[str, Mapping]], group_by: str = GROUP_BY) -> list[str]:
    """The group of each (flight name, flight meta) under ``group_by``, in the given order: what `flight_groups`
    goes by, for flights known by their stored rows alone (a job's quota counts its groups before it starts).

    Raises
    ------
    InvalidInput
        A bad ``group_by`` (`group_rule`), a flight whose name the ``name:REGEX`` pattern does not match, or a
        pattern that takes longer than `PATTERN_TIMEOUT_S` on a name.
    """
    pattern = group_rule(group_by)
    if group_by == "none":
        return ["all"] * len(flights)
    names, unmatched = [], []
    for flight_name, meta in flights:
        if pattern is None:
            names.append(declared_family(meta) or UNDECLARED)
            continue
        try:
            match = pattern.search(flight_name, timeout=PATTERN_TIMEOUT_S)
        except TimeoutError:
            raise InvalidInput(f"group_by {group_by!r}: the pattern took more than {PATTERN_TIMEOUT_S:g} s on the "
                               f"name {flight_name!r} (it backtracks too much: nested repetitions like (a+)+); "
                               "simplify it") from None
        if match is None or not match.group(1):
            unmatched.append(flight_name)
            continue
        names.append(match.group(1))
    if unmatched:
        raise InvalidInput(f"group_by {group_by!r} names no group for flight(s) {', '.join(unmatched)}: the pattern "
                           "must match every flight's name")
    return names


def why_no_choice(flights: Sequence[Flight], groups: Mapping[str, Sequence[Flight]], group_by: str) -> str:
    """Why a training with fewer than two groups keeps the whole residual, in words."""
    if group_by == "none":
        return "grouping switched off (group by none): the whole residual, no scale chosen"
    if len(flights) == 1:
        return "one flight (the paper's protocol): nothing to hold out"
    only = next(iter(groups), "")
    if group_by == GROUP_BY:
        if only == UNDECLARED:
            return "no trajectory family declared in the logs: nothing to hold out; the whole residual"
        return f"one trajectory family ({only}): nothing to hold out; the whole residual"
    return f"one group ({only}) by {group_by}: nothing to hold out; the whole residual"


# -- the gap scores of each scale -----------------------------------------------------------------------------
def gap_gains_by_scale(knode: HybridModel, flights: Sequence[Flight], scales: Sequence[float] = RESIDUAL_SCALES,
                       plan: GapPlan | None = None, cache: dict | None = None) -> dict[float, list[dict]]:
    """The KNODE-UKF's gap gain over the prior UKF on each flight, at each residual scale.

    Parameters
    ----------
    knode : HybridModel
        The trained KNODE (scale 1).
    flights : sequence of Flight
        Flights to score; those failing the quality checks or too short for one gap are skipped.
    scales : sequence of float
        Residual scales in [0, 1] (`models.residual_scale.scaled_residual`); 0 (the prior) is not scored.
    plan : GapPlan, optional
        Where the mocap is hidden (default `GapPlan()`).
    cache : dict, optional
        Compiled functions (`estimators.evaluate.evaluate_sequence`'s ``mhe_cache``).

    Returns
    -------
    dict
        {scale: [{"flight": name, "gain_pct": float, "interval_pct": [lo, hi] or None}, ...]}, gains in % of the
        prior's mean squared gap position error.
    """
    plan = plan or GapPlan()
    cache = {} if cache is None else cache
    models = {s: scaled_model(knode, s) for s in scales if s > 0}
    out: dict[float, list[dict]] = {s: [] for s in models}
    for flight in flights:
        windows = plan.windows(len(flight.t), flight.dt)
        if not flight.quality["ok"] or not windows:
            continue
        prepared = prepare(knode, flight)
        y, u, prior = prepared.y, prepared.u, prepared.prior_params
        inside = gap_mask(len(flight.t), windows)
        base = run_with_gaps(["ukf"], prior, prior, y, u, inside, MHE_HORIZON, cache)["ukf"]["estimates"]
        for scale, model in models.items():
            # the scaled residual runs with the trained KNODE's noise on this flight
            scaled = replace(prepared.params,
                             model=HybridModel(prepared.model.system, model.kind, model.residual, model.meta))
            est = run_with_gaps(["knode-ukf"], prior, scaled, y, u, inside, MHE_HORIZON,
                                cache)["knode-ukf"]["estimates"]
            gaps = gap_scores(flight.p, {"ukf": base, "knode-ukf": est}, windows, plan)
            out[scale].append({"flight": flight.name, "gain_pct": gaps.gain_pct[PAIR],
                               "interval_pct": gaps.gain_interval_pct[PAIR]})
    return out


def group_summary(rows: Sequence[Mapping]) -> dict:
    """{"gains_pct": [...], "median_gain_pct", "worse_beyond": flights worse beyond their interval
    (`estimators.metrics.worse_beyond_interval`)} of `gap_gains_by_scale`'s rows of one scale and group."""
    gains = [float(r["gain_pct"]) for r in rows if r["gain_pct"] is not None]
    worse = sum(1 for r in rows if worse_beyond_interval(r["interval_pct"]))
    return {"gains_pct": gains, "median_gain_pct": float(np.median(gains)) if gains else None, "worse_beyond": worse}


# -- training -------------------------------------------------------------------------------------------------
def held_out_names(flights: Sequence[Flight], validate: Sequence[str] | None) -> list[str] | None:
    """The names of the flights held out whole from the epochs: ``validate`` as given, or (None or empty) the default
    validation of all ``flights`` in their order (`estimators.flight_training.default_validation`: one in five),
    None when that holds out nothing (a single flight: the paper's time blocks).

    Why decided once for all the flights: an inner training that picked its own one in five among its own
    flights would hold out other flights than a stored training, whose version names its validation flights
    before its job starts; the inner residuals, and so the chosen scale, would then depend on the surface.
    """
    if validate:
        return list(validate)
    names = [f.name for f in flights]
    return [names[i] for i in default_validation(len(names))] or None


def _fit(flights: Sequence[Flight], config: TrainingConfig, system: str, validate: Sequence[str] | None,
         progress: Callable[[int, float], None] | None, **train_kwargs) -> TrainingResult:
    """`Algorithm1.fit_flights` (the paper's filter observer) on ``flights``, validated on those ``validate``
    names among them; on the default validation when it names none of them or all of them."""
    names = {f.name for f in flights}
    held = [n for n in validate or () if n in names]
    return Algorithm1(config=config).fit_flights(flights, system, held if held and len(held) < len(names) else None,
                                                 progress=progress, **train_kwargs)


def train_with_scale_choice(groups: Mapping[str, Sequence[Flight]], system: str = "crazyflie",
                            config: TrainingConfig = CRAZYFLIE_TRAINING, scales: Sequence[float] = RESIDUAL_SCALES,
                            on_stage: StageCallback | None = None, progress: Callable[[int, float], None] | None = None,
                            validate: Sequence[str] | None = None, **train_kwargs) -> TrainingResult:
    """One pooled KNODE on every group's flights, its residual scaled by the scale chosen on held-out groups.

    Parameters
    ----------
    groups : mapping
        {group name: its flights}, at least two groups (e.g. trajectory families of one vehicle; `flight_groups`).
    system : str
        The prior (`estimators.prepared.FLIGHT_SYSTEMS`).
    config : TrainingConfig
        Training settings of every pooled training (the inner ones and the final one).
    scales : sequence of float
        Candidate residual scales (`models.residual_scale.RESIDUAL_SCALES`).
    on_stage : callable, optional
        ``on_stage(stage, index, count)`` before each stage: "circle held out" for each group, "final training".
    progress : callable, optional
        ``progress(epoch, mean_training_loss)`` after every epoch of every training.
    validate : sequence of str, optional
        Flights held out whole from the epochs (`Algorithm1.fit_flights`; default: one in five of all the groups'
        flights, listed group after group, `held_out_names`); an inner training keeps those among its flights
        (its own default validation when none or all of its flights are named).
    **train_kwargs
        Passed to `Algorithm1.fit_flights` (``blind_attitude``, ``blind_battery``).

    Returns
    -------
    TrainingResult
        The final training's, its model scaled (`models.residual_scale.scaled_model`); the meta's
        ``residual_scale`` is the chosen scale, ``residual_scale_groups`` the groups' names,
        ``residual_scale_note`` the choice in words, and ``residual_scale_choice`` holds the rule, the groups'
        flights, per held-out group the inner training's validation flights and kept epoch
        (``inner_trainings``), per candidate scale and held-out group the inner median gap gain (%), the flights'
        gains and how many were worse beyond their interval, and the seconds the choice took.  ``seconds`` includes the
        inner trainings and scores.

    Raises
    ------
    InvalidInput
        With fewer than two groups, or a group without flights.
    """
    if len(groups) < 2 or any(not flights for flights in groups.values()):
        raise InvalidInput("choosing the residual scale needs at least two groups of flights, each with flights "
                           f"(got {', '.join(f'{k}: {len(v)}' for k, v in groups.items()) or 'none'})")
    started = time.perf_counter()
    validate = held_out_names([f for flights in groups.values() for f in flights], validate)
    table: dict[float, list[dict]] = {s: [] for s in scales if s > 0}
    inner_trainings = {}
    for index, (held, scored) in enumerate(groups.items()):
        if on_stage:
            on_stage(f"{held} held out", index, len(groups) + 1)
        train = [f for name, flights in groups.items() if name != held for f in flights]
        inner = _fit(train, config, system, validate, progress, **train_kwargs).model
        inner_trainings[held] = {"validation_flights": [f["name"] for f in inner.meta["validation_flights"]],
                                 "best_epoch": inner.meta.get("best_epoch")}
        for scale, rows in gap_gains_by_scale(inner, scored, scales).items():
            table[scale].append({"group": held, **group_summary(rows)})
    chosen = choose_scale(table)
    seconds = time.perf_counter() - started
    choice = {"rule": RULE, "groups": {name: [f.name for f in flights] for name, flights in groups.items()},
              "inner_trainings": inner_trainings, "scales": {str(s): rows for s, rows in table.items()},
              "chosen": chosen, "seconds": seconds}
    if on_stage:
        on_stage("final training", len(groups), len(groups) + 1)
    final = _fit([f for flights in groups.values() for f in flights], config, system, validate, progress,
                 **train_kwargs)
    final.model = scaled_model(final.model, chosen, choice)
    final.model.meta.update(residual_scale_groups=list(groups), residual_scale_note=scale_note(table, chosen))
    if chosen == 0.0:   # the residual is switched off: this version equals its prior, and says so
        final.model.meta.update(learned=False, learned_note=NO_SCALE)
    final.seconds += seconds
    return final


def scale_note(table: Mapping[float, Sequence[Mapping]], chosen: float) -> str:
    """How `train_with_scale_choice` chose ``chosen``, in words: the groups held out, the rule that decided (the
    surfaces print it after the scale: "residual scale 0.25: chosen with circle, helix held out in turn: ...")."""
    held = ", ".join(str(g["group"]) for g in next(iter(table.values()), []))
    if chosen == 0.0:
        return (f"chosen with {held} held out in turn: no scale was better than the prior in the mocap gaps on any "
                "held-out flight; the residual is off")
    how = ("better than the prior in the mocap gaps on the median of every held-out group, no flight worse beyond "
           "its interval") if passes(table[chosen]) else \
        "no scale met the goal on every held-out group; this one was better than the prior on the most held-out flights"
    return f"chosen with {held} held out in turn: {how}"


def train_flights(flights: Sequence[Flight], system: str = "quadrotor", config: TrainingConfig = CRAZYFLIE_TRAINING,
                  group_by: str = GROUP_BY, validate: Sequence[str] | None = None,
                  progress: Callable[[int, float], None] | None = None, on_stage: StageCallback | None = None,
                  scales: Sequence[float] = RESIDUAL_SCALES, noise: str = PAPER,
                  **train_kwargs) -> TrainingResult:
    """Algorithm 1 on one flight or several of one vehicle, the residual's scale chosen on held-out groups of them,
    and, with ``noise="identified"``, the noise of the model and of its prior identified on all of them
    (`estimators.noise_identification`).

    With two groups or more (`flight_groups` under ``group_by``) this is `train_with_scale_choice`; with fewer,
    or ``group_by="none"``, `Algorithm1.fit_flights` with the whole residual, the meta's ``residual_scale`` 1.0 and
    ``residual_scale_note`` saying why no scale was chosen (`why_no_choice`).

    Parameters
    ----------
    flights : sequence of Flight
        The flights (training and validation), distinct names.
    system : {"quadrotor", "crazyflie"}
        The prior.
    config : TrainingConfig
        Training settings of every training.
    group_by : str
        ``"family"`` (default), ``"none"`` or ``"name:REGEX"`` (module docstring).
    validate : sequence of str, optional
        Names of the flights held out whole from the epochs (default: one in five of ``flights`` in the given
        order, decided once for every training: `held_out_names`).
    progress : callable, optional
        ``progress(epoch, mean_training_loss)`` after every epoch of every training.
    on_stage : callable, optional
        ``on_stage(stage, index, count)`` before each stage ("circle held out", "final training"; "training"
        when there is one stage).
    scales : sequence of float
        Candidate residual scales.
    noise : {"paper", "identified"}
        Keep the system's fixed noise (the paper's protocol, the default), or identify the model's and its
        prior's noise on ``flights`` (stored with the model).  The residual's scale is chosen with the fixed
        noise either way.
    **train_kwargs
        ``blind_attitude``, ``blind_battery`` (`Algorithm1.fit_flights`).

    Returns
    -------
    TrainingResult
        Its model's meta holds ``residual_scale``, ``residual_scale_groups`` (the groups' names) and
        ``residual_scale_note`` beside `Algorithm1.fit_flights`'s.

    Raises
    ------
    InvalidInput
        A bad ``group_by`` or what `Algorithm1.fit_flights` refuses.
    """
    flights = list(flights)
    if noise not in NOISE_SOURCES:
        raise InvalidInput(f"noise must be one of {', '.join(NOISE_SOURCES)}, not {noise!r}")
    groups = flight_groups(flights, group_by)
    if len(groups) >= 2:
        result = train_with_scale_choice(groups, system, config, scales, on_stage, progress,
                                         held_out_names(flights, validate), **train_kwargs)
        stages = len(groups) + 1
    else:
        if on_stage:
            on_stage("training", 0, 1)
        result = Algorithm1(config=config).fit_flights(flights, system, validate, progress=progress, **train_kwargs)
        result.model.meta.update(residual_scale=1.0, residual_scale_groups=list(groups),
                                 residual_scale_note=why_no_choice(flights, groups, group_by))
        stages = 1
    if noise == IDENTIFIED:
        started = time.perf_counter()
        # reported as the last stage, after the epochs: the progress never runs backwards
        stage = (lambda name: on_stage(name, stages, stages)) if on_stage else None
        result.model = with_identified_noise(result.model, flights, on_stage=stage)
        result.seconds += time.perf_counter() - started
    return result
