"""What the data can determine, before any claim: the conditioning of a joint fit (sensitivity columns, their
cosines, the condition number), the ties a selection leaves (two effects that explain the residual alike), and
the one combined observable a tied set does determine, with an interval joint over the set.

A tie is a confounded pair (`models.diagnosis.confounded_pairs`) whose sensitivities are nearly parallel
(cosine ≥ `TIE_COSINE`) and which the criterion cannot choose between: ΔBIC_eff within the threshold, or one of
its parameters undetermined by the data's own excitation (`ResidualProblem.undetermined`: then a BIC_eff margin
comes from noise, e.g. the voltage reading's, not from the effect).  Neither effect of a tie is claimed.
"""
from __future__ import annotations

import numpy as np

from .residual_problem import Fit, ResidualProblem

TIE_COSINE = 0.9          # sensitivities this parallel are "the same effect on this data" (diagnosis.ALIKE_COSINE)
TIE_REPLICATES = 30       # bootstrap replicates of a tied set's joint fit (enough for a 95 % percentile interval)


def sensitivity(problem: ResidualProblem, values: dict, params, step: float = 1e-5) -> np.ndarray:
    """Columns ∂r/∂θ at ``values`` (forward finite differences, flattened residual), one per parameter of
    ``params`` (`effects.Param`)."""
    rows = np.arange(problem.n_rows)
    base = problem.residual(values, rows).ravel()
    columns = []
    for p in params:
        h = step * max(1.0, abs(values[p.name]), p.upper - p.lower)
        columns.append((problem.residual({**values, p.name: values[p.name] + h}, rows).ravel() - base) / h)
    return np.column_stack(columns)


def joint_conditioning(columns: np.ndarray, names: list[str]) -> dict:
    """How well a joint fit of the parameters ``names`` (sensitivity ``columns``, one each) is conditioned.

    Returns
    -------
    dict
        ``condition_number`` and ``smallest_singular_value`` of the unit-norm columns (1 and 1: orthogonal;
        ∞ and 0: one column is a combination of the others); ``collinearity`` {name: the multiple
        correlation of its column with the others' span, 0..1: 1 means the others can stand in for it}.
    """
    norms = np.linalg.norm(columns, axis=0)
    unit = columns / np.where(norms > 0, norms, 1.0)
    singular = np.linalg.svd(unit, compute_uv=False)
    collinearity = {}
    for i, name in enumerate(names):
        others = np.delete(unit, i, axis=1)
        if others.shape[1] == 0 or norms[i] == 0:
            collinearity[name] = 0.0 if norms[i] else 1.0
            continue
        coef, *_ = np.linalg.lstsq(others, unit[:, i], rcond=None)
        collinearity[name] = float(np.sqrt(max(0.0, 1.0 - np.sum((unit[:, i] - others @ coef) ** 2))))
    return {"condition_number": float(singular[0] / max(singular[-1], 1e-300)),
            "smallest_singular_value": float(singular[-1]), "collinearity": collinearity}


def joint_half_width(problem: ResidualProblem, fitted: Fit, params) -> dict[str, float]:
    """95 % half-widths of ``params`` in the joint fit ``fitted``, linearised: 1.96 σ √τ √((JᵀJ)⁻¹)_ii with
    J the sensitivity at the fit, σ² the residual's mean square and τ its autocorrelation time (samples);
    ∞ where J is singular."""
    values = {**{p.name: p.nominal for e in problem.candidates for p in e.params}, **fitted.values}
    J = sensitivity(problem, values, params)
    sigma2 = float(np.mean(fitted.residual ** 2)) * max(fitted.tau, 1.0)
    try:
        cov = sigma2 * np.linalg.inv(J.T @ J)
    except np.linalg.LinAlgError:
        return {p.name: float("inf") for p in params}
    return {p.name: float(1.96 * np.sqrt(max(cov[i, i], 0.0))) for i, p in enumerate(params)}


def is_tie(pair: dict, undetermined: dict) -> bool:
    """The confounded ``pair`` is a tie (see the module's docstring): nearly parallel, and the criterion
    cannot choose, or one of its parameters is undetermined by the excitation."""
    if pair.get("cancelling") or pair["cosine"] < TIE_COSINE:
        return False
    return pair.get("data_prefer") is None or any(name in undetermined for name in pair["params"])


