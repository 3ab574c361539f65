"""The thrust axis calibrated against the mocap body frame (`models.crazyflie.thrust_axis`): an exact circle flown
with a known offset between the markers' frame and the motors' axis, and the real NanoBench flight whose
offset is largest."""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.ingest.frames import GRAVITY, quat_to_matrix
from learnest.models.crazyflie.thrust_axis import calibrated_attitude, heading_removed, thrust_axis_offset
from learnest.models.inputs import ATTITUDE_CALIBRATED, flight_thrust_axis, system_inputs
from learnest.models.systems import make_system

NANOBENCH = Path(__file__).resolve().parents[4] / "shared" / "data" / "nanobench"
needs_data = pytest.mark.skipif(not NANOBENCH.is_dir(), reason="../shared/data/nanobench not present")


def circle_with_offset(offset, seconds=20.0, dt=0.01, radius=0.5, omega=2.0):
    """p (T, 3) of a level circle, the motors' axis along p̈ + g e₃ (yaw 0), and the mocap attitude of
    markers whose frame sees that axis at body direction d = (offset, √(1 − |offset|²))."""
    t = np.arange(int(seconds / dt)) * dt
    p = np.column_stack([radius * np.cos(omega * t), radius * np.sin(omega * t), np.ones_like(t)])
    acc = np.column_stack([-omega**2 * p[:, 0], -omega**2 * p[:, 1], np.zeros_like(t)])
    thrust_dir = acc + [0.0, 0.0, GRAVITY]
    thrust_dir /= np.linalg.norm(thrust_dir, axis=1, keepdims=True)
    # the vehicle's attitude: the shortest rotation taking e₃ to the thrust direction (no yaw)
    axis = np.cross([0.0, 0.0, 1.0], thrust_dir)
    angle = np.arcsin(np.linalg.norm(axis, axis=1))
    vehicle = Rotation.from_rotvec(axis / np.linalg.norm(axis, axis=1, keepdims=True) * angle[:, None])
    d = np.array([offset[0], offset[1], np.sqrt(1.0 - offset[0] ** 2 - offset[1] ** 2)])
    d_axis = np.cross([0.0, 0.0, 1.0], d)
    sine = np.linalg.norm(d_axis)
    delta = Rotation.from_rotvec(d_axis * (np.arcsin(sine) / sine if sine > 0 else 1.0))
    markers = vehicle * delta.inv()        # R_markers · d = R_vehicle · e₃ = thrust direction
    return t, p, markers.as_quat(), thrust_dir


def test_offset_of_an_exact_circle_is_recovered_and_the_calibrated_attitude_points_along_the_thrust():
    offset = (0.03, -0.02)                   # 1.7° and -1.1°
    t, p, quat, thrust_dir = circle_with_offset(offset)
    found = thrust_axis_offset(p, quat, t[1] - t[0])
    np.testing.assert_allclose(found, offset, atol=2e-4)
    body_z = quat_to_matrix(calibrated_attitude(quat, found))[:, :, 2]
    raw_z = quat_to_matrix(quat)[:, :, 2]
    assert np.degrees(np.arccos(np.clip(np.sum(body_z * thrust_dir, axis=1), -1, 1))).max() < 0.02
    assert np.degrees(np.arccos(np.clip(np.sum(raw_z * thrust_dir, axis=1), -1, 1))).min() > 1.9   # 2.1° before


def test_removing_the_heading_keeps_the_body_z_axis_and_the_crazyflie_prior_exactly():
    rng = np.random.default_rng(4)
    tilted = Rotation.from_rotvec(np.column_stack([rng.normal(0, 0.3, (200, 2)), rng.uniform(-3, 3, 200)]))
    spun = tilted * Rotation.from_euler("z", rng.uniform(-np.pi, np.pi, (200, 1)))     # another heading, same body z
    free = heading_removed(tilted.as_quat())
    assert np.abs(free[:, 2]).max() == 0.0 and np.allclose(np.linalg.norm(free, axis=1), 1.0)
    np.testing.assert_allclose(quat_to_matrix(free)[:, :, 2], tilted.as_matrix()[:, :, 2], atol=1e-12)
    np.testing.assert_allclose(heading_removed(spun.as_quat()), free, atol=1e-12)
    # the prior's vector field (thrust along body z, rotor drag the same along body x and y) does not change
    system = make_system("crazyflie")
    x = np.column_stack([rng.normal(0, 1, (200, 3)), rng.normal(0, 1.5, (200, 3)), rng.normal(0, 2, (200, 3))])
    u = np.column_stack([tilted.as_quat(), rng.uniform(40000, 65000, (200, 4)), rng.uniform(3.2, 4.1, 200)])
    u_free = u.copy()
    u_free[:, :4] = free
    np.testing.assert_allclose(system.f_prior(x, u_free), system.f_prior(x, u), rtol=1e-10, atol=1e-10)
    upside_down = heading_removed(Rotation.from_euler("x", np.pi).as_quat()[None])
    np.testing.assert_allclose(quat_to_matrix(upside_down)[0, :, 2], [0.0, 0.0, -1.0], atol=1e-12)


