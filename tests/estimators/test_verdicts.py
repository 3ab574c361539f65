"""One verdict per flight: the mocap-gap gain's 95 % interval, which the headline counts and the recommended
estimate follows; the one-step prediction check stays beside it as a number, never a second verdict."""
from __future__ import annotations

import json

import numpy as np
import pytest

from learnest.estimators.evaluate import prediction_check, recommended_model, summarize
from learnest.estimators.evaluation_report import FlightScore
from learnest.ingest import read_flights
from learnest.ingest.sim import Circle, simulate, write_flight
from learnest.models.knode import HybridModel, Residual
from learnest.models.systems import make_system
from learnest.service.cli import format_report
from learnest.workflows.flights import evaluate_flights

RADIUS, SPEED = 0.5, 1.0          # m, m/s: ω = 2 rad/s, a centripetal jerk of ω³ r = 4 m/s³


def test_the_ratio_compares_the_chosen_channels_only_and_flags_above_one():
    names = ["px", "py", "pz", "ax", "ay", "az"]
    prior, knode = [1.0, 2.0, 1.0, 5.0, 5.0, 5.0], [1.0, 2.0, 2.0, 0.1, 0.1, 0.1]
    check = prediction_check(prior, knode, [0, 1, 2], names)
    assert check["channels"] == ["px", "py", "pz"]
    assert check["innovation_ratio"] == pytest.approx(5.0 / 4.0)
    assert check["knode_predicts_worse"]
    assert not prediction_check(prior, knode, [3, 4, 5], names)["knode_predicts_worse"]   # 0.3 / 15
    same = prediction_check(prior, [x * (1 + 1e-12) for x in prior], [0, 1, 2], names)
    assert not same["knode_predicts_worse"]          # equal up to rounding is not worse


def _circle_jerk_knode(sign: float) -> HybridModel:
    """The kinematic prior plus a residual jerk sign·(−ω² v) in the plane: sign +1 is the true physics of a
    circle at constant speed (ȧ = −ω² v), sign −1 the same effect with the wrong sign."""
    system = make_system("quadrotor")
    assert system.prior_params["omega"] == 0.0          # the prior has no jerk at all
    w2 = (SPEED / RADIUS) ** 2
    weight, bias = np.zeros((9, 9)), np.zeros(9)
    weight[6, 3] = weight[7, 4] = -sign * w2
    return HybridModel(system, "knode", Residual([(weight, bias)]), {"name": f"jerk{sign:+.0f}"})


@pytest.fixture(scope="module")
def circle(tmp_path_factory):
    sim = simulate(Circle(radius=RADIUS, speed=SPEED, duration_s=20.0), seed=3, name="circle")
    return read_flights(write_flight(sim, "nanobench", tmp_path_factory.mktemp("check"), "circle"))[0]


def test_the_true_effect_is_better_and_the_wrong_sign_worse_and_every_surface_says_so(circle):
    right = evaluate_flights(_circle_jerk_knode(+1.0), [circle], ["ukf", "knode-ukf"])
    wrong = evaluate_flights(_circle_jerk_knode(-1.0), [circle], ["ukf", "knode-ukf"])
    key, name = "knode-ukf_vs_ukf", circle.name
    # the verdict, from the gaps the estimators never saw, agrees with the simulated truth
    assert right["flights"][0]["verdict"] == {key: "better"} and wrong["flights"][0]["verdict"] == {key: "worse"}
    assert wrong["flights"][0]["mse"]["knode-ukf"] > wrong["flights"][0]["mse"]["ukf"]
    assert right["flights"][0]["mse"]["knode-ukf"] < right["flights"][0]["mse"]["ukf"]
    # the one-step check points the same way here, but only as a number
    assert wrong["flights"][0]["one_step_innovation_ratio"] > 1.0 > right["flights"][0]["one_step_innovation_ratio"]
    assert "prediction_check" not in wrong["flights"][0] and "knode_predicts_worse" not in wrong
    # one verdict: the report's lists, the headline's counts and the recommended estimate agree
    assert wrong["verdicts"][key]["worse"] == [name] and right["verdicts"][key]["better"] == [name]
    assert wrong["headline"]["flights_worse_names"][key] == [name]
    assert wrong["headline"]["flights_worse_beyond_interval"][key] == 1
    assert right["headline"]["flights_better_beyond_interval"][key] == 1
    assert wrong["recommended"]["prior_on"] == {"ukf": [name]} and wrong["recommended"]["knode_on"] == {"ukf": []}
    assert right["recommended"]["prior_on"] == {"ukf": []} and right["recommended"]["knode_on"] == {"ukf": [name]}
    gaps = wrong["flights"][0]["yardsticks"]["mocap_gaps"]["rmse_m"]
    assert wrong["recommended"]["median_gap_rmse_m"]["ukf"] == gaps["ukf"]          # the prior's, where worse
    assert right["recommended"]["median_gap_rmse_m"]["ukf"] == \
        right["flights"][0]["yardsticks"]["mocap_gaps"]["rmse_m"]["knode-ukf"]
    json.dumps(wrong)
    table = format_report(wrong)
    assert "do not trust" not in table and "one-step" not in table
    # stated first: the verdict rows and the recommended estimate come before the tables
    recommended_at = table.index("Recommended estimate: per flight, the KNODE's estimate, or its prior's where")
    assert recommended_at < table.index("Mocap gaps (headline)")
    assert f"UKF: the KNODE's on 0 of 1 flight, the prior's on {name}; median gap RMSE " in table
    assert "WORSE beyond its interval" in table[:recommended_at]