def tie_groups(confounded: list[dict], undetermined: dict) -> list[list[str]]:
    """The tied sets of effect ids (`is_tie`), pairs sharing an effect merged, in the order first met."""
    groups: list[list[str]] = []
    for pair in confounded:
        if not is_tie(pair, undetermined):
            continue
        if pair.get("data_prefer") is not None:     # a margin the excitation cannot back is the noise's
            lacking = ", ".join(n for n in pair["params"] if n in undetermined)
            pair["note"] = (f"{pair['effects'][1]} explains the residual as well as {pair['effects'][0]} (cosine "
                            f"{pair['cosine']:.3f}); {lacking} is not determined by these flights' excitation, so "
                            f"the ΔBIC_eff of {pair['delta_bic']:g} is the noise's, not the effect's: neither is "
                            "claimed")
        pair["tie"], pair["data_prefer"] = True, None
        touching = [g for g in groups if set(g) & set(pair["effects"])]
        merged = [i for g in touching for i in g] + list(pair["effects"])
        groups = [g for g in groups if g not in touching] + [list(dict.fromkeys(merged))]
    return groups


def combined_observable(problem: ResidualProblem, effects: list, values: dict, fit_fn, others: tuple = (),
                        seed: int = 0, replicates: int = TIE_REPLICATES) -> dict:
    """What a tied set of ``effects`` determines together: their joint contribution to the residual, read as the
    value of the first effect's first parameter that alone gives the same contribution (its "equivalent").

    The tied effects are fitted jointly with the ``others`` chosen beside them (``fit_fn`` =
    `models.diagnosis.fit`, started at ``values``); the
    equivalent is fitted to the joint fit's residual.  The joint fit is resampled by a moving-block bootstrap of
    its residual rows (blocks of 2τ), and each replicate's joint residual is read as an equivalent through the
    sensitivity of the equivalent's residual to it (linearised: a replicate moves it little).  The interval is
    over the tied set, never conditional on one effect's pick.  Returns {``param``, ``unit``, ``value``,
    ``ci95`` [2.5 %, 97.5 %], ``effects`` ids, ``explained_fraction`` (of the residual with every tied effect
    at its nominal value), ``joint``: the joint fit's values (not claimed: the set cannot apportion them)}.
    """
    lead = effects[0].params[0]
    everything = np.arange(problem.n_rows)
    nominal = {p.name: p.nominal for e in problem.candidates for p in e.params}
    together = [*effects, *others]
    joint = fit_fn(problem, together, start={p.name: values.get(p.name, p.initial) for e in together
                                             for p in e.params if p.name not in problem.frozen})
    target = problem.residual({**nominal, **joint.values}, everything)
    kept = {k: v for k, v in joint.values.items() if k in {p.name for e in others for p in e.params}}
    # the lead alone, the others held at their joint values: it reads the tied set's contribution
    alone = fit_fn(problem, [effects[0]], offset=-target, start={
        p.name: joint.values.get(p.name, p.initial) for p in effects[0].params}, base=kept)
    column = sensitivity(problem, {**nominal, **kept, **alone.values}, [lead])[:, 0]
    rng = np.random.default_rng(seed)
    r, n = joint.residual, len(joint.residual)
    block = int(np.clip(np.ceil(2 * joint.tau), 5, max(5, n // 5)))
    samples = []
    for _ in range(replicates):
        starts = rng.integers(0, n - block + 1, size=int(np.ceil(n / block)))
        resampled = np.concatenate([r[s:s + block] for s in starts])[:n]
        refit = fit_fn(problem, together, offset=resampled - r, start=joint.values)
        # the replicate's joint values, read on the data as observed (its contribution, not its noise)
        moved = (problem.residual({**nominal, **refit.values}, everything) - target).ravel()
        samples.append(alone.values[lead.name] + float(column @ moved) / float(column @ column))
    rss_nominal = float(np.sum(problem.residual({**nominal, **kept}, everything) ** 2))
    return {"param": lead.name, "unit": lead.unit, "value": float(alone.values[lead.name]),
            "ci95": [float(np.percentile(samples, 2.5)), float(np.percentile(samples, 97.5))],
            "effects": [e.id for e in effects], "joint": dict(joint.values),
            "explained_fraction": 1.0 - joint.rss / rss_nominal if rss_nominal > 0 else 0.0}
