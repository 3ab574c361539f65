"""A diagnosis report as text: effects with units and intervals, confounded pairs, before and after."""
from __future__ import annotations

import numpy as np

from learnest.models import crazyflie as cf
from learnest.models.crazyflie.identify import LOWPASS_HZ
from learnest.models.diagnosis import MULTIPLE_SHARE


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


THRUST_SOURCE_TEXT = {"pwm": "motor PWM and battery voltage", "rpm": "rotor speed (rpm deck)",
                      "thrust_n": "the controller's thrust command in N"}


def how_much(fraction: float) -> str:
    """A rival's share of the residual the chosen effect removes, in words (it can exceed 1: a rival with
    more parameters can remove more and still have the worse BIC_eff)."""
    if fraction >= MULTIPLE_SHARE:
        return f"removes {fraction:.1f}× as much"
    return f"explains {100 * fraction:.0f} % as much"


def confounded_label(pair: dict) -> str:
    """How a confounded pair is introduced: a close rival the data still rank lower, or a true tie."""
    return f"close rival (the data prefer {pair['data_prefer']})" if pair.get("data_prefer") else "cannot tell apart"


def _unit(unit: str | None) -> str:
    """A unit as printed after a value: nothing for a dimensionless one ("1") or none."""
    return "" if unit in (None, "1") else unit


def format_diagnosis(result: dict) -> str:
    """The human-readable report: effects as equations, intervals, what could not be told apart, and
    the estimators' error before and after.  ``result`` is `diagnose`'s or `diagnose_simulated`'s dict."""
    lines = [f"diagnosis of {result['system']}"]
    if result.get("prior"):
        prior = result["prior"]["params"]
        lines.append("  prior: " + ", ".join(f"{k} = {v:.4g} {_unit(cf.UNITS.get(k))}".rstrip()
                                            for k, v in prior.items() if k in cf.UNITS))
    if result.get("thrust_source"):
        declared = result.get("declared_mass_kg")
        lines.append(f"  thrust from: {THRUST_SOURCE_TEXT[result['thrust_source']]}"
                     + (f"; declared mass {declared:g} kg" if declared else "; no declared mass"))
    if result.get("vehicle_fits_prior"):
        fits = result["vehicle_fits_prior"]
        verdict = "vehicle fits the prior" if fits["ok"] else "VEHICLE DOES NOT FIT THE PRIOR"
        lines.append(f"  {verdict}: {fits['message']}")
    lines += _excitation_lines(result)
    if result.get("thrust_map_fit"):
        lines += _thrust_map_lines(result["thrust_map_fit"])
    if result.get("simulated_truth"):
        lines.append(f"  (simulated; truth hidden from the diagnosis: {result['simulated_truth']})")
    if not result["effects"]:
        lines.append("  no effect explains the residual better than noise: the model is not missing anything "
                     "these candidates describe")
    for e in result["effects"]:
        lines += _effect_lines(e)
    for c in result["confounded"]:
        lines.append(f"  {confounded_label(c)}: {c['note']}")
    for tie in result.get("ties", []):
        lines.append(f"  tie, neither claimed: {tie.get('words') or tie['effects']}")
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
    lines += _gap_lines(result, methods, median)
    if methods:
        lines.append(f"  MSE on held-out data, the paper's SG yardstick{median}   before        after")
    for m in methods:
        helped = result.get("improved_flights", {}).get(m)
        lines.append(f"    {m:<20}{result['before'][m]:>10.4g}  {result['after'][m]:>10.4g}"
                     + (f"   better on {helped} flights" if helped else ""))
    return "\n".join(lines)


def _gap_lines(result: dict, methods: list[str], median: str) -> list[str]:
    """The repair's yardstick, the evaluation's headline: position RMSE inside the mocap gaps, before and after."""
    gaps = (result.get("yardsticks") or {}).get("mocap_gaps")
    if not gaps or not methods:
        return []
    if gaps["before_rmse_m"] is None:
        return [f"  no mocap-gap score: {'; '.join(gaps['skipped'])}"]
    lines = [f"  position RMSE (m) inside {gaps['gap_s']:g}-s mocap gaps on held-out data{median}   before        "
             "after"]
    for m in methods:
        lines.append(f"    {m:<20}{gaps['before_rmse_m'][m]:>10.4g}  {gaps['after_rmse_m'][m]:>10.4g}"
                     f"   better on {gaps['improved_flights'][m]} flights")
    return lines


