"""`learnest thrust-map`: identify the Crazyflie's thrust map on some flights and score it on others.

The question a user asks of their logs: how well do the inputs alone (motor PWM, battery voltage, mocap
attitude and velocity; no accelerometer) predict the body-frame z specific force the accelerometer reads?
The protocol is issue 14's (`models.identify`: both sides low-passed at 5 Hz, samples the recorder
interpolated across gaps and the filter edges left out); the model is `models.thrust_map`.
"""
from __future__ import annotations

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.models import thrust_map as tm
from learnest.models.identify import LOWPASS_HZ, FlightArrays, flight_arrays

PROTOCOL = {"target": "accelerometer body-frame z specific force, m/s²",
            "inputs": "motor PWM m1..m4, battery voltage, mocap attitude and velocity (no accelerometer)",
            "lowpass": f"{LOWPASS_HZ:g} Hz, 2nd-order Butterworth, zero phase, on both sides",
            "left_out": "samples interpolated across radio gaps (±5 samples) and the first/last 0.5 s"}


def _usable(flights: list[Flight], role: str) -> tuple[list[FlightArrays], list[dict]]:
    arrays, excluded = [], []
    for flight in flights:
        if not flight.quality["ok"]:
            excluded.append({"flight": flight.name, "role": role,
                             "reason": "quality: " + "; ".join(flight.quality["issues"])})
            continue
        try:
            arrays.append(flight_arrays(flight))
        except ValueError as err:      # names the flight and the channels it lacks
            excluded.append({"flight": flight.name, "role": role, "reason": str(err)})
    return arrays, excluded


def _scores(fitted: tm.ThrustMap, arrays: list[FlightArrays]) -> dict:
    rmse, constant = fitted.rmse(arrays), tm.rmse_constant(arrays)
    return {"rmse": rmse, "r2": tm.r2(fitted, arrays), "constant_rmse": constant,
            "fraction_of_constant": rmse / constant}


def thrust_map_report(fit_flights: list[Flight], score_flights: list[Flight]) -> dict:
    """Fit `models.thrust_map` on ``fit_flights`` and score it on each of ``score_flights`` (whole flights
    held out).

    Returns
    -------
    dict
        ``protocol``; ``fit_on`` (names); ``map`` {``terms``, ``coef`` {term: m/s² per unit}, ``tau_s``,
        ``vbat_tau_s`` (s), ``rmse_train`` (m/s²)}; ``readings`` (`models.thrust_map.readings` at the fit
        flights' mean); ``flights`` [{``flight``, ``rmse``, ``r2``, ``constant_rmse``,
        ``fraction_of_constant``}] and ``held_out`` (the same, pooled); ``excluded`` [{``flight``, ``role``,
        ``reason``}].

    Raises
    ------
    InvalidInput
        If no fitting flight, or no flight to score, is usable (each exclusion's reason is in the message).
    """
    fit_arrays, excluded = _usable(fit_flights, "fit")
    score_arrays, excluded_score = _usable(score_flights, "score")
    excluded += excluded_score
    reasons = "; ".join(f"{e['flight']}: {e['reason']}" for e in excluded)
    if not fit_arrays:
        raise InvalidInput(f"thrust map: no usable flight to fit on ({reasons or 'none given'})")
    if not score_arrays:
        raise InvalidInput(f"thrust map: no usable flight to score ({reasons or 'none given'})")
    fitted = tm.fit_thrust_map(fit_arrays)
    return {"protocol": PROTOCOL, "fit_on": [a.name for a in fit_arrays],
            "map": {"terms": list(fitted.terms), "coef": dict(zip(fitted.terms, map(float, fitted.coef))),
                    "tau_s": fitted.tau_s, "vbat_tau_s": fitted.vbat_tau_s, "rmse_train": fitted.rmse_train},
            "readings": tm.readings(fitted, fit_arrays),
            "flights": [{"flight": a.name, **_scores(fitted, [a])} for a in score_arrays],
            "held_out": _scores(fitted, score_arrays), "excluded": excluded}


def format_thrust_map(report: dict) -> str:
    """The report as text: the map, then one line per scored flight and the pooled held-out score."""
    m, r = report["map"], report["readings"]
    lines = [f"thrust map fitted on {len(report['fit_on'])} flight(s): motor lag {1e3 * m['tau_s']:.0f} ms, battery "
             f"voltage filtered over {m['vbat_tau_s']:g} s, training RMSE {m['rmse_train']:.3f} m/s²",
             f"  at the fit flights' mean: {r['dfz_dV']:+.2f} m/s² per V of battery "
             f"({r['percent_g_per_V']:+.1f} % of g per V), {r['dfz_dsum']:+.2f} m/s² per unit of summed duty, "
             f"{r['dfz_dsplit']:+.2f} per unit of CW/CCW split",
             f"body-z specific force from the inputs alone ({report['protocol']['lowpass']}), held-out flights:",
             f"{'flight':<28}{'RMSE m/s²':>11}{'R²':>8}{'constant 1 g':>14}{'fraction':>10}"]
    for f in [*report["flights"], {"flight": "all held-out", **report["held_out"]}]:
        lines.append(f"{f['flight']:<28}{f['rmse']:>11.3f}{f['r2']:>8.2f}{f['constant_rmse']:>14.3f}"
                     f"{100 * f['fraction_of_constant']:>9.0f}%")
    lines += [f"excluded ({e['role']}): {e['flight']}: {e['reason']}" for e in report["excluded"]]
    return "\n".join(lines)
