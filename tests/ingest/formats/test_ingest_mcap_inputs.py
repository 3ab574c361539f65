"""The Crazyflie's inputs in MCAP recordings and ROS 2 bags: crazyswarm2's LogDataGeneric topics, named by a
crazyflies.yaml beside the file or by log_variables, become the channels a uSD/cfclient log gives (same
names, same unit converters), and the Crazyflie prior's inputs can be taken from them."""
import numpy as np
import pytest

from learnest.ingest import read_flights
from learnest.ingest.formats.mcap import reader as mcap_reader
from learnest.ingest.formats.mcap import writer as mcap_writer
from learnest.ingest.formats.mcap.inputs import crazyswarm_log_variables
from learnest.ingest.formats.rosbag import reader as rosbag_reader
from learnest.ingest.formats.rosbag.writer import BagWriter
from learnest.ingest.frames import GRAVITY
from learnest.ingest.sim import write_canonical_flight
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.crazyflie.thrust_axis import calibrated_attitude, heading_removed
from learnest.models.inputs import MissingInputs, flight_thrust_axis, system_inputs
from learnest.models.systems import Crazyflie, Quadrotor

INNER = slice(5, -5)    # the grid's ends hold the first/last sample


@pytest.fixture(scope="module")
def flight():
    """A short closed-loop Crazyflie flight with known motor PWM and a battery sagging 4.1 -> 3.4 V."""
    return simulate_crazyflie(SimulatedFlight(duration_s=8, vbat=(4.1, 3.4)))


def _on_read_grid(read, sim_t, values):
    """The simulation's values interpolated at the read Flight's rows (a ROS recording's clock starts at the
    simulation's t = 0; the reader cut take-off and landing)."""
    t = read.t + read.meta["t0_source_s"] + read.meta["flying_window"]["start_s"]
    values = np.asarray(values, float).reshape(len(sim_t), -1)
    return np.column_stack([np.interp(t, sim_t, column) for column in values.T])


def test_a_ros2_mcap_with_crazyswarm_topics_gives_the_crazyflie_prior_its_inputs(flight, tmp_path):
    files = write_canonical_flight(flight, "mcap-ros2", tmp_path, "flight")
    assert (tmp_path / "flight_crazyflies.yaml").is_file()      # what names the LogDataGeneric values
    read = read_flights(files)[0]
    assert read.meta["mcap"]["inputs"]["motors"]["topic"] == "/cf1/motors"
    assert read.meta["mcap"]["inputs"]["vbat"]["variables"] == ["pm.vbat"]
    for name, tolerance in (("motors", 0.5), ("vbat", 1e-6)):   # linear resampling of a 100 Hz stream on its grid
        got = np.asarray(read.channels[name]).reshape(len(read.t), -1)
        expected = _on_read_grid(read, flight.t, flight.channels[name])
        assert np.abs(got - expected)[INNER].max() < tolerance, name
    u = system_inputs(read, Crazyflie(), motor_heating=False)   # the channels as logged (no thermal state)
    assert u.shape == (len(read.t), Crazyflie().n_inputs)
    # the attitude, calibrated onto the thrust axis: the simulator's motors push along its body z
    assert np.degrees(np.abs(flight_thrust_axis(read))).max() < 0.3
    np.testing.assert_allclose(u[:, :4], heading_removed(calibrated_attitude(read.quat, flight_thrust_axis(read))))
    np.testing.assert_allclose(u[:, 4:8], read.channels["motors"])
    np.testing.assert_allclose(u[:, 8], np.ravel(read.channels["vbat"]))
    # the flight is airborne throughout and read whole: the battery as simulated (its sag and its noise)
    logged = np.ravel(flight.channels["vbat"])
    assert logged.min() - 1e-6 <= u[:, 8].min() < 3.45 and 4.05 < u[:, 8].max() <= logged.max() + 1e-6


def test_a_ros2_db3_with_log_variables_converts_each_unit_like_the_usd_reader(flight, tmp_path):
    """Other firmware variables, in their firmware units: mV, rpm, deg/s, N; the accelerometer shares a topic
    with the gyro, as a crazyswarm2 user may log it."""
    t = flight.t
    vbat_mv = 4100.0 - 700.0 * t / t[-1]
    rpm = 15000.0 + 1000.0 * np.sin(np.outer(t, [1.0, 1.3, 1.7, 2.1]))
    gyro_deg_s = 30.0 * np.sin(np.outer(t, [0.9, 1.1, 0.5]))
    thrust_n = 0.3 + 0.02 * np.cos(t)
    acc_g = np.asarray(flight.channels["acc_body"]) / GRAVITY
    with BagWriter(tmp_path / "bag", "sqlite3") as bag:
        bag.add_pose("/mocap/cf1/pose", t, flight.p, flight.quat)
        bag.add_log_data("/cf1/imu", t, np.column_stack([gyro_deg_s, acc_g]))
        bag.add_log_data("/cf1/power", t, np.column_stack([vbat_mv, thrust_n]))
        bag.add_log_data("/cf1/rpm", t, rpm)
    log_variables = {"/cf1/imu": ["gyro.x", "gyro.y", "gyro.z", "acc.x", "acc.y", "acc.z"],
                     "/cf1/power": ["pm.vbatMV", "ctrlLee.thrustSI"],
                     "/cf1/rpm": ["rpm.m1", "rpm.m2", "rpm.m3", "rpm.m4"]}
    read = rosbag_reader.read(bag.storage_file, log_variables=log_variables)
    assert read.meta["topics"]["accel"] == "/cf1/imu"
    expected = {"vbat": vbat_mv / 1000.0, "rotor_speed": rpm * 2.0 * np.pi / 60.0,
                "gyro": np.radians(gyro_deg_s), "thrust_si": thrust_n}
    for name, values in expected.items():
        got = np.asarray(read.channels[name]).reshape(len(read.t), -1)
        want = _on_read_grid(read, t, values)
        scale = np.abs(want).max()
        assert np.abs(got - want)[INNER].max() < 1e-3 * scale, name
    assert "motors" not in read.channels
    with pytest.raises(MissingInputs, match="motor PWM") as missing:
        system_inputs(read, Crazyflie())
    assert "battery voltage" not in str(missing.value)      # vbat came from pm.vbatMV


