"""`learnest thrust-map`: identify the Crazyflie's thrust map on some flights and score it on others.

The question a user asks of their logs: how well do the inputs alone (motor PWM, battery voltage, mocap
attitude and velocity; no accelerometer) predict the body-frame z specific force the accelerometer reads?
The protocol is the held-out specific-force target's (`models.crazyflie.identify`: both sides low-passed
at 5 Hz, samples the recorder interpolated across gaps and the filter edges left out); the model is
`models.crazyflie.thrust_map`.
"""
from __future__ import annotations

from collections.abc import Callable

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.models import crazyflie as cf
from learnest.models.crazyflie import thrust_map as tm
from learnest.models.crazyflie.identify import LOWPASS_HZ, FlightArrays, flight_arrays
from learnest.models.inputs import CHANNEL_SOURCES

PROTOCOL = {"target": "accelerometer body-frame z specific force, m/s²",
            "inputs": "motor PWM m1..m4, battery voltage, mocap attitude and velocity (no accelerometer)",
            "lowpass": f"{LOWPASS_HZ:g} Hz, 2nd-order Butterworth, zero phase, on both sides",
            "left_out": "samples interpolated across radio gaps (±5 samples) and the first/last 0.5 s"}


def _sources(flight: Flight) -> set[str]:
    return {s["sha256"] for s in flight.meta.get("sources", []) if s.get("sha256")}


def _source_path(flight: Flight) -> str:
    """The log file a flight came from (its name when the reader recorded none)."""
    sources = flight.meta.get("sources") or [{}]
    return str(sources[0].get("path") or flight.name)


def _usable(flights: list[Flight], role: str,
            fitted_on: frozenset[str] = frozenset()) -> tuple[list[FlightArrays], list[dict]]:
    """The flights' arrays, and an exclusion {flight, file, role, reason} for each one that cannot be used:
    failed quality, missing inputs, or (``fitted_on``: source sha256s) a score flight also fitted on."""
    arrays, excluded = [], []
    for flight in flights:
        reason = None
        missing = [name for name in ("motors", "vbat", "acc_body") if name not in flight.channels]
        if _sources(flight) & fitted_on:
            reason = "also in --fit: a flight the map was fitted on is not held out"
        elif not flight.quality["ok"]:
            reason = "quality: " + "; ".join(flight.quality["issues"])
        elif missing:
            reason = "no " + "; no ".join(CHANNEL_SOURCES.get(name, "body-frame accelerometer") for name in missing)
        if reason is None:
            arrays.append(flight_arrays(flight))
        else:
            excluded.append({"flight": flight.name, "file": _source_path(flight), "role": role, "reason": reason})
    return arrays, excluded


def _scores(fitted: tm.ThrustMap, arrays: list[FlightArrays]) -> dict:
    rmse, constant = fitted.rmse(arrays), tm.rmse_constant(arrays)
    return {"rmse": rmse, "r2": tm.r2(fitted, arrays), "constant_rmse": constant,
            "fraction_of_constant": rmse / constant}


def thrust_map_report(fit_flights: list[Flight], score_flights: list[Flight],
                      progress: Callable[[str, int, int], object] | None = None) -> dict:
    """Fit `models.crazyflie.thrust_map` on ``fit_flights`` and score it on each of ``score_flights`` (whole flights
    held out).  ``progress(stage, done, total)`` is told the stages "fitting" (grid points of the two time
    constants) and "scoring" (flights).

    Returns
    -------
    dict
        ``protocol``; ``fit_on`` (names); ``map`` {``terms``, ``coef`` {term: m/s² per unit}, ``tau_s``,
        ``vbat_tau_s`` (s), ``rmse_train`` (m/s²)}; ``readings`` (`models.crazyflie.thrust_map.readings` at the fit
        flights' mean); ``flights`` [{``flight``, ``rmse``, ``r2``, ``constant_rmse``,
        ``fraction_of_constant``}] and ``held_out`` (the same, pooled); ``excluded`` [{``flight``, ``file``,
        ``role``, ``reason``}]: failed quality, missing inputs, or a score flight that is also a fit flight
        (same source file content), which would not be held out.

    Raises
    ------
    InvalidInput
        If no fitting flight, or no flight to score, is usable (each exclusion's reason is in the message).
    """
    fit_arrays, excluded = _usable(fit_flights, "fit")
    fitted_on = frozenset().union(*(_sources(f) for f in fit_flights if f.name in {a.name for a in fit_arrays}))
    score_arrays, excluded_score = _usable(score_flights, "score", fitted_on)
    excluded += excluded_score
    reasons = "; ".join(f"{e['file']}: {e['reason']}" for e in excluded)
    if not fit_arrays:
        raise InvalidInput(f"thrust map: no usable flight to fit on ({reasons or 'none given'})")
    if not score_arrays:
        raise InvalidInput(f"thrust map: no usable flight to score ({reasons or 'none given'})")
    fitted = tm.fit_thrust_map(fit_arrays, progress=(lambda done, total: progress("fitting", done, total))
                               if progress else None)
    scores = []
    for done, arrays in enumerate(score_arrays, start=1):
        scores.append({"flight": arrays.name, **_scores(fitted, [arrays])})
        if progress:
            progress("scoring", done, len(score_arrays))
    return {"protocol": PROTOCOL, "fit_on": [a.name for a in fit_arrays],
            "map": {"terms": list(fitted.terms), "coef": dict(zip(fitted.terms, map(float, fitted.coef))),
                    "tau_s": fitted.tau_s, "vbat_tau_s": fitted.vbat_tau_s, "rmse_train": fitted.rmse_train},
            "readings": tm.readings(fitted, fit_arrays),
            "flights": scores,
            "held_out": _scores(fitted, score_arrays), "excluded": excluded}


