"""The scoring metrics (`estimators.metrics`) on analytic answers, and the one `prepare` of a flight that every
evaluation and check starts from."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.headline import learned_note
from learnest.estimators.metrics import (
    better_beyond_interval,
    gain_pct,
    mse,
    rms_norm,
    score,
    squared_errors,
    worse_beyond_interval,
)
from learnest.estimators.prepared import corrected_flight, initial_state, prepare, system_for
from learnest.ingest import read_flights
from learnest.models.knode import HybridModel
from learnest.models.training import NOT_CHECKED, NOT_LEARNED, learned_meta
from learnest.workflows.flights import evaluate_flight, evaluate_prepared, flight_envelope

SAMPLES = Path(__file__).resolve().parents[2] / "sample_logs"


def test_errors_and_gains_have_their_analytic_values():
    estimates, reference = np.zeros((4, 9)), np.zeros((4, 9))
    estimates[:, 0:3] = 0.1          # p off by 0.1 m in every axis
    estimates[:, 3:6] = 2.0          # v off by 2 m/s
    scores = score(estimates, reference)
    assert scores["groups"] == pytest.approx({"p": 0.01, "v": 4.0, "a": 0.0})
    assert scores["mse"] == pytest.approx((3 * 0.01 + 3 * 4.0) / 9) == mse(estimates, reference)
    assert rms_norm(np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]])) == pytest.approx(np.sqrt(12.5))
    assert np.isnan(rms_norm(np.zeros((0, 3))))
    assert gain_pct(2.0, 1.5) == 25.0 and gain_pct(1.0, 1.2) == pytest.approx(-20.0)
    assert worse_beyond_interval([-9.0, -0.1]) and not worse_beyond_interval([-9.0, 0.1])
    assert better_beyond_interval([0.1, 9.0]) and not better_beyond_interval([-0.1, 9.0])
    assert not worse_beyond_interval(None) and not better_beyond_interval(None)
    with pytest.raises(InvalidInput):
        squared_errors(np.zeros((4, 9)), np.zeros((3, 9)))


def test_the_report_keeps_a_models_own_learned_note():
    assert learned_note(learned_meta(-1)) == {"learned": False, "learned_note": NOT_LEARNED}
    assert learned_note(learned_meta(5)) == {"learned": True, "learned_note": None}
    # trained with nothing held out: learned, but the report says it was never checked
    assert learned_note(learned_meta(5, validated=False)) == {"learned": True, "learned_note": NOT_CHECKED}
    assert learned_note({}) == {"learned": None, "learned_note": None}


def test_prepare_builds_what_the_model_sees_once_and_the_evaluation_uses_it():
    flight = read_flights([SAMPLES / "circle_rep1.csv"])[0]
    effects = {"bias_x": 0.3}
    model = HybridModel(system_for(flight), "prior", meta={"measurement_effects": effects})
    prepared = prepare(model, flight)
    fixed = corrected_flight(flight, effects)
    assert np.array_equal(prepared.y, fixed.measurements()) and np.array_equal(prepared.x0, initial_state(fixed))
    assert not np.allclose(prepared.y, flight.measurements())   # the bias came off the accelerometer
    assert prepared.u.shape == (len(flight.t), 0) and prepared.dt == flight.dt and prepared.thrust_gain
    assert prepared.model.system.dt == flight.dt and prepared.prior.kind == "prior"
    with pytest.raises(AttributeError):
        prepared.y = None   # type: ignore[misc]
    assert flight_envelope(prepared) is None          # a model without a training envelope
    direct = evaluate_flight(model, flight, ["ukf"])["results"]["ukf"]
    assert evaluate_prepared(prepared, ["ukf"])["results"]["ukf"]["mse"] == direct["mse"]

