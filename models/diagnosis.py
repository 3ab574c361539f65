"""Tracing a residual to named effects: sparse selection, blocked validation, an autocorrelation-aware
information criterion, block-bootstrap intervals, and an honest "cannot tell apart".

A `ResidualProblem` is one channel of data in regression form, observed = predicted(θ) + e, exposed as
residual(values, rows) -> (len(rows), k).  Effects enter through their parameters (nominal = the prior).

Selection is greedy forward: at each step every remaining candidate is fitted together with those
already chosen (nonlinear least squares, scipy); the best by BIC_eff is kept only if it lowers BIC_eff
by more than DELTA_BIC and lowers the blocked cross-validation error.  BIC_eff replaces the sample count
by the effective number of independent samples N/τ (τ the integrated autocorrelation time): residuals of
smoothed or dynamic data are strongly autocorrelated, and counting every sample would claim effects
that are not there.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING, Any

import numpy as np

from .identifiability import combined_observable, sensitivity, tie_groups
from .residual_problem import Fit as Fit
from .residual_problem import ResidualProblem as ResidualProblem
from .residual_problem import bic_eff as bic_eff
from .residual_problem import common_bic as common_bic

if TYPE_CHECKING:
    from .effects import Effect

DELTA_BIC = 10.0          # "very strong" evidence on Kass & Raftery's scale
MIN_CV_GAIN = 0.0         # and it must not raise the held-out (blocked CV) error: it has to transfer
BOOTSTRAP_REPLICATES = 60
ALIKE_COSINE = 0.9        # sensitivities this parallel are "the same effect on this data"
MULTIPLE_SHARE = 1.05     # a rival's share of the chosen effect's gain from here up is told as a multiple
# A rival that, in place of a chosen effect, removes this fraction of the residual the chosen one removes is
# an alternative explanation, whatever the BIC says: with many samples a small misfit of the prior (a sensor
# filter, drag) moves BIC_eff by tens, so a BIC margin alone would hide a tilt behind a bias.
ALTERNATIVE_FRACTION = 0.9


def _all_values(candidates, chosen_values=None):
    values = {}
    for effect in candidates:
        values.update(effect.nominal())
    values.update(chosen_values or {})
    return values


def fit(problem: ResidualProblem, effects: list, rows: np.ndarray | None = None,
        offset: np.ndarray | None = None, start: dict[str, float] | None = None,
        base: dict[str, float] | None = None) -> Fit:
    """Least squares over the parameters of `effects`, every other candidate at its nominal value.

    Bounded trust-region fit (scipy ``least_squares``) on ``rows`` (default all); ``offset`` (same shape as
    the residual) is added to the residual (bootstrap replicates).  It starts at ``start`` ({parameter name:
    value}, e.g. an earlier fit's values) when given, else at each parameter's ``initial`` moved to the best
    point of its coarse scan (parameters with a ``scan_step``).  ``base`` holds values of other parameters,
    kept fixed (default: every other candidate nominal).
    """
    from scipy.optimize import least_squares  # scipy.optimize costs ~1 s to import: loaded on first use

    rows = np.arange(problem.n_rows) if rows is None else rows
    params = [p for e in effects for p in e.params if p.name not in problem.frozen]
    base = {**_all_values(problem.candidates), **(base or {})}

    def residual_of(theta):
        values = {**base, **{p.name: v for p, v in zip(params, theta)}}
        r = problem.residual(values, rows)
        return r if offset is None else r + offset

    if params:
        lower, upper = [p.lower for p in params], [p.upper for p in params]
        if start is not None:
            x0 = np.clip([start[p.name] for p in params], lower, upper)
        else:
            x0 = np.clip([p.initial for p in params], lower, upper)
            x0 = _scanned_start(params, x0, lambda th: float(np.sum(residual_of(th) ** 2)))
        solution = least_squares(lambda th: residual_of(th).ravel(), x0, method="trf", x_scale="jac",
                                 bounds=(lower, upper))
        theta = solution.x
    else:
        theta = np.zeros(0)
    r = residual_of(theta)
    bic, tau = bic_eff(r, len(params))
    return Fit(list(effects), {p.name: float(v) for p, v in zip(params, theta)}, r, float(np.sum(r**2)), bic, tau)


def _scanned_start(params: list, x0: np.ndarray, cost: Callable) -> np.ndarray:
    """x0 with each parameter that has a ``scan_step`` moved to the best point of a grid over its bounds
    (the others held at x0): a local fit of a non-convex parameter (a delay) then starts in the right dip."""
    x0 = np.array(x0, dtype=float)
    for i, p in enumerate(params):
        if p.scan_step:
            # whole multiples of the step: 0 must be exactly 0 (scipy's trust region starts with a radius of
            # |x0| in Jacobian units, so a start at 1e-16 from float round-off never moves)
            grid = np.round(np.arange(p.lower, p.upper + 0.5 * p.scan_step, p.scan_step) / p.scan_step) * p.scan_step
            grid = np.clip(grid, p.lower + 1e-3 * p.scan_step, p.upper - 1e-3 * p.scan_step)   # off the bounds
            costs = [cost(np.r_[x0[:i], value, x0[i + 1:]]) for value in grid]
            x0[i] = grid[int(np.argmin(costs))]
    return x0


def cv_error(problem: ResidualProblem, effects: list) -> float:
    """Blocked cross-validation: fit without each block, score on it (never random samples)."""
    everything = np.arange(problem.n_rows)
    errors = []
    for block in problem.blocks:
        train = np.setdiff1d(everything, block)
        fitted = fit(problem, effects, train)
        held_out = problem.residual({**_all_values(problem.candidates), **fitted.values}, block)
        errors.append(np.mean(held_out**2))
    return float(np.mean(errors))


def confounded_pairs(problem: ResidualProblem, chosen: list, values: dict, near_ties: list) -> list[dict]:
    """Chosen effects that another candidate explains about as well (BIC_eff within DELTA_BIC, or removing
    at least ALTERNATIVE_FRACTION of the residual the chosen one removes), with the pair of parameters whose
    sensitivities are most nearly parallel as the reason.

    ``near_ties`` is a list of (chosen effect, rival effect, ΔBIC_eff[, fraction]) where fraction is the share
    of the chosen effect's RSS reduction the rival achieves in its place; ``chosen`` is not used.  An entry
    admitted by the fraction alone (ΔBIC_eff ≥ DELTA_BIC) has ``data_prefer`` = the chosen effect's id: the
    criterion does choose (residual and number of parameters together); otherwise ``data_prefer`` is None.
    """
    allv = _all_values(problem.candidates, values)
    out = []
    for a, b, delta_bic, *rest in near_ties:
        fraction = rest[0] if rest else None
        A, B = sensitivity(problem, allv, a.params), sensitivity(problem, allv, b.params)
        norms = np.linalg.norm(A, axis=0)[:, None] * np.linalg.norm(B, axis=0)[None, :]
        with np.errstate(invalid="ignore", divide="ignore"):
            cosine = np.nan_to_num(np.abs(A.T @ B) / norms)
        i, j = np.unravel_index(np.argmax(cosine), cosine.shape)
        pa, pb, c = a.params[i].name, b.params[j].name, float(cosine[i, j])
        preferred = delta_bic >= DELTA_BIC     # admitted by the fraction rule only: BIC_eff does choose
        if preferred:
            alike = (f"{pa} and {pb} act alike on most of this data (cosine {c:.3f})" if c >= ALIKE_COSINE else
                     f"the two act differently (largest cosine {c:.3f}, {pa} vs {pb})")
            why = (f"{alike}; the data prefer {a.id} by BIC_eff (residual and number of parameters together), "
                   f"and more varied motion (thrust, speed) would make that certain")
        elif c >= ALIKE_COSINE:
            why = (f"{pa} and {pb} act alike on this data (cosine {c:.3f}): they cannot be told apart here, and "
                   f"data with more varied motion (thrust, speed) would separate them")
        else:
            why = (f"the two act differently (largest cosine {c:.3f}, {pa} vs {pb}) yet fit about equally well: "
                   f"the data cannot choose between these explanations; more flights would")
        if not preferred or fraction is None:
            how_well = f"BIC_eff within {DELTA_BIC:g}"
        elif fraction >= MULTIPLE_SHARE:
            how_well = (f"it removes {fraction:.1f}× the residual {a.id} removes, but with more parameters its "
                        f"BIC_eff is {delta_bic:g} worse")
        else:
            how_well = f"ΔBIC_eff {delta_bic:g}, but it removes {100 * fraction:.0f} % of the residual {a.id} removes"
        out.append({"effects": [a.id, b.id], "params": [pa, pb], "cosine": round(c, 4), "delta_bic": delta_bic,
                    "fraction_of_chosen": None if fraction is None else round(float(fraction), 4),
                    "data_prefer": a.id if preferred else None,
                    "note": f"{b.id} explains the residual about as well as {a.id} ({how_well}); {why}"})
    return out


def bootstrap_ci(problem: ResidualProblem, final: Fit, replicates: int = BOOTSTRAP_REPLICATES,
                 seed: int = 0) -> dict[str, list[float]]:
    """95 % intervals by a moving-block bootstrap of the residual rows (blocks keep the autocorrelation).

    Returns {parameter name: [2.5 %, 97.5 %] percentile} for each fitted parameter of ``final``
    (empty if it has no effects); the block length is 2τ, clipped to [5, n/5] rows.
    """
    if not final.effects or len(final.residual) < 2:
        return {}      # nothing fitted, or no rows to resample (a problem without samples is refused upstream)
    rng = np.random.default_rng(seed)
    r = final.residual
    n = len(r)
    block = int(np.clip(np.ceil(2 * final.tau), 5, max(5, n // 5)))
    samples: dict[str, list[float]] = {name: [] for name in final.values}
    for _ in range(replicates):
        starts = rng.integers(0, n - block + 1, size=int(np.ceil(n / block)))
        resampled = np.concatenate([r[s:s + block] for s in starts])[:n]
        # observed* = fitted + e*; each replicate starts from the fit it perturbs (no scan: it is in the dip)
        refit = fit(problem, final.effects, offset=resampled - r, start=final.values)
        for name, value in refit.values.items():
            samples[name].append(value)
    return {name: [float(np.percentile(v, 2.5)), float(np.percentile(v, 97.5))] for name, v in samples.items()}


def _claimed(param, interval) -> bool:
    """The interval excludes the prior's value: the data say this parameter differs from the prior."""
    return bool(interval is not None and not interval[0] <= param.nominal <= interval[1])


# a fit this close to a bound (fraction of the physical range) sits on it: the data pushed the parameter as
# far as physics allows, so the value is the bound's, not the data's
AT_BOUND_FRACTION = 0.005
# a parameter whose return to the prior's value costs less than this fraction of the residual (RSS) the
# prior leaves explains nothing worth claiming, whatever its interval says
MIN_PARAM_SHARE = 0.002
# two chosen effects cancel when their contributions to the residual point opposite ways (cosine below
# this) and each is larger than what they add up to by this factor: the pair fits noise or a third effect
# with opposite large values (an accelerometer bias against a tilt), and neither value is physical
CANCEL_COSINE = -0.5
CANCEL_RATIO = 2.0


def _at_bound(param, value) -> bool:
    """``value`` lies within `AT_BOUND_FRACTION` of the physical range from ``param``'s lower or upper bound."""
    margin = AT_BOUND_FRACTION * (param.upper - param.lower)
    return bool(value <= param.lower + margin or value >= param.upper - margin)


def _contribution(problem: ResidualProblem, values: dict, effect) -> np.ndarray:
    """What ``effect`` at ``values`` changes in the residual against it at its nominal values (flattened)."""
    rows = np.arange(problem.n_rows)
    allv = _all_values(problem.candidates, values)
    return (problem.residual({**allv, **effect.nominal()}, rows) - problem.residual(allv, rows)).ravel()


def cancelling(problem: ResidualProblem, values: dict, a, b) -> dict | None:
    """The pair (a, b) of effects at ``values`` cancel each other (see `CANCEL_COSINE`): returns
    {"cosine", "ratio"} when they do, else None."""
    ca, cb = _contribution(problem, values, a), _contribution(problem, values, b)
    na, nb, nab = np.linalg.norm(ca), np.linalg.norm(cb), np.linalg.norm(ca + cb)
    if na == 0 or nb == 0:
        return None
    cosine = float(ca @ cb / (na * nb))
    ratio = float(min(float(na), float(nb)) / max(float(nab), 1e-300))
    return {"cosine": round(cosine, 4), "ratio": round(ratio, 2)} \
        if cosine < CANCEL_COSINE and ratio > CANCEL_RATIO else None


def _determined(param, interval) -> bool:
    """The data pin the parameter down: its interval excludes the prior's value or is narrow (< 5 % of
    the physical range).  Otherwise the value is reported but should not be trusted."""
    if interval is None:
        return False
    lo, hi = interval
    return bool(not lo <= param.nominal <= hi or hi - lo < 0.05 * (param.upper - param.lower))


def select_effects(problem: ResidualProblem, max_effects: int = 3, min_cv_gain: float = MIN_CV_GAIN,
                   on_stage: Callable[[str, float], None] | None = None) -> dict:
    """Forward selection; returns the chosen effects with values, intervals, explained fractions, the
    confounded pairs and the selection trace.

    An effect is kept only if it lowers BIC_eff by more than ``DELTA_BIC`` and the blocked cross-validation
    error by more than the fraction ``min_cv_gain`` (default ``MIN_CV_GAIN``: any gain), and only if it does
    not cancel an effect already chosen (`cancelling`: then the pair is reported in ``confounded`` with
    ``cancelling`` True and the simpler, earlier explanation stays alone).

    A fitted parameter is *identified* (and claimed) only when its 95 % interval excludes the prior's value,
    it does not sit on a physical bound (`AT_BOUND_FRACTION`), and returning it to the prior's value costs at
    least `MIN_PARAM_SHARE` of the residual the prior leaves, and only when the data can determine it: never a
    parameter of ``problem.undetermined`` (the data's own excitation cannot determine it), nor one of a chosen
    effect that another explains alike (a tie, `identifiability.is_tie`).  Such parameters get no interval; a tie
    is reported with the one combined observable its effects determine, its interval joint over the tied set.
    A repair uses ``values_identified``: the identified parameters refitted with every other one at the
    prior's value.

    Returns
    -------
    dict
        ``channel``; ``effects`` (per chosen effect: ``id``, ``target``, ``params``, ``held_nominal``,
        ``nominal``, ``units``, ``ci95``, ``determined``, ``identified`` and ``claimed`` (the same: see above),
        ``at_bound``, ``bounds`` [lower, upper], ``explained_by_param`` (share of the prior's RSS each parameter
        removes),
        ``explained_fraction`` of the baseline RSS, ``equation``, ``alternatives``: every rival within the
        criterion's threshold (BIC_eff within ``DELTA_BIC``, or removing ≥ ``ALTERNATIVE_FRACTION`` of the
        residual the effect removes) with ``id``, ``params`` it would take in the effect's place, ``units``,
        ``delta_bic``, ``fraction_of_chosen``), ``undetermined`` {param: why it is not claimed}), sorted by
        explained fraction; ``confounded`` (a tie's entries with ``tie`` True); ``ties`` (each: ``effects``,
        ``combined``, `identifiability.combined_observable`); ``excitation`` (the problem's); ``values``;
        ``values_identified``;
        ``rss_before``; ``rss_after``;
        ``trace``; ``fit`` (the final `Fit`); ``candidates`` (every candidate: ``id``, ``target``, ``chosen``,
        ``params`` fitted on its own, ``nominal``, ``units``, ``delta_bic_alone`` its BIC_eff change alone).

    ``on_stage``, when given, is called as ``on_stage(name, fraction)`` before each candidate is fitted
    ("fitting effects on <channel> (<effect>, i/M)") and before the bootstrap intervals, with the fraction
    (0..1, non-decreasing) of the selection done: each of the ``max_effects`` steps and the bootstrap count
    as one equal part.
    """
    current = fit(problem, [])
    baseline_rss = current.rss
    current, chosen, trace, near_ties, cancelled, alternatives, alone, alone_delta = \
        _forward_selection(problem, current, max_effects, min_cv_gain, on_stage)
    if on_stage is not None:
        on_stage(f"fitting effects on {problem.name} (bootstrap intervals)", max_effects / (max_effects + 1))
    intervals = bootstrap_ci(problem, current)
    confounded = confounded_pairs(problem, chosen, current.values, near_ties) + cancelled
    ties, unclaimable = _ties(problem, chosen, current, confounded)
    at_bound, share, identified, values_identified = _identified(problem, chosen, current, intervals, baseline_rss,
                                                                 unclaimable)
    results = _effect_results(problem, chosen, current, {k: v for k, v in intervals.items() if k not in unclaimable},
                              baseline_rss, at_bound, share, identified, alternatives)
    for e in results:
        e["undetermined"] = {p: why for p, why in unclaimable.items() if p in e["params"]}
    candidates = [{"id": e.id, "target": e.target, "chosen": e in chosen,
                   "params": {p.name: alone[e.id].values.get(p.name, p.nominal) for p in e.params}
                   if e.id in alone else e.nominal(),
                   "nominal": e.nominal(), "units": {p.name: p.unit for p in e.params},
                   "delta_bic_alone": alone_delta.get(e.id)}
                  for e in problem.candidates]
    return {"channel": problem.name, "effects": results, "confounded": confounded, "ties": ties,
            "excitation": problem.excitation, "values": current.values,
            "values_identified": values_identified,
            "rss_before": baseline_rss, "rss_after": current.rss, "trace": trace, "fit": current,
            "candidates": candidates}


def _forward_selection(problem: ResidualProblem, current: Fit, max_effects: int, min_cv_gain: float,
                       on_stage: Callable[[str, float], None] | None = None):
    """`select_effects`' forward selection: ``(current, chosen, trace, near_ties, cancelled, alternatives,
    alone, alone_delta)``, the final `Fit`, the chosen effects in order, each step's record, the rivals
    within the threshold, the cancelling pairs, each chosen effect's alternatives, and each candidate fitted
    alone with its BIC_eff change.  ``current`` is the fit of no effect."""
    current_cv = cv_error(problem, [])
    chosen: list[Effect] = []
    trace: list[dict[str, Any]] = []
    near_ties: list[tuple[Effect, Effect, float, float]] = []
    cancelled: list[dict[str, Any]] = []
    alternatives: dict[str, list[dict[str, Any]]] = {}    # chosen effect id -> rivals that explain as much
    alone: dict[str, Fit] = {}     # each candidate fitted on its own (the first step)
    alone_delta: dict[str, float] = {}   # and its BIC_eff change against no effect
    excluded: list[Effect] = []    # rivals that cancel a chosen effect: never tried again
    while len(chosen) < max_effects:
        remaining = [e for e in problem.candidates if e not in chosen and e not in excluded]
        if not remaining:
            break
        trials = _trials(problem, chosen, remaining, on_stage, len(chosen) / (max_effects + 1), 1 / (max_effects + 1))
        # one N_eff for all models compared at this step (see common_bic): the τ of the best-fitting
        # candidate's residual, the best estimate here of how correlated the noise is
        tau = min(trials, key=lambda f: f.rss).tau
        bic = {id(f): common_bic(f, tau) for f in [current, *trials]}
        trials.sort(key=lambda f: bic[id(f)])
        if not chosen:
            alone = {t.effects[-1].id: t for t in trials}
            alone_delta = {t.effects[-1].id: round(float(bic[id(t)] - bic[id(current)]), 2) for t in trials}
        best = trials[0]
        step: dict[str, Any] = {"tau": round(float(tau), 2),
                                "candidates": {t.effects[-1].id: round(float(bic[id(t)] - bic[id(current)]), 2)
                                               for t in trials}}
        if bic[id(best)] > bic[id(current)] - DELTA_BIC:
            step["stop"] = "no candidate lowers BIC_eff enough"
            trace.append(step)
            break
        pairs = _cancelling_pairs(problem, chosen, best, round(float(bic[id(best)] - bic[id(current)]), 2))
        if pairs:
            # never both: the simpler explanation (the one already chosen) stays, the pair is reported
            rival = best.effects[-1]
            cancelled += pairs
            step["cancelled"] = [pair["effects"][0] for pair in pairs] + [rival.id]
            # left out of the next steps, not out of the problem: its parameters stay in every fit's values
            # (at their nominal), which the residuals look up by name
            excluded.append(rival)
            trace.append(step)
            continue
        cv = cv_error(problem, chosen + [best.effects[-1]])
        step["cv_gain"] = round(1 - cv / current_cv, 4) if current_cv > 0 else 0.0
        if cv > (1 - min_cv_gain) * current_cv:
            step["stop"] = f"{best.effects[-1].id} does not improve held-out error"
            trace.append(step)
            break
        gain = current.rss - best.rss
        for t in trials[1:]:
            fraction = (current.rss - t.rss) / gain if gain > 0 else 0.0
            if bic[id(t)] - bic[id(best)] < DELTA_BIC or fraction >= ALTERNATIVE_FRACTION:
                rival, delta_bic = t.effects[-1], round(float(bic[id(t)] - bic[id(best)]), 2)
                near_ties.append((best.effects[-1], rival, delta_bic, fraction))
                alternatives.setdefault(best.effects[-1].id, []).append(
                    {"id": rival.id, "params": {p.name: t.values.get(p.name, p.nominal) for p in rival.params},
                     "units": {p.name: p.unit for p in rival.params}, "delta_bic": delta_bic,
                     "fraction_of_chosen": round(float(fraction), 4)})
        chosen.append(best.effects[-1])
        current, current_cv = best, cv
        step["chosen"] = best.effects[-1].id
        trace.append(step)
    return current, chosen, trace, near_ties, cancelled, alternatives, alone, alone_delta


def _trials(problem: ResidualProblem, chosen: list, remaining: list, on_stage, start: float, width: float) -> list:
    """Each of ``remaining`` fitted together with ``chosen``; ``on_stage`` told before each, the fraction
    moving from ``start`` across ``width``."""
    trials = []
    for i, effect in enumerate(remaining):
        if on_stage is not None:
            on_stage(f"fitting effects on {problem.name} ({effect.id}, {i + 1}/{len(remaining)})",
                     start + width * i / len(remaining))
        trials.append(fit(problem, chosen + [effect]))
    return trials


def _cancelling_pairs(problem: ResidualProblem, chosen: list, best: Fit, delta_bic: float) -> list[dict[str, Any]]:
    """The ``confounded`` entries of each chosen effect that ``best``'s new effect cancels (`cancelling`)."""
    rival = best.effects[-1]
    pairs = []
    for c in chosen:
        how = cancelling(problem, best.values, c, rival)
        if how:
            pairs.append({
                "effects": [c.id, rival.id], "params": [c.params[0].name, rival.params[0].name],
                "cosine": how["cosine"], "delta_bic": delta_bic,
                "fraction_of_chosen": None, "data_prefer": None, "cancelling": True,
                "note": (f"{rival.id} and {c.id} fitted together cancel each other (their contributions point "
                         f"opposite ways, cosine {how['cosine']:.2f}, each {how['ratio']:.1f}× larger than "
                         f"their sum): their joint values are not physical, so {rival.id} is not added and "
                         f"{c.id} is kept alone")})
    return pairs


def _ties(problem: ResidualProblem, chosen: list, current: Fit, confounded: list) -> tuple[list[dict], dict]:
    """The tied sets among ``confounded`` (`identifiability.tie_groups`), each with its combined observable
    (`identifiability.combined_observable`, led by the chosen effect), and {parameter: why it is not claimed}:
    the excitation's undetermined parameters and every parameter of a tied set's chosen effects."""
    unclaimable = dict(problem.undetermined)
    by_id = {e.id: e for e in problem.candidates}
    ties = []
    for group in tie_groups(confounded, problem.undetermined):
        members = sorted((by_id[i] for i in group), key=lambda e: e not in chosen)   # a chosen effect leads
        tie = {"effects": [e.id for e in members],
               "combined": combined_observable(problem, members, current.values, fit,
                                               tuple(e for e in chosen if e not in members))}
        for e in members:
            for p in e.params:
                if e in chosen and p.name not in unclaimable:
                    unclaimable[p.name] = (f"tied with {', '.join(i for i in tie['effects'] if i != e.id)}: the two "
                                           "explain the residual alike, so neither is claimed (see ties)")
        ties.append(tie)
    return ties, unclaimable


def _identified(problem: ResidualProblem, chosen: list, current: Fit, intervals: dict, baseline_rss: float,
                unclaimable: dict | None = None):
    """``(at_bound, share, identified, values_identified)`` of the chosen effects' parameters (see
    `select_effects`): on a bound, share of the prior's RSS, identified, and the values a repair may use.
    Parameters in ``unclaimable`` (undetermined by the excitation, or tied) are never identified."""
    unclaimable = unclaimable or {}
    everything = np.arange(problem.n_rows)
    allv = _all_values(problem.candidates, current.values)
    at_bound = {p.name: _at_bound(p, current.values[p.name]) for e in chosen for p in e.params
                if p.name in current.values}
    share = {}
    for e in chosen:
        for p in e.params:
            if p.name in current.values:
                r = problem.residual({**allv, p.name: p.nominal}, everything)
                share[p.name] = float((np.sum(r**2) - current.rss) / baseline_rss) if baseline_rss > 0 else 0.0
    identified = {name: bool(_claimed(p, intervals.get(name)) and not at_bound[name] and name not in unclaimable
                             and share.get(name, 0.0) >= MIN_PARAM_SHARE)
                  for e in chosen for p in e.params for name in [p.name] if name in at_bound}
    # the values a repair may use: identified parameters refitted with the others at the prior's values
    values_identified = dict(current.values)
    if chosen and not all(identified.values()):
        held = {name: "not identified" for name, ok in identified.items() if not ok}
        kept = [e for e in chosen if any(identified.get(p.name) for p in e.params)]
        values_identified = fit(replace(problem, frozen={**problem.frozen, **held}), kept).values if kept else {}
    return at_bound, share, identified, values_identified


def _effect_results(problem: ResidualProblem, chosen: list, current: Fit, intervals: dict, baseline_rss: float,
                    at_bound: dict, share: dict, identified: dict, alternatives: dict) -> list[dict[str, Any]]:
    """`select_effects`' ``effects``: one entry per chosen effect, largest explained fraction first."""
    results: list[dict[str, Any]] = []
    for effect in chosen:
        without_rss = fit(problem, [e for e in chosen if e is not effect]).rss if len(chosen) > 1 else baseline_rss
        results.append({"id": effect.id, "target": effect.target,
                        "params": {p.name: current.values.get(p.name, p.nominal) for p in effect.params},
                        "nominal": effect.nominal(),
                        "held_nominal": {p.name: problem.frozen[p.name] for p in effect.params
                                         if p.name in problem.frozen},
                        "units": {p.name: p.unit for p in effect.params},
                        # only fitted parameters have one: held-nominal ones are listed above
                        "ci95": {p.name: intervals[p.name] for p in effect.params if p.name in intervals},
                        "determined": {p.name: _determined(p, intervals.get(p.name)) for p in effect.params},
                        "claimed": {p.name: identified.get(p.name, False) for p in effect.params},
                        "identified": {p.name: identified.get(p.name, False) for p in effect.params},
                        "at_bound": {p.name: at_bound.get(p.name, False) for p in effect.params},
                        "explained_by_param": {p.name: round(share[p.name], 5) for p in effect.params
                                               if p.name in share},
                        "bounds": {p.name: [p.lower, p.upper] for p in effect.params},
                        "alternatives": alternatives.get(effect.id, []),
                        "explained_fraction": float((without_rss - current.rss) / baseline_rss),
                        "equation": effect.equation({**effect.nominal(), **current.values})})
    results.sort(key=lambda r: -r["explained_fraction"])
    return results