# the notebook API's name (`learnest.thrust_map(fit_flights, score_flights)`)
thrust_map = thrust_map_report


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
    lines += [f"excluded ({e['role']}): {e['file']}: {e['reason']}" for e in report["excluded"]]
    return "\n".join(lines)


# -- a bench calibration CSV -----------------------------------------------------------------------------------
BENCH_COLUMNS = {"thrust": ("thrust_n", "thrust_g"), "x": ("pwm", "rpm", "omega_rad_s"), "vbat": ("vbat", "vbat_v")}


def read_bench_csv(path) -> dict:
    """A bench calibration of one motor: a CSV with a header, one row per steady point.

    Columns: the thrust, ``thrust_n`` (N) or ``thrust_g`` (grams-force); what drove it, ``pwm`` (0..65535),
    ``rpm`` (rev/min) or ``omega_rad_s`` (rad/s); optionally ``vbat`` (V).  Other columns are ignored.

    Returns
    -------
    dict
        ``kind`` ("pwm" or "rpm"), ``x`` (PWM or rad/s), ``thrust_n`` (N), ``vbat`` (V or None), arrays (n,).

    Raises
    ------
    InvalidInput
        Naming the file: no such file, no thrust or drive column, a value that is not a number.
    """
    import csv
    from pathlib import Path

    import numpy as np

    path = Path(path)
    try:
        with path.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
    except OSError as err:
        raise InvalidInput(f"{path}: cannot read the bench calibration ({err.strerror or err})") from None
    header = {name.strip().lower(): name for name in (rows[0].keys() if rows else [])}

    def column(name):
        try:
            return np.array([float(r[header[name]]) for r in rows])
        except (TypeError, ValueError) as err:
            raise InvalidInput(f"{path}: column {name!r} holds a value that is not a number ({err})") from None

    thrust_name = next((n for n in BENCH_COLUMNS["thrust"] if n in header), None)
    x_name = next((n for n in BENCH_COLUMNS["x"] if n in header), None)
    if thrust_name is None or x_name is None:
        raise InvalidInput(f"{path}: a bench calibration needs a thrust column "
                           f"({' or '.join(BENCH_COLUMNS['thrust'])}) "
                           f"and what drove it ({' or '.join(BENCH_COLUMNS['x'])}); the header has "
                           f"{', '.join(header) or 'nothing'}")
    thrust = column(thrust_name) * (cf.GRAVITY / 1000.0 if thrust_name == "thrust_g" else 1.0)
    x = column(x_name)
    if x_name == "rpm":
        x = x * 2.0 * np.pi / 60.0
    vbat_name = next((n for n in BENCH_COLUMNS["vbat"] if n in header), None)
    return {"kind": "pwm" if x_name == "pwm" else "rpm", "x": x, "thrust_n": thrust,
            "vbat": column(vbat_name) if vbat_name else None}


def bench_thrust_map_report(path, mass_kg: float | None = None) -> dict:
    """Fit one motor's thrust map on a bench calibration CSV (`read_bench_csv`,
    `models.crazyflie.thrust_map.fit_bench_map`).

    Returns
    -------
    dict
        ``file``; ``kind`` ("pwm" or "rpm"); ``map`` {``coef`` [c2, c1, c0] N per unit², unit, 1 of PWM or
        rad/s, ``gamma`` (None without a voltage spread), ``rmse_n``, ``rows``}; ``gain_vs_prior`` (the
        measured thrust over the prior's Förster map at the measured points); ``prior_params``: what the
        Crazyflie prior needs for this vehicle — with ``mass_kg`` (kg) the effective mass m_kg = mass / gain
        against Förster's map (the prior's thrust map is Förster's scaled by 1/m_kg), and ``gamma`` when fitted.

    Raises
    ------
    InvalidInput
        The file is not a usable calibration (the message names it and why).
    """
    data = read_bench_csv(path)
    try:
        bench = tm.fit_bench_map(data["kind"], data["x"], data["thrust_n"], data["vbat"])
    except ValueError as err:
        raise InvalidInput(f"{path}: {err}") from None
    prior = {"q_pwm2": 1.0}
    if mass_kg:
        prior["m_kg"] = mass_kg / bench.gain_vs_prior
    if bench.gamma is not None:
        prior["gamma"] = bench.gamma
    return {"file": str(path), "kind": bench.kind,
            "map": {"coef": list(bench.coef), "unit_x": "PWM" if bench.kind == "pwm" else "rad/s",
                    "gamma": bench.gamma, "rmse_n": bench.rmse_n, "rows": bench.n},
            "gain_vs_prior": bench.gain_vs_prior, "mass_kg": mass_kg, "prior_params": prior}


def format_bench_map(report: dict) -> str:
    """The bench map's report as text."""
    m = report["map"]
    c2, c1, c0 = m["coef"]
    x = "p" if report["kind"] == "pwm" else "ω"
    lines = [f"bench thrust map of one motor ({report['file']}, {m['rows']} points): T = {c2:.4g}·{x}² + {c1:.4g}·{x} "
             f"+ {c0:.4g} N" + (f" × (V / {cf.V_REF} V)^{m['gamma']:.3g}" if m["gamma"] is not None else "")
             + f", RMSE {m['rmse_n'] * 1e3:.2f} mN",
             f"  {report['gain_vs_prior']:.3f}× the thrust of the prior's map (Förster's) at the measured points"]
    if report["mass_kg"]:
        lines.append(f"  for the prior: m_kg = {report['prior_params']['m_kg']:.4g} kg (the {report['mass_kg']:g}-kg "
                     "vehicle's effective mass against Förster's map)")
    else:
        lines.append("  give --mass-kg to get the prior's effective mass for this vehicle")
    return "\n".join(lines)