def test_no_offset_gives_zero_and_the_attitude_unchanged():
    t, p, quat, _ = circle_with_offset((0.0, 0.0))
    assert np.abs(thrust_axis_offset(p, quat, 0.01)).max() < 2e-4
    np.testing.assert_allclose(calibrated_attitude(quat, np.zeros(2)), quat)


def test_a_short_record_is_not_calibrated_and_a_wrong_attitude_is_refused_with_the_flight_name():
    t, p, quat, _ = circle_with_offset((0.0, 0.0), seconds=2.0)
    assert thrust_axis_offset(p, quat, 0.01).tolist() == [0.0, 0.0]
    t, p, quat, _ = circle_with_offset((0.0, 0.0))
    tilted = (Rotation.from_quat(quat) * Rotation.from_euler("x", 30, degrees=True)).as_quat()  # 30° off
    flight = Flight(t, p, np.zeros_like(p), tilted, {}, {"name": "tilted markers"})
    with pytest.raises(InvalidInput, match=r"tilted markers: .*30\.0° off the mocap body z axis"):
        flight_thrust_axis(flight)
    broken = quat.copy()
    broken[100] = 0.0                         # a zero quaternion: a dropped mocap frame written as zeros
    flight = Flight(t, p, np.zeros_like(p), broken, {"motors": np.full((len(t), 4), 40000.0),
                                                    "vbat": np.full((len(t), 1), 3.7)}, {"name": "dropped frame"})
    with pytest.raises(InvalidInput, match=r"dropped frame: .*non-finite or zero quaternions"):
        system_inputs(flight, make_system("crazyflie"))


@needs_data
def test_on_the_real_flight_with_the_largest_offset_the_calibrated_crazyflie_prior_tracks_far_better():
    """B3_figure8_medium_rep2: the specific force leans ~2.7° off the mocap z axis; the Crazyflie prior's UKF
    with the mocap attitude as logged scored 0.041 (the kinematic prior 0.024), calibrated 0.021
    (benchmarks/results/crazyflie_thrust_axis)."""
    from learnest.estimators.params import EstimatorParams
    from learnest.estimators.prepared import initial_state, system_for
    from learnest.estimators.ukf import run_ukf
    from learnest.ingest import read_flights
    from learnest.ingest.baseline import references
    from learnest.models.knode import HybridModel
    from learnest.models.presets import SG_WINDOW

    flight = read_flights([NANOBENCH / "B3_figure8_medium_rep2.csv"])[0]
    offset = np.degrees(flight_thrust_axis(flight))
    assert 2.0 < np.hypot(*offset) < 3.5
    system = system_for(flight, "crazyflie")
    calibrated = system_inputs(flight, system)
    raw = calibrated.copy()
    raw[:, :4] = flight.quat
    reference = references(flight, window=SG_WINDOW)
    steps = 1200                    # the first 12 s of the 33 s flight: the offset acts throughout
    mse = {}
    for name, u in (("raw", raw), ("calibrated", calibrated)):
        params = EstimatorParams(HybridModel(system, "prior"), flight.dt, system.Q, system.R, system.P0,
                                 initial_state(flight))
        means = run_ukf(params, flight.measurements()[:steps], u[:steps]).means
        mse[name] = float(np.mean((means - reference[:steps]) ** 2))
    assert mse["calibrated"] < 0.7 * mse["raw"], mse


def test_a_crazyflie_knode_trained_before_the_calibration_is_scored_with_a_warning():
    from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
    from learnest.models.knode import HybridModel, Residual
    from learnest.models.systems import make_system
    from learnest.service.cli import format_report
    from learnest.workflows.flights import evaluate_flights

    system = make_system("crazyflie")
    zero_net = Residual([(np.zeros((4, system.n + system.n_inputs)), np.zeros(4)), (np.zeros((9, 4)), np.zeros(9))])
    flight = simulate_crazyflie(SimulatedFlight(duration_s=6, vbat=(4.0, 3.8)))
    for meta, warned in (({}, "the mocap attitude as logged"),
                         ({"attitude_input": "mocap attitude calibrated onto the thrust axis"}, "onto the thrust axis)"),
                         ({"attitude_input": ATTITUDE_CALIBRATED}, None)):
        report = evaluate_flights(HybridModel(system, "knode", zero_net, meta), [flight], ["ukf"])
        entry = report["flights"][0]
        assert not entry["excluded"]
        warnings = [w for w in entry["warnings"] if "trained on another attitude input" in w]
        assert (warnings and warned in warnings[0]) if warned else not warnings
        assert np.hypot(*entry["thrust_axis_offset_deg"]) < 0.3     # the simulator's motors push along body z
        assert "thrust axis vs mocap frame (deg, x/y): " in format_report(report)


def test_the_model_a_crazyflie_diagnosis_repairs_records_its_calibrated_attitude_input():
    """The repaired model a diagnosis registers was trained on `system_inputs`: its meta must say so, or every
    evaluation of it would carry the warning for models trained on the raw attitude."""
    from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
    from learnest.workflows.diagnosis import diagnose_flights

    flights = [simulate_crazyflie(SimulatedFlight(duration_s=8), seed=seed) for seed in (0, 1)]
    _, repaired = diagnose_flights(flights, methods=("ukf",), epochs=1, return_model=True, system="crazyflie")
    assert repaired.kind == "knode" and repaired.meta["attitude_input"] == ATTITUDE_CALIBRATED
