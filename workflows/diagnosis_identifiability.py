"""What a Crazyflie diagnosis may claim of the thrust map: whether the fitting flights determine the battery
exponent against the map's shape (`map_shape_check`), the thrust gain and exponent with the shape refitted
where the data span it (`thrust_map_fit`), and a tie between a payload and the battery's gain in physical words
(`tie_words`).

Along a flight a controller raises the PWM as the battery sags, so PWM and voltage move together, and a map
whose curvature (q_pwm2) is wrong can be absorbed into gamma.  Gamma is refitted with the gain and the map's
curvature together; when that joint fit cannot pin gamma to ±`GAMMA_HALF_WIDTH` (several thrust levels at one
voltage are what separate them), gamma is confounded with the map's shape and not claimed.
"""
from __future__ import annotations

from learnest.models import crazyflie as cf
from learnest.models.crazyflie.excitation import battery_words
from learnest.models.diagnosis import AT_BOUND_FRACTION, bootstrap_ci, fit
from learnest.models.effects import Effect, Param
from learnest.models.identifiability import joint_conditioning, joint_half_width, sensitivity
from learnest.models.residual_problem import ResidualProblem

# gamma is determined when the joint fit with the gain and the map's curvature pins it to ± this (a tenth of its
# physical range [0, 3]: the tolerance a flight's gamma is wanted to)
GAMMA_HALF_WIDTH = 0.3


def shape_effect(prior: dict) -> Effect:
    """The thrust map's curvature as an effect (no candidate of the selection: only the thrust map's fit moves it)."""
    return Effect("thrust_map_shape", "crazyflie", "dynamics",
                  (Param("q_pwm2", cf.UNITS["q_pwm2"], float(prior["q_pwm2"]), *cf.BOUNDS["q_pwm2"], key="q_pwm2"),),
                  "T_i = (q_pwm2·a2·p_i² + a1·p_i + a0)·(V / V_ref)^gamma: the map's curvature")


def map_shape_check(problem: ResidualProblem, prior: dict) -> dict:
    """Whether ``problem``'s flights determine gamma with the map's curvature free, and why not.

    Fits the gain (m_kg), gamma and q_pwm2 together and reads the joint fit's conditioning: the linearised 95 %
    half-widths (`identifiability.joint_half_width`) and the collinearity of each column with the others.
    Returns {``determined`` (the joint fit pins gamma), ``half_width`` {param: value}, ``conditioning``, ``fit``
    (the joint `Fit`), ``reason``: None when gamma is determined with the prior's shape too, else why the
    selection, which holds the shape at the prior's, must not claim it (the shape confounds it, or the refitted
    shape differs from the prior's)}; when gamma is already undetermined by the excitation, ``determined``
    False, ``reason`` and ``fit`` None.
    """
    if "gamma" in problem.undetermined:
        return {"determined": False, "reason": problem.undetermined["gamma"], "fit": None}
    effects = _effects(problem) + [shape_effect(prior)]
    params = [p for e in effects for p in e.params]
    joint = fit(problem, effects)
    values = {**{p.name: p.nominal for e in problem.candidates for p in e.params}, **joint.values}
    half = joint_half_width(problem, joint, params)
    conditioning = joint_conditioning(sensitivity(problem, values, params), [p.name for p in params])
    determined = bool(half["gamma"] <= GAMMA_HALF_WIDTH)
    q, q_prior = joint.values["q_pwm2"], float(prior["q_pwm2"])
    reason = None
    if determined and abs(q - q_prior) > half["q_pwm2"]:
        # the prior's shape is wrong, and a gamma fitted with it held absorbs the difference
        reason = (f"the thrust map's shape differs from the prior's (curvature q_pwm2 = {q:.3g} ± {half['q_pwm2']:.2g} "
                  f"against {q_prior:.3g}): gamma is determined only with the shape refitted, "
                  f"{joint.values['gamma']:.3g} ± {half['gamma']:.2g} (the thrust map's fit); fitted with the "
                  "prior's shape it absorbs the difference, so the effect is not claimed")
    if not determined:
        beyond = problem.excitation.get("thrust_beyond_vbat", float("nan"))
        reason = (f"gamma is confounded with the thrust map's shape: with the map's curvature q_pwm2 refitted, "
                  f"gamma is known only to ±{half['gamma']:.2f} (its column is "
                  f"{conditioning['collinearity']['gamma']:.3f} collinear with the gain's and the curvature's; "
                  f"{100 * beyond:.0f} % of the thrust input's "
                  "variance is beyond what the battery voltage explains).  Fly several thrust levels at one "
                  "charge (hover, climbs, fast circles) early and late on one battery")
    return {"determined": determined, "half_width": half, "conditioning": conditioning, "fit": joint,
            "reason": reason}


def _effects(problem: ResidualProblem) -> list[Effect]:
    return [e for e in problem.candidates if e.id in ("mass", "battery_thrust")]