def _scored(name: str, rmse: dict[str, float], intervals: dict[str, list[float] | None]) -> dict:
    """A scored flight entry with a mocap-gap score: gap RMSE per method (m) and the gain intervals (%)."""
    gains = {key: 0.0 if interval is None else sum(interval) / 2 for key, interval in intervals.items()}
    return {"flight": name, "excluded": False, "mse": dict(rmse),
            "yardsticks": {"mocap_gaps": {"rmse_m": dict(rmse), "gain_pct": gains, "gain_interval_pct": intervals,
                                          "gaps": 5, "gap_s": 0.5, "every_s": 2.5, "start_s": 5.0}}}


def test_the_recommended_estimate_follows_the_verdict_per_base_method():
    flights = [_scored("gains", {"ukf": 4.0, "knode-ukf": 2.0, "mhe": 3.0, "knode-mhe": 1.0},
                       {"knode-ukf_vs_ukf": [10.0, 60.0], "knode-mhe_vs_mhe": [20.0, 70.0]}),
               _scored("loses", {"ukf": 1.0, "knode-ukf": 5.0, "mhe": 2.0, "knode-mhe": 6.0},
                       {"knode-ukf_vs_ukf": [-90.0, -40.0], "knode-mhe_vs_mhe": [-5.0, 3.0]}),
               _scored("cannot_tell", {"ukf": 3.0, "knode-ukf": 3.5, "mhe": 5.0, "knode-mhe": 4.0},
                       {"knode-ukf_vs_ukf": None, "knode-mhe_vs_mhe": [-3.0, 8.0]}),
               {"flight": "bad", "excluded": True, "mse": {}}]
    assert [recommended_model(f, "ukf") for f in flights] == ["knode", "prior", "knode", None]
    assert [recommended_model(f, "mhe") for f in flights[:3]] == ["knode", "knode", "knode"]
    report = summarize([FlightScore.from_dict(f) for f in flights])
    recommended = report["recommended"]
    assert recommended["prior_on"] == {"ukf": ["loses"], "mhe": []}
    assert recommended["knode_on"] == {"ukf": ["gains", "cannot_tell"], "mhe": ["gains", "loses", "cannot_tell"]}
    # UKF: 2.0 (knode), 1.0 (prior), 3.5 (knode) -> 2.0 against the prior's 4, 1, 3 -> 3.0
    assert recommended["median_gap_rmse_m"] == {"ukf": 2.0, "mhe": 4.0}        # MHE: 1, 6, 4 -> 4
    assert recommended["prior_median_gap_rmse_m"] == {"ukf": 3.0, "mhe": 3.0}
    assert report["verdicts"]["knode-ukf_vs_ukf"] == {"better": ["gains"], "worse": ["loses"], "within": [],
                                                      "undecided": ["cannot_tell"]}
    assert report["verdicts"]["knode-mhe_vs_mhe"]["within"] == ["loses", "cannot_tell"]
    # the headline counts the very same verdicts
    head = report["headline"]
    for key, verdicts in report["verdicts"].items():
        assert head["flights_worse_beyond_interval"][key] == len(verdicts["worse"])
        assert head["flights_better_beyond_interval"][key] == len(verdicts["better"])
        assert head["flights_within_interval"][key] == len(verdicts["within"])
        assert head["flights_undecided"][key] == len(verdicts["undecided"])
    assert summarize([FlightScore.from_dict({"flight": "x", "excluded": False, "mse": {"ukf": 1.0}})])["recommended"] \
        is None


def test_the_one_step_ratio_is_computed_when_only_the_mhe_rows_are_asked_for(circle):
    with_ukf = evaluate_flights(_circle_jerk_knode(-1.0), [circle], ["ukf", "knode-ukf"])["flights"][0]
    mhe_only = evaluate_flights(_circle_jerk_knode(-1.0), [circle], ["mhe"])["flights"][0]
    assert set(mhe_only["mse"]) == {"mhe"}
    assert mhe_only["one_step_innovation_ratio"] == pytest.approx(with_ukf["one_step_innovation_ratio"], rel=1e-9)


def test_a_prior_only_model_gets_no_ratio_and_no_verdict(circle):
    report = evaluate_flights(HybridModel(make_system("quadrotor"), "prior"), [circle], ["ukf"])
    assert "one_step_innovation_ratio" not in report["flights"][0]
    assert report["flights"][0]["verdict"] == {} and report["verdicts"] == {} and report["recommended"] is None
