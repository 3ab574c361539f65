"""Training envelope: a model remembers the region its training data covered, and an evaluation says which
flights (and which states) lie outside it."""
import json

import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.ingest import read_flights
from learnest.ingest.sim import Circle, simulate, write_flight
from learnest.models.envelope import MARGIN, THRESHOLD, envelope_report, training_envelope
from learnest.models.knode import HybridModel
from learnest.models.presets import TrainingConfig
from learnest.service.cli import format_report
from learnest.workflows.flights import evaluate_flights, train_on_flight


def test_box_fraction_outside_is_the_analytic_share():
    rng = np.random.default_rng(0)
    train = rng.uniform(0.0, 1.0, size=(20_000, 3))
    envelope = training_envelope(train[:, :2], train[:, 2:], ["a", "b", "c"], invariant=("a",))
    assert envelope["low"] == pytest.approx([0.005] * 3, abs=2e-3)
    assert envelope["high"] == pytest.approx([0.995] * 3, abs=2e-3)

    test = rng.uniform(0.0, 1.0, size=(20_000, 3))
    test[:, 0] *= 3.0                  # far outside, but "a" is invariant: reported, not flagged
    test[:, 1] *= 2.0                  # outside beyond 0.995 + MARGIN·0.99 ≈ 1.094: (2 - 1.094) / 2 = 45 %
    report = envelope_report(envelope, test[:, :2], test[:, 2:])
    edge = 0.995 + MARGIN * 0.99
    assert report["per_state"]["b"] == pytest.approx((2.0 - edge) / 2.0, abs=0.01)
    assert report["per_state"]["a"] == pytest.approx((3.0 - edge) / 3.0, abs=0.01)
    assert report["per_state"]["c"] == 0.0
    assert report["states_outside"] == ["b"] and report["outside_training_envelope"]
    assert report["fraction_outside"] == pytest.approx(report["per_state"]["b"], abs=1e-4)   # per_state is rounded

    same = envelope_report(envelope, train[:1000, :2] * 0.99, train[:1000, 2:])
    assert not same["outside_training_envelope"] and same["fraction_outside"] < THRESHOLD

    with pytest.raises(InvalidInput, match="x and u"):
        envelope_report(envelope, test[:, :1], test[:, 2:])


def test_with_the_residual_a_record_is_flagged_only_where_the_network_answer_depends_on_the_new_region():
    """Δθ = [c, 0]: it reads input c and ignores state b.  Leaving the box in b changes nothing; leaving it in
    c moves Δθ by (c - edge) once clipped, more than SENSITIVITY × the training RMS of |c| (√(1/3)) beyond
    c* = edge + 0.5·√(1/3): for c ~ U(0, 3) a share (3 - c*) / 3 of the samples."""
    from learnest.models.envelope import SENSITIVITY

    def residual(x, u):
        return np.column_stack([u[:, 0], np.zeros(len(u))])

    rng = np.random.default_rng(1)
    train = rng.uniform(0.0, 1.0, size=(20_000, 3))
    envelope = training_envelope(train[:, :2], train[:, 2:], ["a", "b", "c"], residual=residual)
    assert envelope["residual_rms"] == pytest.approx(np.sqrt(1 / 3), rel=0.01)

    wide_b = rng.uniform(0.0, 1.0, size=(20_000, 3))
    wide_b[:, 1] *= 2.0
    box_only = envelope_report(envelope, wide_b[:, :2], wide_b[:, 2:])
    checked = envelope_report(envelope, wide_b[:, :2], wide_b[:, 2:], residual=residual)
    assert box_only["outside_training_envelope"] and box_only["states_outside"] == ["b"]
    assert checked["states_outside"] == ["b"] and checked["fraction_extrapolating"] == 0.0
    assert not checked["outside_training_envelope"] and checked["residual_checked"]

    wide_c = rng.uniform(0.0, 1.0, size=(20_000, 3))
    wide_c[:, 2] *= 3.0
    checked = envelope_report(envelope, wide_c[:, :2], wide_c[:, 2:], residual=residual)
    edge = np.array(envelope["high"][2]) + MARGIN * (envelope["high"][2] - envelope["low"][2])
    c_star = edge + SENSITIVITY * envelope["residual_rms"]
    assert checked["fraction_extrapolating"] == pytest.approx((3.0 - c_star) / 3.0, abs=0.01)
    assert checked["outside_training_envelope"] and checked["states_outside"] == ["c"]


@pytest.fixture(scope="module")
def circles(tmp_path_factory):
    """A slow training circle, a similar slow one and a fast one (8 s of circling each)."""
    root = tmp_path_factory.mktemp("envelope")
    specs = {"slow": (0.3, 0), "slow_again": (0.3, 1), "fast": (1.2, 2)}
    flights = {}
    for name, (speed, seed) in specs.items():
        sim = simulate(Circle(radius=0.5, speed=speed, duration_s=8.0), seed=seed, name=name)
        flights[name] = read_flights(write_flight(sim, "nanobench", root, name))[0]
    return flights


def test_a_fast_flight_is_outside_a_slow_models_envelope_and_a_similar_one_is_not(circles, tmp_path):
    config = TrainingConfig(hidden=8, epochs=3, lr=1e-3, validation_fraction=0.0)
    model = train_on_flight(circles["slow"], config).model
    envelope = model.meta["envelope"]
    assert envelope["names"][:3] == ["px", "py", "pz"] and set(envelope["invariant"]) == {"px", "py", "pz"}

    model.save(tmp_path / "m.json")                                   # stored with the model file
    model = HybridModel.load(tmp_path / "m.json")
    report = evaluate_flights(model, [circles["fast"], circles["slow_again"]], ["ukf"])
    fast, similar = (f["envelope"] for f in report["flights"])
    # 1.2 m/s on a 0.5 m circle: speeds 4x and centripetal accelerations 16x those of training
    assert fast["outside_training_envelope"]
    assert {"vx", "vy", "ax", "ay"} <= set(fast["states_outside"])
    assert not {"px", "py", "pz"} & set(fast["states_outside"])       # where it flew is not new physics
    assert fast["fraction_outside"] > 0.5
    assert not similar["outside_training_envelope"] and similar["fraction_outside"] < THRESHOLD
    assert report["outside_training_envelope"] == [circles["fast"].name]
    json.dumps(report)                                                # the JSON report carries it as is

    table = format_report(report)
    fast_line = next(line for line in table.splitlines() if line.startswith(circles["fast"].name))
    assert "OUTSIDE" in fast_line and "vx" in fast_line
    assert f"outside what this model saw in training: {circles['fast'].name}" in table