def _at_bound(param: Param, value: float) -> bool:
    margin = AT_BOUND_FRACTION * (param.upper - param.lower)
    return bool(value <= param.lower + margin or value >= param.upper - margin)


def thrust_map_fit(problem: ResidualProblem, prior: dict, declared: float | None, shape: dict | None = None) -> dict:
    """The thrust gain against the prior's PWM map, and the battery exponent only where the flights determine it.

    With gamma determined (`map_shape_check`): gain, gamma and the map's curvature q_pwm2 fitted together, with
    95 % block-bootstrap intervals over the three.  Otherwise the gain alone (gamma at the prior's value) with its
    interval, and gamma None, no interval, ``gamma_reason`` saying why and what flight would determine it.
    ``gain`` = m_prior / m_fit (dimensionless), or ``m_kg`` scaled onto a declared mass; ``at_bound`` per fitted
    parameter; ``excitation``: the flights' spread (`models.crazyflie.excitation`).
    """
    shape = shape or map_shape_check(problem, prior)
    mass, battery = _effects(problem)
    if shape["determined"]:
        effects = [mass, battery, shape_effect(prior)]
        fitted = shape["fit"]
    else:
        effects = [mass]
        fitted = fit(problem, effects)
    intervals = bootstrap_ci(problem, fitted)
    m_prior = float(prior["m_kg"])
    m_fit, (m_lo, m_hi) = fitted.values["m_kg"], intervals["m_kg"]
    params = {p.name: p for e in effects for p in e.params}
    out = {"gain": m_prior / m_fit, "gain_ci95": [m_prior / m_hi, m_prior / m_lo], "gamma": None, "gamma_ci95": None,
           "gamma_prior": float(prior["gamma"]), "gamma_identified": False, "gamma_reason": shape["reason"],
           "map_shape": "held at the prior's", "at_bound": {k: _at_bound(params[k], fitted.values[k]) for k in params},
           "gamma_bounds": list(cf.BOUNDS["gamma"]), "excitation": problem.excitation}
    if shape["determined"]:
        out.update(gamma=fitted.values["gamma"], gamma_ci95=intervals["gamma"], q_pwm2=fitted.values["q_pwm2"],
                   q_pwm2_ci95=intervals["q_pwm2"], q_pwm2_prior=float(prior["q_pwm2"]), map_shape="refitted",
                   gamma_identified=not out["at_bound"]["gamma"], gamma_reason=None,
                   shape_differs_from_prior=shape["reason"] is not None, conditioning=shape["conditioning"])
        if out["at_bound"]["gamma"]:
            out["gamma_reason"] = "gamma sits on a physical bound: the bound's value, not the data's"
    if declared is not None:
        out.update(m_kg=declared * m_fit / m_prior, m_kg_ci95=[declared * m_lo / m_prior, declared * m_hi / m_prior])
    return out


def tie_words(tie: dict, prior: dict, excitation: dict, candidates: list[dict]) -> str:
    """A tie of the Crazyflie diagnosis in physical words: the one combined observable the tied effects
    determine, with its interval joint over the set, and what would separate them."""
    combined = tie["combined"]
    value, (lo, hi) = combined["value"], combined["ci95"]
    if combined["param"] == "m_kg":
        m_prior = float(prior["m_kg"])
        gain, g_lo, g_hi = m_prior / value, m_prior / hi, m_prior / lo
        alone = {c["id"]: c["params"] for c in candidates}
        others = [i for i in tie["effects"] if i != "mass"]
        rivals = "; ".join(f"{i} alone would give it with " + ", ".join(f"{k} = {v:.3g}" for k, v in alone[i].items())
                           for i in others if i in alone)
        change = 100 * abs(1 / gain - 1)
        reading = (f"a payload of about +{change:.0f} %, or that much thrust lost" if gain < 1 else
                   f"about {change:.0f} % less mass than the map's vehicle, or that much more thrust")
        at = f" at {battery_words(excitation)}" if excitation else ""
        return (f"thrust over mass is ×{gain:.3f} [{g_lo:.3f}, {g_hi:.3f}] of what the prior's map gives{at}: "
                f"{reading}"
                + (f" ({rivals})" if rivals else "")
                + f".  These flights cannot apportion it between {' and '.join(tie['effects'])}, so neither is "
                  "claimed; a flight whose battery sags, or one with a known payload, would separate them")
    unit = f" {combined['unit']}" if combined.get("unit") not in (None, "", "1") else ""
    return (f"{' and '.join(tie['effects'])} explain the residual alike: together they remove "
            f"{100 * combined['explained_fraction']:.1f} % of it, read as {tie['effects'][0]} alone "
            f"{combined['param']} = {value:.4g} [{lo:.4g}, {hi:.4g}]{unit} (the interval joint over the two); "
            "neither is claimed, and data with more varied motion (thrust, speed) would separate them")
