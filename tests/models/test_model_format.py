"""A model's input format is an integer (`models.metadata`): new models record ``format_version``; models stored
with only the sentence of their inputs load with the same integer and are evaluated on the inputs they were
trained on, the numbers identical to a model that records the integer."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.inputs import calibrates_attitude, calibrates_thrust_gain, training_meta
from learnest.models.knode import HybridModel, Residual
from learnest.models.metadata import (
    ATTITUDE_CALIBRATED,
    ATTITUDE_CALIBRATED_FORMAT,
    RAW_ATTITUDE,
    THRUST_GAIN_CALIBRATED,
    THRUST_GAIN_FORMAT,
    ModelMetadata,
    input_format,
)
from learnest.models.systems import make_system
from learnest.workflows.flights import evaluate_flights

PRIOR = {**cf.IDENTIFIED, "m_kg": 0.016}


def _zero_knode(system, meta):
    net = Residual([(np.zeros((4, system.n + system.n_inputs)), np.zeros(4)), (np.zeros((9, 4)), np.zeros(9))])
    return HybridModel(system, "knode", net, meta)


def _stored_without_integer(tmp_path, meta):
    """A model file as written before the integer existed: its meta holds only the sentence."""
    system = replace(make_system("crazyflie"), prior_params=dict(PRIOR))
    path = tmp_path / "old.json"
    _zero_knode(system, meta).save(path)
    data = json.loads(path.read_text())
    assert "format_version" not in data["meta"]
    return HybridModel.load(path)


@pytest.mark.parametrize(("meta", "version", "gain", "attitude"), [
    ({"attitude_input": THRUST_GAIN_CALIBRATED}, THRUST_GAIN_FORMAT, True, True),
    ({"attitude_input": ATTITUDE_CALIBRATED}, ATTITUDE_CALIBRATED_FORMAT, False, True),
    ({"attitude_input": "mocap attitude calibrated onto the thrust axis"}, RAW_ATTITUDE, False, False),
    ({}, RAW_ATTITUDE, False, False),
])
def test_old_sentences_load_as_integers(tmp_path, meta, version, gain, attitude):
    model = _stored_without_integer(tmp_path, meta)
    assert input_format(model.meta) == version
    assert model.meta.get("format_version", RAW_ATTITUDE) == version
    assert calibrates_thrust_gain(model.meta, "knode") is gain and calibrates_attitude(model.meta) is attitude
    # the typed metadata reads the same integer, and gives the meta back key for key
    typed = ModelMetadata.from_dict(model.meta)
    assert typed.format == version and typed.to_dict() == model.meta


def test_new_models_record_the_integer():
    system = make_system("crazyflie")
    assert training_meta(system)["format_version"] == THRUST_GAIN_FORMAT
    assert training_meta(system, thrust_gain=False)["format_version"] == ATTITUDE_CALIBRATED_FORMAT
    assert isinstance(training_meta(system)["format_version"], int)


def test_an_old_model_evaluates_as_trained(tmp_path):
    """The same weights with the old sentence (loaded from a file) and with the integer: identical reports."""
    flight = simulate_crazyflie(SimulatedFlight(truth={**PRIOR, "m_kg": 0.0192}, controller=PRIOR, duration_s=8,
                                                hover_height_m=0.3), seed=2)
    old = _stored_without_integer(tmp_path, {"attitude_input": ATTITUDE_CALIBRATED})
    old.system = replace(old.system, dt=flight.dt)
    new = _zero_knode(old.system, training_meta(old.system, thrust_gain=False))
    assert new.meta["format_version"] == ATTITUDE_CALIBRATED_FORMAT
    a, b = (evaluate_flights(m, [flight], ["ukf"])["flights"][0] for m in (old, new))
    assert "thrust_gain" not in a and "thrust_gain" not in b and not a["warnings"]
    assert a["mse"] == b["mse"]
