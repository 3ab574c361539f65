"""The typed reports give back the JSON they were read from, key for key, and type what users read: a real
Crazyflie diagnosis (simulated payload, thrust in N) and a real evaluation (simulated flight)."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from learnest.estimators.yardsticks import FlightYardsticks
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.inputs import training_meta
from learnest.models.knode import HybridModel, Residual
from learnest.models.metadata import THRUST_GAIN_FORMAT, ModelMetadata
from learnest.models.systems import make_system
from learnest.workflows.diagnosis import diagnose_crazyflie
from learnest.workflows.flights import evaluate_flights
from learnest.workflows.reports import DiagnosisReport, EvaluationReport

M0 = 0.016
BASE = {**cf.IDENTIFIED, "m_kg": M0, "kappa_th": 0.0}


def _json(report: dict) -> dict:
    return json.loads(json.dumps(report))   # as stored: JSON, not numpy


def test_a_crazyflie_diagnosis_reads_and_gives_back_its_json():
    flights = [simulate_crazyflie(SimulatedFlight(truth={**BASE, "m_kg": 1.2 * M0}, controller=BASE, duration_s=20,
                                                  thrust_source="thrust_n"), seed=s) for s in range(2)]
    stored = _json(diagnose_crazyflie(flights, methods=(), prior=cf.prior_for("thrust_n", M0, BASE)))
    report = DiagnosisReport.from_dict(stored)
    assert report.to_dict() == stored
    top = report.effects[0]
    assert report.thrust_source == "thrust_n" and top.id == "mass" and top.units == {"m_kg": "kg"}
    assert top.params["m_kg"] == pytest.approx(1.2 * M0, rel=0.05) and top.identified == {"m_kg": True}
    assert report.vehicle_fits_prior is not None and set(report.vehicle_fits_prior) == {"ok", "thrust_gain", "message"}
    assert report.repair is not None and report.improves == report.repair.improves
    assert report.per_flight and report.per_flight[0].after["specific_force_rmse"] < \
        report.per_flight[0].before["specific_force_rmse"]
    # the split names are added by diagnose_flights: absent here, and absent from the JSON it gives back
    assert "fitting_flights" not in stored and "fitting_flights" not in report.to_dict()
    # keys the type does not name (candidates, channels, residual_series, ...) are kept as stored
    assert {"candidates", "channels", "residual_series"} <= set(report.extra)


def test_an_evaluation_reads_and_gives_back_its_json():
    flight = simulate_crazyflie(SimulatedFlight(truth=dict(BASE), controller=BASE, duration_s=10,
                                                hover_height_m=0.3), seed=3)
    system = replace(make_system("crazyflie"), dt=flight.dt, prior_params=dict(BASE))
    net = Residual([(np.zeros((4, system.n + system.n_inputs)), np.zeros(4)), (np.zeros((9, 4)), np.zeros(9))])
    model = HybridModel(system, "knode", net, {**training_meta(system), "learned": False})
    stored = _json(evaluate_flights(model, [flight], ["ukf", "knode-ukf"], gap_s=0.4, gap_every_s=2.0))
    report = EvaluationReport.from_dict(stored)
    assert report.to_dict() == stored
    assert report.learned is False and report.flights_scored == 1 and report.headline is not None
    score = report.flights[0]
    assert not score.excluded and set(score.mse) == {"ukf", "knode-ukf"}
    yardsticks = score.typed_yardsticks
    assert isinstance(yardsticks, FlightYardsticks) and yardsticks.to_dict() == score.yardsticks
    assert yardsticks.mocap_gaps.gaps > 0


def test_model_metadata_reads_a_meta_and_its_prior():
    system = make_system("crazyflie")
    meta = {**training_meta(system), "learned": True, "training_flights": [{"name": "a", "sha256": ["x"],
                                                                             "samples": 10, "dt": 0.01}]}
    typed = ModelMetadata.from_dict(meta)
    assert typed.to_dict() == meta and typed.format == THRUST_GAIN_FORMAT
    assert typed.training_flights[0].dt == 0.01 and typed.learned is True
    full = ModelMetadata.of_model(meta, system.prior_params)
    assert full.prior_params == system.prior_params and full.to_dict() == {**meta, "prior_params": system.prior_params}


def test_the_evaluation_schema_is_the_typed_report():
    """The API's evaluation schema (service.api.report_models) is built from the typed report: the same fields,
    each with the typed report's description, and the nested flights' schema from `FlightScore`."""
    from learnest.service.api.report_models import EvaluationReportOut, schema_of
    from learnest.workflows.reports import FlightScore

    assert list(EvaluationReportOut.model_fields) == EvaluationReport.typed_fields()
    assert list(schema_of(FlightScore).model_fields) == FlightScore.typed_fields()
    assert EvaluationReportOut.model_fields["flights_scored"].description == "flights scored"
    assert EvaluationReportOut.model_fields["flights"].annotation == list[schema_of(FlightScore)]
