"""Known answers for what a Crazyflie diagnosis may claim: a parameter the flights' own excitation cannot
determine is never claimed, a tie stays untied with its combined observable stated, and the battery exponent is
kept where the battery sags (with the thrust map's shape refitted where the prior's is wrong).

The flights are flown closed-loop by `models.crazyflie.simulate_crazyflie`; the truth of each case is in its test."""
import json
import re
from pathlib import Path

import pytest

from learnest.ingest import read_flights
from learnest.ingest.sim import write_canonical_flight
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.workflows.diagnosis import diagnose_crazyflie, format_diagnosis

PRIOR = cf.IDENTIFIED
RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"


def _flights(truth, n=3, **settings):
    return [simulate_crazyflie(SimulatedFlight(truth=truth, controller=PRIOR, duration_s=20, **settings), seed=s)
            for s in range(n)]


def _claimed(report, name):
    return [e["id"] for e in report["effects"] if e["identified"].get(name)]


def test_a_payload_at_a_constant_battery_claims_no_battery_exponent_and_states_the_tie(tmp_path):
    """Truth: clean, this vehicle's thrust over mass is ×1.325 the prior's map; it carries a 25 % payload
    (×1.325 / 1.25 = ×1.06), the battery held at 3.80 V; PWM, battery and Vicon logged (Vicon + cfclient files).
    At one voltage gamma is a gain: gamma = 2.6 gives the ×1.06 as well as the payload does.  Before, the
    diagnosis claimed one of the two by order or by the voltage noise, with a narrow interval given that pick,
    and gave gamma an interval; now neither is claimed, the combined observable is stated, and the reason names
    the constant battery.  The payload's gain against the clean flights' is 1 / 1.25 within 5 %."""
    clean_mass = PRIOR["m_kg"] / 1.325
    files = []
    for i, flight in enumerate(_flights({**PRIOR, "m_kg": 1.25 * clean_mass}, vbat=(3.8, 3.8))):
        files += read_flights(write_canonical_flight(flight, "vicon+cfclient", tmp_path, f"payload{i}"))
    report = diagnose_crazyflie(files, methods=(), prior=PRIOR)
    assert _claimed(report, "gamma") == [] and report["thrust_map_fit"]["gamma"] is None
    assert report["thrust_map_fit"]["gamma_ci95"] is None and not report["thrust_map_fit"]["gamma_identified"]
    why = report["undetermined"]["gamma"]
    assert "3.80" in why and "sags" in why
    (tie,) = report["ties"]
    assert set(tie["effects"]) == {"mass", "battery_thrust"}
    for e in report["effects"]:            # neither tied effect is claimed, nor given an interval
        if e["id"] in ("thrust_gain", "mass", "battery_thrust"):
            assert not any(e["identified"].values()) and e["ci95"] == {}
    stated = re.search(r"thrust over mass is ×([0-9.]+)", tie["words"])
    assert float(stated.group(1)) == pytest.approx(1.06, rel=0.01) and "less mass" in tie["words"]
    text = format_diagnosis(report)
    assert "tie, neither claimed" in text and "the battery stayed at 3.80" in text
    clean = diagnose_crazyflie(_flights({**PRIOR, "m_kg": clean_mass}, vbat=(3.8, 3.8)), methods=(), prior=PRIOR)
    ratio = report["thrust_map_fit"]["gain"] / clean["thrust_map_fit"]["gain"]
    assert ratio == pytest.approx(1 / 1.25, rel=0.05)
    # the tie's interval is joint over mass and gamma, in the one thing they determine together
    m_lo, m_hi = tie["combined"]["ci95"]
    assert PRIOR["m_kg"] / m_hi <= 1.06 * 1.01 and PRIOR["m_kg"] / m_lo >= 1.06 * 0.99


def test_a_sagging_battery_still_determines_the_battery_exponent():
    """Truth: gamma 1.5 (prior 0.42), the battery sagging from 4.1 to 3.4 V, thrust varied by climbs and circles:
    gamma is claimed within its interval, by the selection and by the thrust map's fit with the shape refitted."""
    report = diagnose_crazyflie(_flights({**PRIOR, "gamma": 1.5}, vbat=(4.1, 3.4)), methods=(), prior=PRIOR)
    assert "gamma" not in report["undetermined"] and report["ties"] == []
    (battery,) = [e for e in report["effects"] if e["id"] == "battery_thrust"]
    assert battery["identified"] == {"gamma": True}
    lo, hi = battery["ci95"]["gamma"]
    assert lo <= 1.5 <= hi or battery["params"]["gamma"] == pytest.approx(1.5, abs=0.05)
    fit = report["thrust_map_fit"]
    assert fit["gamma_identified"] and fit["map_shape"] == "refitted" and fit["gamma"] == pytest.approx(1.5, abs=0.1)
    assert fit["gamma_ci95"][0] - 0.05 <= 1.5 <= fit["gamma_ci95"][1] + 0.05


def test_a_map_shape_other_than_the_priors_is_refitted_and_never_absorbed_into_gamma():
    """Truth: Förster's map curvature (q_pwm2 1, the prior's -0.153), gamma 1.5, a sag from 4.1 to 3.4 V.  With
    the prior's shape held, the selection's gamma comes out near 1 (the shape absorbed into it): it is not
    claimed.  The thrust map's fit refits the shape, as the flights span several thrust levels at each voltage,
    and gives gamma within 0.3 of 1.5."""
    report = diagnose_crazyflie(_flights({**PRIOR, "gamma": 1.5, "q_pwm2": 1.0}, vbat=(4.1, 3.4)), methods=(),
                                prior=PRIOR)
    assert _claimed(report, "gamma") == []
    assert "shape" in report["undetermined"]["gamma"]
    fit = report["thrust_map_fit"]
    assert fit["map_shape"] == "refitted" and fit["gamma_identified"]
    assert fit["gamma"] == pytest.approx(1.5, abs=0.3) and fit["q_pwm2"] == pytest.approx(1.0, abs=0.2)


def _reports(data):
    """Every dict under ``data`` that holds a list of effects (a report, or one nested in a benchmark's JSON)."""
    stack = [data]
    while stack:
        node = stack.pop()
        children = node.values() if isinstance(node, dict) else node if isinstance(node, list) else []
        if isinstance(node, dict) and isinstance(node.get("effects"), list):
            yield node
        stack.extend(children)


def test_no_committed_result_claims_a_parameter_its_flights_cannot_determine():
    """Every diagnosis report under benchmarks/results: no claimed parameter is one its report lists as
    undetermined (by the excitation, a tie or the map's shape), and a thrust map fit gives gamma an interval only
    where it says gamma is determined."""
    walked = 0
    for path in sorted(RESULTS.rglob("*.json")):
        try:
            data = json.loads(path.read_text())
        except (ValueError, UnicodeDecodeError):
            continue
        for report in _reports(data):
            undetermined = report.get("undetermined") or {}
            for e in report["effects"]:
                if not isinstance(e, dict):
                    continue
                walked += 1
                lacking = {**undetermined, **(e.get("undetermined") or {})}
                claimed = [k for k, ok in (e.get("identified") or {}).items() if ok]
                assert not set(claimed) & set(lacking), (path, e["id"])
            fit = report.get("thrust_map_fit") or {}
            if "gamma_identified" in fit and not fit["gamma_identified"]:
                assert fit["gamma_ci95"] is None, path
    assert walked > 0
