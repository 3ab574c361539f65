"""Pooled training whose residual scale is chosen by holding out whole groups of its own training flights.

`train_with_scale_choice` trains one pooled KNODE (`flights.train_on_flights`) on every group of flights (e.g.
trajectory families) and scales its residual (`models.residual_scale`) by the scale `models.residual_scale.choose_scale`
picks from how, for each group held out in turn, a KNODE pooled over the other groups carries the KNODE-UKF
through that group's mocap gaps against its prior UKF, at each candidate scale.
Only training flights take part: the flights the model is later scored on never do.  Why groups and not single
flights: flights of one family share their trajectory, so a held-out flight of a trained family cannot show
what the residual extrapolates to a new kind of flight (a held-out circle does not test a helix).

The inner scores use the UKF only (the MHE costs minutes per flight set; its gains followed the UKF's on every
family on the shared flights) and the default gap plan (`models.presets.GAP_S`, `GAP_EVERY_S`).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

from learnest.errors import InvalidInput
from learnest.estimators.mocap_gaps import gap_mask
from learnest.estimators.prepared import initial_state, model_system
from learnest.estimators.yardsticks import GapPlan, gap_scores, run_with_gaps
from learnest.ingest.flight import Flight
from learnest.models.inputs import calibrates_thrust_gain, system_inputs
from learnest.models.knode import HybridModel
from learnest.models.presets import CRAZYFLIE_TRAINING, MHE_HORIZON, TrainingConfig
from learnest.models.residual_scale import RESIDUAL_SCALES, choose_scale, scaled_model
from learnest.models.training import TrainingResult

from .flights import train_on_flights

PAIR = "knode-ukf_vs_ukf"
# What a model says when no scale passed on the held-out groups.
NO_SCALE = ("no residual scale beat the prior in the mocap gaps on every held-out group of training flights; "
            "this version equals its prior")


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
        Residual scales in [0, 1] (`models.residual_scale.scaled_residual`).
    plan : GapPlan, optional
        Where the mocap is hidden (default `GapPlan()`).
    cache : dict, optional
        Compiled functions (`estimators.evaluate.evaluate_sequence`'s ``mhe_cache``), keyed by the models' ids: share
        it only across calls whose models are all still alive (a freed model's id may be reused by another).

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
        system = model_system(knode, flight)
        u = system_inputs(flight, system, thrust_gain=calibrates_thrust_gain(knode.meta, knode.kind))
        y, x0 = flight.measurements(), initial_state(flight)
        inside = gap_mask(len(flight.t), windows)
        prior = HybridModel(system, "prior")
        base = run_with_gaps(["ukf"], prior, prior, y, u, flight.dt, system.Q, system.R, x0, system.P0, inside,
                             MHE_HORIZON, cache)["ukf"]["estimates"]
        for scale, model in models.items():
            model = HybridModel(system, model.kind, model.residual, model.meta)
            est = run_with_gaps(["knode-ukf"], prior, model, y, u, flight.dt, system.Q, system.R, x0, system.P0,
                                inside, MHE_HORIZON, cache)["knode-ukf"]["estimates"]
            gaps = gap_scores(flight.p, {"ukf": base, "knode-ukf": est}, windows, plan)
            out[scale].append({"flight": flight.name, "gain_pct": gaps.gain_pct[PAIR],
                               "interval_pct": gaps.gain_interval_pct[PAIR]})
    return out


def group_summary(rows: Sequence[Mapping]) -> dict:
    """{"gains_pct": [...], "median_gain_pct", "worse_beyond": flights whose interval lies below 0} of
    `gap_gains_by_scale`'s rows of one scale and group."""
    gains = [float(r["gain_pct"]) for r in rows if r["gain_pct"] is not None]
    worse = sum(1 for r in rows if r["interval_pct"] is not None and r["interval_pct"][1] < 0)
    return {"gains_pct": gains, "median_gain_pct": float(np.median(gains)) if gains else None, "worse_beyond": worse}


def train_with_scale_choice(groups: Mapping[str, Sequence[Flight]], system: str = "crazyflie",
                            config: TrainingConfig = CRAZYFLIE_TRAINING, scales: Sequence[float] = RESIDUAL_SCALES,
                            progress: Callable[[str], object] | None = None, **train_kwargs) -> TrainingResult:
    """One pooled KNODE on every group's flights, its residual scaled by the scale chosen on held-out groups.

    Parameters
    ----------
    groups : mapping
        {group name: its flights}, at least two groups (e.g. trajectory families of one vehicle).
    system : str
        The prior (`flights.FLIGHT_SYSTEMS`).
    config : TrainingConfig
        Training settings of every pooled training (the inner ones and the final one).
    scales : sequence of float
        Candidate residual scales (`models.residual_scale.RESIDUAL_SCALES`).
    progress : callable, optional
        Told each stage in words ("circle held out", "final training").
    **train_kwargs
        Passed to `flights.train_on_flights` (``blind_attitude``, ``blind_battery``, ``validate``...).

    Returns
    -------
    TrainingResult
        The final training's, its model scaled (`models.residual_scale.scaled_model`); the meta's
        ``residual_scale`` is the chosen scale and ``residual_scale_choice`` holds, per candidate scale and
        held-out group, the inner median gap gain (%), the flights' gains and how many were worse beyond their
        interval, and the seconds the choice took.  ``seconds`` includes the inner trainings and scores.

    Raises
    ------
    InvalidInput
        With fewer than two groups, or a group without flights.
    """
    import time

    if len(groups) < 2 or any(not flights for flights in groups.values()):
        raise InvalidInput("choosing the residual scale needs at least two groups of flights, each with flights "
                           f"(got {', '.join(f'{k}: {len(v)}' for k, v in groups.items()) or 'none'})")
    started = time.perf_counter()
    table: dict[float, list[dict]] = {s: [] for s in scales if s > 0}
    for held, scored in groups.items():
        if progress:
            progress(f"{held} held out")
        train = [f for name, flights in groups.items() if name != held for f in flights]
        inner = train_on_flights(train, config, system=system, **train_kwargs).model
        for scale, rows in gap_gains_by_scale(inner, scored, scales).items():
            table[scale].append({"group": held, **group_summary(rows)})
    chosen = choose_scale(table)
    choice_seconds = time.perf_counter() - started
    choice: dict = {"rule": "largest scale whose inner KNODE-UKF beats its prior UKF in the mocap gaps on the median "
                            "of every held-out group with no flight worse beyond its 95 % interval; else the scale "
                            "better than the prior on the most held-out flights",
                    "scales": {str(s): rows for s, rows in table.items()}, "chosen": chosen,
                    "seconds": choice_seconds}
    if progress:
        progress("final training")
    final = train_on_flights([f for flights in groups.values() for f in flights], config, system=system,
                             **train_kwargs)
    final.model = scaled_model(final.model, chosen, choice)
    if chosen == 0.0:   # the residual is switched off: this version equals its prior, and says so
        final.model.meta.update(learned=False, learned_note=NO_SCALE)
    final.seconds += choice_seconds
    return final