def _effect_lines(e: dict) -> list[str]:
    """One effect of a diagnosis report: its equation, interval, prior value, and why a parameter is not
    claimed (held at the prior, at a bound, not pinned down) or what else fits."""
    lines = []
    units = e.get("units", {})
    cis = ", ".join(f"{k} in [{lo:.4g}, {hi:.4g}] {_unit(units.get(k))}".rstrip()
                    for k, (lo, hi) in e["ci95"].items())
    shaky = [k for k, ok in e.get("determined", {}).items() if not ok]
    lines.append(f"  {e['equation']}  ({e['channel']}; explains {100 * e['explained_fraction']:.1f} % of the "
                 f"residual; " + (f"95 % CI {cis})" if cis else "no interval: not determined)"))
    if "nominal" in e:
        lines.append("    prior's value: " + ", ".join(f"{k} = {v:.4g} {_unit(units.get(k))}".rstrip()
                                                      for k, v in e["nominal"].items()))
    for name, why in e.get("held_nominal", {}).items():
        lines.append(f"    {name}: {why}")
    at_bound = [k for k, b in e.get("at_bound", {}).items() if b]
    if at_bound:
        lines.append(f"    at a physical bound, so not identified: {', '.join(at_bound)}")
    for name, why in e.get("undetermined", {}).items():
        lines.append(f"    {name} not claimed, no interval: {why}")
    for key in ("note", "held_out"):
        if e.get(key):
            lines.append(f"    {e[key]}")
    shaky = [k for k in shaky if k not in e.get("held_nominal", {}) and k not in e.get("undetermined", {})]
    if shaky:
        lines.append(f"    not pinned down by this data: {', '.join(shaky)}")
    unclaimed = [k for k, claimed in e.get("claimed", {}).items() if not claimed and k in e["ci95"]]
    if unclaimed:
        lines.append(f"    not claimed (the interval holds the prior's value): {', '.join(unclaimed)}")
    for alt in e.get("alternatives", []):
        values = ", ".join(f"{k} = {v:.4g} {_unit(alt['units'].get(k))}".rstrip() for k, v in alt["params"].items())
        lines.append(f"    alternative: {alt['id']} with {values} {how_much(alt['fraction_of_chosen'])} "
                     f"(ΔBIC_eff {alt['delta_bic']:+g})")
    return lines


def _excitation_lines(result: dict) -> list[str]:
    """What the fitting flights' signals span (`models.crazyflie.excitation`), and the parameters they leave
    undetermined with why."""
    x = result.get("excitation")
    if not x:
        return []
    lines = [f"  fitting flights span: battery {x['vbat_v']['mean']:.2f} ± {x['vbat_v']['std']:.3f} V "
             f"({x['vbat_v']['min']:.2f}–{x['vbat_v']['max']:.2f} V), {x['thrust_input_name']} "
             f"{x['thrust_input']['mean']:.4g} ± {x['thrust_input']['std']:.3g} {x['thrust_input_unit']} "
             f"({100 * x['thrust_beyond_vbat']:.0f} % of its variance beyond the battery's), speed "
             f"{x['speed_m_s']['min']:.2f}–{x['speed_m_s']['max']:.2f} m/s, height "
             f"{x['height_m']['min']:.2f}–{x['height_m']['max']:.2f} m"]
    lines += [f"  undetermined by these flights, never claimed: {name}: {why}"
              for name, why in (result.get("undetermined") or {}).items()]
    return lines


def _thrust_map_lines(t: dict) -> list[str]:
    """The thrust against the prior's map: the gain, and the battery exponent only where it is determined."""
    bound = ("; at a bound: " + ", ".join(k for k, b in t["at_bound"].items() if b)) if any(t["at_bound"].values()) \
        else ""
    gain = f"gain {t['gain']:.4g} [{t['gain_ci95'][0]:.4g}, {t['gain_ci95'][1]:.4g}]"
    if t.get("gamma") is None:
        return [f"  thrust against the prior's map: {gain} (gamma held at the prior's {t['gamma_prior']:.3g}, not "
                f"determined by these flights){bound}"]
    shape = (f", map curvature q_pwm2 {t['q_pwm2']:.3g} [{t['q_pwm2_ci95'][0]:.3g}, {t['q_pwm2_ci95'][1]:.3g}] "
             f"(prior {t['q_pwm2_prior']:.3g})") if t.get("map_shape") == "refitted" else ""
    return [f"  thrust against the prior's map, gain, battery exponent and map shape fitted together: {gain}, gamma "
            f"{t['gamma']:.3g} [{t['gamma_ci95'][0]:.3g}, {t['gamma_ci95'][1]:.3g}] (prior {t['gamma_prior']:.3g})"
            f"{shape}{bound}"]
