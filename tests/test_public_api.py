"""The notebook API (`import learnest as le`) and the installed package, as a user meets them."""
import importlib.metadata
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import learnest as le
from learnest.estimators.covariance import linearized_covariances
from learnest.estimators.kf import run_kf
from learnest.estimators.params import EstimatorParams
from learnest.estimators.ukf import run_ukf
from learnest.models.knode import HybridModel
from learnest.models.systems import make_system

REPO = Path(__file__).resolve().parents[1]
SAMPLES = REPO / "sample_logs"


def test_the_distribution_installs_one_top_level_name():
    if _editable():   # a strict editable install lists a folder of links, which holds the package alone
        tops = {p.name for p in Path(le.__file__).parents[1].iterdir()}
    else:
        files = importlib.metadata.files("learnest") or []
        tops = {f.parts[0] for f in files if f.suffix == ".py" and len(f.parts) > 1}
    assert tops == {"learnest"}, tops
    # and the tests use the installed copy, not the checkout (unless it is an editable install)
    assert "site-packages" in le.__file__ or _editable(), le.__file__


def _editable() -> bool:
    direct = importlib.metadata.distribution("learnest").read_text("direct_url.json") or "{}"
    return json.loads(direct).get("dir_info", {}).get("editable", False)


def test_import_learnest_is_light():
    """`import learnest` and its errors load no torch, CasADi, FastAPI or SQLAlchemy."""
    code = ("import sys, learnest; heavy = [m for m in ('torch', 'casadi', 'fastapi', 'sqlalchemy', 'filterpy') "
            "if m in sys.modules]; print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd="/")
    assert out.stdout.strip() == ""


def test_science_layers_import_without_the_service_stack():
    code = ("import sys; import learnest.workflows.estimation, learnest.workflows.diagnosis, "
            "learnest.workflows.table1, learnest.estimators.knode_estimator; "
            "print(','.join(m for m in ('fastapi', 'sqlalchemy', 'starlette', 'alembic') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd="/")
    assert out.stdout.strip() == ""


def test_the_workflows_load_torch_and_filterpy_only_when_they_run():
    """Importing the training, estimation and experiment modules (what every test module and job worker
    does) loads neither torch (3 s) nor filterpy (2 s of scipy.stats): the suite's collection stays fast."""
    code = ("import sys; import learnest.models.training, learnest.estimators.ukf, learnest.estimators.kf, "
            "learnest.workflows.flights, learnest.workflows.estimation; "
            "print(','.join(m for m in ('torch', 'filterpy', 'torchdiffeq') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd="/")
    assert out.stdout.strip() == ""


def test_public_names_resolve_and_unknown_names_fail():
    for name in le.__all__:
        assert getattr(le, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'nonsense'"):
        le.nonsense  # noqa: B018


def test_errors_carry_their_http_status():
    assert (le.InvalidInput.status, le.NotFound.status, le.Conflict.status) == (422, 404, 409)
    assert issubclass(le.IngestError, le.InvalidInput) and issubclass(le.InvalidInput, ValueError)


def test_flight_dataframe_round_trip_keeps_arrays_units_and_meta():
    [flight] = le.read_flights([SAMPLES / "circle_rep1.csv"])
    frame = flight.to_dataframe()
    assert len(frame) == len(flight.t)
    assert frame.attrs["units"]["p_x"] == "m" and frame.attrs["units"]["a_meas_z"] == "m/s^2"
    np.testing.assert_array_equal(frame[["p_x", "p_y", "p_z"]].to_numpy(), flight.p)
    back = le.Flight.from_dataframe(frame)
    for name in ("t", "p", "a_meas", "quat"):
        np.testing.assert_array_equal(getattr(back, name), getattr(flight, name))
    assert back.channels.keys() == flight.channels.keys()
    for name, values in flight.channels.items():
        np.testing.assert_array_equal(back.channels[name], values)
    assert back.meta == json.loads(json.dumps(flight.meta))
    with pytest.raises(le.InvalidInput, match="missing column"):
        le.Flight.from_dataframe(frame.drop(columns=["p_y"]))


def test_flight_repr_is_one_line_summary():
    [flight] = le.read_flights([SAMPLES / "circle_rep1.csv"])
    text = repr(flight)
    assert "\n" not in text and len(text) < 300 and "circle_rep1" in text and "Hz" in text


@pytest.fixture(scope="module")
def linear_case():
    system = make_system("quadrotor")
    return system, HybridModel(system, "prior"), system.simulate(3, n_samples=200)


def test_ukf_result_has_covariances_equal_to_the_kalman_filter(linear_case):
    """On a linear-Gaussian model the UKF is the KF: means and covariances, step for step."""
    system, model, run = linear_case
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
    kf = run_kf(params, run.y)
    ukf = run_ukf(params, run.y, alpha=1.0)       # u=None: a model without inputs
    assert ukf.covariances.shape == (200, 9, 9) and ukf.innovations.shape == (200, 6)
    np.testing.assert_allclose(ukf.covariances, kf.covariances, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(ukf.innovations, kf.innovations, atol=1e-9)
    np.testing.assert_allclose(ukf.t, system.dt * np.arange(200))


def test_linearized_covariances_equal_the_kalman_filter_on_a_linear_model(linear_case):
    system, model, run = linear_case
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, run.x_noisy[0])
    kf = run_kf(params, run.y)
    covariances = linearized_covariances(params, kf.means)
    np.testing.assert_allclose(covariances, kf.covariances, rtol=1e-9, atol=1e-15)


def test_inputs_required_by_a_model_are_asked_for():
    system = make_system("cartpole")
    run = system.simulate(1, n_samples=20)
    with pytest.raises(le.InvalidInput, match="u is required"):
        run_ukf(EstimatorParams(HybridModel(system, "true"), system.dt, system.Q, system.R, system.P0, run.x[0]),
                run.y, None)


def test_notebook_workflow_on_sample_flights():
    flights = le.read_flights([SAMPLES / "circle_rep1.csv", SAMPLES / "circle_rep2.csv"])
    knode = le.KNODE(epochs=5, seed=1).fit(flights[0])
    assert knode is not None and len(knode.losses_) == 5 and knode.seconds_ > 0
    assert knode.model_.meta["training_flight"] == "circle_rep1"
    post = le.ukf(knode.model_, flights[1])
    T = len(flights[1].t)
    assert post.means.shape == (T, 9) and post.covariances.shape == (T, 9, 9)
    np.testing.assert_array_equal(post.t, flights[1].t)
    # the filter tracks the mocap position to within its noise level
    assert np.sqrt(np.mean((post.means[:, :3] - flights[1].p) ** 2)) < 0.01
    assert np.all(np.linalg.eigvalsh(post.covariances) > 0)
    window = flights[1].slice(0, 120)
    mhe = le.mhe(knode.model_, window, horizon=5)
    assert mhe.means.shape == (120, 9) and mhe.solver_failures == 0
    assert np.sqrt(np.mean((mhe.means[:, :3] - window.p) ** 2)) < 0.01
    report = le.evaluate(knode.model_, flights, methods=("ukf", "knode-ukf"))
    [trained, scored] = report["flights"]
    assert trained["excluded"] and "training flight" in trained["reason"]
    assert set(scored["mse"]) == {"ukf", "knode-ukf"} and report["flights_scored"] == 1
    with pytest.raises(le.InvalidInput, match="unknown method"):
        le.evaluate(knode.model_, flights, methods=("ukf", "kalman"))
    with pytest.raises(le.InvalidInput, match="choose one of"):
        le.KNODE(system="cartpole").fit(flights[0])


def test_a_repaired_model_sees_its_measurement_effects_in_ukf_and_mhe():
    """A model a diagnosis repaired carries accelerometer effects: le.ukf/le.mhe correct the flight
    exactly as le.evaluate does, so the same model gives the same estimates through every entry point."""
    from learnest.estimators.prepared import corrected_flight

    [flight] = le.read_flights([SAMPLES / "circle_rep2.csv"])
    flight = flight.slice(0, 150)
    effects = {"bias_z": 0.4, "scale_x": 1.05}
    prior = le.HybridModel(le.make_system("quadrotor"))
    repaired = le.HybridModel(le.make_system("quadrotor"), meta={"measurement_effects": effects})
    fixed = corrected_flight(flight, effects)
    np.testing.assert_allclose(le.ukf(repaired, flight).means, le.ukf(prior, fixed).means, rtol=0, atol=1e-12)
    np.testing.assert_allclose(le.mhe(repaired, flight, horizon=3).means, le.mhe(prior, fixed, horizon=3).means,
                               rtol=0, atol=1e-9)
    assert not np.allclose(le.ukf(repaired, flight).means, le.ukf(prior, flight).means)


def test_the_notebook_knode_picks_its_prior_from_the_flights_inputs_as_the_cli_demo_does():
    """No system given: a NanoBench log with motor PWM and battery voltage trains the Crazyflie prior, a log
    without motor channels the kinematic one (`models.inputs.prior_for_flights`, which ``learnest demo`` uses
    too); the fitted estimator says which, and an asked-for prior is kept."""
    from learnest.models.inputs import prior_for_flights

    nanobench, plain = le.read_flights([SAMPLES / "B2_circle_fast_rep1.csv", SAMPLES / "circle_rep1.csv"])
    assert "motors" in nanobench.channels and "motors" not in plain.channels
    assert le.KNODE().system is None
    driven = le.KNODE(epochs=2).fit(nanobench)
    assert driven.system_ == "crazyflie" and driven.model_.system.name == "crazyflie"
    kinematic = le.KNODE(epochs=2).fit(plain)
    assert kinematic.system_ == "quadrotor" and kinematic.model_.system.name == "quadrotor"
    assert le.KNODE(system="quadrotor", epochs=2).fit(nanobench).system_ == "quadrotor"
    # the one rule: every flight must carry the inputs, unless fewer are asked for (the demo asks for two)
    assert prior_for_flights([nanobench, plain]) == "quadrotor"
    assert prior_for_flights([nanobench, nanobench, plain], least=2) == "crazyflie"
    assert prior_for_flights([]) == "quadrotor"