def test_a_recording_without_input_topics_reads_and_the_crazyflie_prior_names_what_is_missing(flight, tmp_path):
    path = tmp_path / "plain.mcap"
    acc_g = np.asarray(flight.channels["acc_body"]) / GRAVITY
    mcap_writer.write_ros2(path, flight.t, flight.p, flight.quat, acc_g)
    read = mcap_reader.read(path)
    assert not {"motors", "vbat"} & set(read.channels)
    assert read.meta["mcap"]["inputs"] == {}
    assert system_inputs(read, Quadrotor()).shape == (len(read.t), 0)     # the kinematic prior needs none
    with pytest.raises(MissingInputs, match="motor PWM.*battery voltage.*kinematic prior"):
        system_inputs(read, Crazyflie())


def test_an_unreadable_crazyflies_yaml_is_a_warning_and_the_flight_still_reads(flight, tmp_path):
    files = write_canonical_flight(flight, "mcap-ros2", tmp_path, "flight")
    (tmp_path / "flight_crazyflies.yaml").write_text("robots: [cf1:\n")
    read = read_flights(files)[0]
    assert not {"motors", "vbat"} & set(read.channels)
    assert any("flight_crazyflies.yaml" in note and "not used" in note for note in read.meta["mcap"]["warnings"])


def test_crazyflies_yaml_topics_merge_all_robot_type_and_robot_scopes():
    motors = ["motor.m1", "motor.m2", "motor.m3", "motor.m4"]
    config = {
        "robots": {"cf1": {"type": "cf21", "firmware_logging": {"custom_topics": {"power": {"vars": ["pm.vbatMV"]}}}},
                   "cf2": {"type": "other"}, "broken": "not a mapping"},
        "robot_types": {"cf21": {"firmware_logging": {"custom_topics": {"motors": {"frequency": 100, "vars": motors},
                                                                         "bad": {"vars": "pm.vbat"}}}}},
        "all": {"firmware_logging": {"enabled": True, "custom_topics": {"power": {"vars": ["pm.vbat"]}}}},
    }
    assert crazyswarm_log_variables(config) == {"/cf1/power": ["pm.vbatMV"], "/cf1/motors": motors,
                                                "/cf2/power": ["pm.vbat"], "/broken/power": ["pm.vbat"]}
    assert crazyswarm_log_variables(["not", "a", "config"]) == {}


def test_crazyflies_yaml_beside_a_recording_is_read_with_it_from_a_folder_and_an_upload(flight, tmp_path):
    from learnest.ingest import collect_logs
    from learnest.service.jobs.reading import read_uploaded_flight
    from learnest.service.operations.uploads import LocalFile, stage_uploads

    folder = tmp_path / "run"
    write_canonical_flight(flight, "mcap-ros2", folder, "flight")
    (folder / "flight_crazyflies.yaml").rename(folder / "crazyflies.yaml")    # the folder's configuration
    logs, notes = collect_logs([folder])
    assert logs == [folder / "flight.mcap"]
    assert any(note.startswith("crazyflies.yaml: metadata of") for note in notes)
    read = read_flights(logs)[0]
    assert {"motors", "vbat"} <= set(read.channels)
    assert [s["path"] for s in read.meta["sources"]] == [str(folder / "flight.mcap"), str(folder / "crazyflies.yaml")]

    staging = tmp_path / "staging"           # uploaded together (web form, POST /flights)
    staging.mkdir()
    with open(folder / "crazyflies.yaml", "rb") as config, open(folder / "flight.mcap", "rb") as recording:
        staged = stage_uploads([LocalFile("crazyflies.yaml", config), LocalFile("flight.mcap", recording)], staging)
    assert [f.role for f in staged] == ["sidecar", "log"]
    uploaded = read_uploaded_flight(staged)
    assert {"motors", "vbat"} <= set(uploaded.channels)
    assert [s["path"] for s in uploaded.meta["sources"]] == ["flight.mcap", "crazyflies.yaml"]   # the client's names
