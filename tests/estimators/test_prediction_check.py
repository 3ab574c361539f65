"""The prediction check: does a KNODE predict a flight's measurements worse than its prior (no ground truth)?"""
from __future__ import annotations

import json

import numpy as np
import pytest

from learnest.estimators.evaluate import prediction_check, recommended_model, summarize
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


def test_the_true_effect_predicts_better_and_the_wrong_sign_is_flagged(circle):
    right = evaluate_flights(_circle_jerk_knode(+1.0), [circle], ["ukf", "knode-ukf"])
    wrong = evaluate_flights(_circle_jerk_knode(-1.0), [circle], ["ukf", "knode-ukf"])
    right_check, wrong_check = right["flights"][0]["prediction_check"], wrong["flights"][0]["prediction_check"]
    assert right_check["channels"] == ["px", "py", "pz"]
    assert right_check["innovation_ratio"] < 1.0 and not right_check["knode_predicts_worse"]
    assert wrong_check["innovation_ratio"] > 1.0 and wrong_check["knode_predicts_worse"]
    # and the check agrees with the ground truth it never saw: the flagged model's estimates are worse
    assert wrong["flights"][0]["mse"]["knode-ukf"] > wrong["flights"][0]["mse"]["ukf"]
    assert right["flights"][0]["mse"]["knode-ukf"] < right["flights"][0]["mse"]["ukf"]
    assert wrong["knode_predicts_worse"] == [circle.name] and right["knode_predicts_worse"] == []
    # the wrong sign loses beyond the flight's own variability, the right one gains beyond it
    assert wrong["flights"][0]["gain_interval_pct"]["knode-ukf_vs_ukf"][1] < 0
    assert right["flights"][0]["gain_interval_pct"]["knode-ukf_vs_ukf"][0] > 0
    assert wrong["knode_clearly_worse"] == {"ukf": [circle.name]} and right["knode_clearly_worse"] == {"ukf": []}
    json.dumps(wrong)
    table = format_report(wrong)
    assert f"do not trust the KNODE on: {circle.name}" in table
    assert f"KNODE-UKF worse than UKF beyond the flight's own variability (95 % interval of the gain below 0) on: " \
           f"{circle.name}" in table
    assert f"{circle.name} {wrong_check['innovation_ratio']:.3f}" in table
    assert f"do not trust the KNODE on: {circle.name} ({wrong_check['innovation_ratio']:.3f}): the prediction " \
           "check (one-step innovations, no ground truth) finds it predicts these flights worse than its prior, " \
           "so the recommended estimate uses the prior's there" in table
    # the recommended estimate falls back to the prior exactly where the check flags the flight
    assert wrong["recommended"]["prior_on"] == [circle.name] and right["recommended"]["prior_on"] == []
    assert wrong["recommended"]["median"]["ukf"] == wrong["flights"][0]["mse"]["ukf"]
    assert right["recommended"]["median"]["ukf"] == right["flights"][0]["mse"]["knode-ukf"]
    assert wrong["recommended"]["flights_worse_than_prior"]["ukf"] == []
    assert "recommended estimate" in table and "prior's used on: " + circle.name in table


def _scored(name: str, mse: dict[str, float], ratio: float) -> dict:
    return {"flight": name, "excluded": False, "mse": mse,
            "prediction_check": prediction_check([1.0], [ratio], [0], ["px"])}


def test_the_recommended_estimate_is_scored_per_base_method_against_the_prior_median():
    flights = [_scored("gains", {"ukf": 4.0, "knode-ukf": 2.0, "mhe": 3.0, "knode-mhe": 1.0}, 0.8),
               _scored("loses_flagged", {"ukf": 1.0, "knode-ukf": 5.0, "mhe": 2.0, "knode-mhe": 6.0}, 1.3),
               _scored("loses_unflagged", {"ukf": 3.0, "knode-ukf": 3.5, "mhe": 5.0, "knode-mhe": 4.0}, 0.9),
               {"flight": "bad", "excluded": True, "mse": {}}]
    assert [recommended_model(f) for f in flights] == ["knode", "prior", "knode", None]
    report = summarize(flights)
    recommended = report["recommended"]
    # UKF: chosen 2.0 (knode), 1.0 (prior), 3.5 (knode) -> median 2.0; prior median of 4, 1, 3 = 3
    assert recommended["median"] == {"ukf": 2.0, "mhe": 2.0}           # MHE: 1.0, 2.0, 4.0 vs 3, 2, 5
    assert recommended["improvement_pct"] == pytest.approx({"ukf": 100 * (1 - 2.0 / 3.0), "mhe": 100 * (1 - 2 / 3)})
    assert recommended["flights_worse_than_prior"] == {"ukf": ["loses_unflagged"], "mhe": []}
    assert recommended["prior_on"] == ["loses_flagged"]
    assert summarize([{"flight": "x", "excluded": False, "mse": {"ukf": 1.0}, "prediction_check": None}]
                     )["recommended"] is None


def test_the_check_runs_the_filters_itself_when_only_the_mhe_rows_are_asked_for(circle):
    with_ukf = evaluate_flights(_circle_jerk_knode(-1.0), [circle], ["ukf", "knode-ukf"])["flights"][0]
    mhe_only = evaluate_flights(_circle_jerk_knode(-1.0), [circle], ["mhe"])["flights"][0]
    assert set(mhe_only["mse"]) == {"mhe"}
    assert mhe_only["prediction_check"]["innovation_ratio"] == pytest.approx(
        with_ukf["prediction_check"]["innovation_ratio"], rel=1e-9)


def test_a_prior_only_model_gets_no_check(circle):
    report = evaluate_flights(HybridModel(make_system("quadrotor"), "prior"), [circle], ["ukf"])
    assert report["flights"][0]["prediction_check"] is None and report["knode_predicts_worse"] == []
