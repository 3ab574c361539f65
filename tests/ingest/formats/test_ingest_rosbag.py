"""ROS bags (ROS 2 sqlite3 .db3, ROS 2 MCAP storage, ROS 1 .bag) written with rosbags from the real message
definitions: every pose type read back against the analytic flight, topic and vehicle choice, the candidate
list, the onboard-estimate warning, damaged files, the CLI's --pose-topic and an upload with pose_topic."""
import numpy as np
import pytest
from utils.analytic_flight import (
    acc_interpolation_tolerance,
    accelerometer_g,
    assert_matches_truth,
    imu_times,
    mocap_times,
    true_position,
    true_quaternion,
)

from learnest.ingest import detect, read_flights, summary
from learnest.ingest.flight import IngestError
from learnest.ingest.formats.rosbag import container as bag_container
from learnest.ingest.formats.rosbag.writer import BagWriter
from learnest.service.cli import main

OFFSET = np.array([1.5, -0.5, 0.2])    # cf2 flies the same path, shifted


def swarm_bag(tmp_path, storage, *, with_mocap=True, name="swarm"):
    """Two Crazyflies as crazyswarm2 records them: mocap /poses (NamedPoseArray), each one's onboard estimate
    /cfX/pose (1 cm off) and its IMU /cfX/imu (cf2's reads 1.1x, so a mix-up shows)."""
    t, t_acc = mocap_times(), imu_times()
    p, q, acc = true_position(t), true_quaternion(t), accelerometer_g(t_acc)
    path = tmp_path / (f"{name}.bag" if storage == "ros1" else name)
    with BagWriter(path, storage) as bag:
        if with_mocap:
            bag.add_bodies("/poses", t, {"cf1": (p, q), "cf2": (p + OFFSET, q)})
        bag.add_pose("/cf1/pose", t, p + 0.01, q)
        bag.add_imu("/cf1/imu", t_acc, acc)
        if with_mocap:
            bag.add_pose("/cf2/pose", t, p + OFFSET + 0.01, q)
            bag.add_imu("/cf2/imu", t_acc, acc * 1.1)
    return bag.storage_file


@pytest.mark.parametrize("storage, adapter", [("sqlite3", "rosbag-ros2"), ("ros1", "rosbag-ros1"),
                                              ("mcap", "mcap-ros2")])
def test_each_storage_reads_the_chosen_vehicle_and_its_imu(tmp_path, storage, adapter):
    path = swarm_bag(tmp_path, storage)
    assert detect(path) == ("mcap" if storage == "mcap" else "rosbag")
    flight = read_flights([path], pose_topic="/poses:cf1")[0]
    assert flight.meta["adapter"] == adapter and flight.meta["vehicle"] == "cf1"
    assert flight.meta["topics"]["pose"] == "/poses:cf1" and flight.meta["topics"]["accel"] == "/cf1/imu"
    assert flight.meta["topics"]["pose_source"] == "motion capture" and flight.meta["warnings"] == []
    assert_matches_truth(flight, acc_interpolation_tolerance())
    cf2 = read_flights([path], pose_topic="/poses:cf2")[0]
    assert cf2.meta["topics"]["accel"] == "/cf2/imu"            # the vehicle named by the pose picks its IMU
    np.testing.assert_allclose(cf2.p, flight.p + OFFSET, atol=1e-9)


def test_several_vehicles_without_a_choice_list_every_candidate(tmp_path):
    path = swarm_bag(tmp_path, "sqlite3")
    n = len(mocap_times())
    with pytest.raises(IngestError) as error:
        read_flights([path])
    message = str(error.value)
    assert path.name in message and "4 candidate motion-capture pose topics" in message
    assert f"/poses:cf1 (motion_capture_tracking_interfaces/msg/NamedPoseArray, cdr, {n} messages, motion capture)" \
        in message and "/poses:cf2 (" in message
    assert f"/cf1/pose (geometry_msgs/msg/PoseStamped, cdr, {n} messages, onboard estimate)" in message
    assert "--pose-topic" in message and "pose_topic" in message
    with pytest.raises(IngestError, match="carries 2 bodies.*/poses:cf1.*/poses:cf2"):
        read_flights([path], pose_topic="/poses:cf9")
    with pytest.raises(IngestError, match="no topic '/vicon/cf1'.*/cf2/imu"):
        read_flights([path], pose_topic="/vicon/cf1")
    with pytest.raises(IngestError, match="cannot be read as acceleration"):
        read_flights([path], pose_topic="/poses:cf1", imu_topic="/cf1/pose")


def test_an_onboard_estimate_alone_is_read_with_a_warning(tmp_path):
    path = swarm_bag(tmp_path, "sqlite3", with_mocap=False)
    flight = read_flights([path])[0]
    assert flight.meta["topics"]["pose"] == "/cf1/pose" and flight.meta["topics"]["pose_source"] == "onboard estimate"
    assert len(flight.meta["warnings"]) == 1 and "onboard estimate, not motion capture" in flight.meta["warnings"][0]
    assert summary(flight)["warnings"] == flight.meta["warnings"]
    t = mocap_times()
    np.testing.assert_allclose(flight.p, true_position(t)[: len(flight.p)] + 0.01, atol=1e-9)


@pytest.mark.parametrize("pose_type, topic, source", [
    ("TFMessage", "/tf:cf1", "unknown"),
    ("Odometry", "/cf1/odom", "onboard estimate"),
    ("PoseWithCovarianceStamped", "/optitrack/cf1", "motion capture"),
    ("TransformStamped", "/vicon/cf1/cf1", "motion capture"),
])
def test_every_pose_type_matches_the_truth(tmp_path, pose_type, topic, source):
    t, t_acc = mocap_times(), imu_times()
    p, q = true_position(t), true_quaternion(t)
    with BagWriter(tmp_path / "bag", "sqlite3") as bag:
        if pose_type == "TFMessage":
            bag.add_bodies("/tf", t, {"cf1": (p, q)}, message_type="TFMessage")
            bag.add_bodies("/tf", t, {"propeller": (p * 0, q)}, frame_id="cf1", message_type="TFMessage")
        else:
            bag.add_pose(topic, t, p, q, message_type=pose_type)
        bag.add_imu("/cf1/imu", t_acc, accelerometer_g(t_acc))
    flight = read_flights([bag.storage_file])[0]
    assert flight.meta["topics"]["pose"] == topic and flight.meta["topics"]["pose_source"] == source
    assert bool(flight.meta["warnings"]) == (source == "onboard estimate")
    assert_matches_truth(flight, acc_interpolation_tolerance())


def test_content_not_the_name_decides(tmp_path):
    """A .db3 or .bag renamed without its extension is still found and read (rosbags needs the suffix: a link)."""
    for storage in ("sqlite3", "ros1"):
        source = swarm_bag(tmp_path, storage, name=f"orig_{storage}")
        renamed = tmp_path / f"upload_{storage}"
        renamed.write_bytes(source.read_bytes())
        assert detect(renamed) == "rosbag"
        assert read_flights([renamed], pose_topic="/poses:cf2")[0].meta["topics"]["accel"] == "/cf2/imu"


def test_compressed_ros1_chunks_are_capped(tmp_path, monkeypatch):
    from rosbags.rosbag1 import Writer

    t, t_acc = mocap_times(), imu_times()
    monkeypatch.setattr(Writer, "open", _open_with_bz2(Writer.open))
    with BagWriter(tmp_path / "bz2.bag", "ros1") as bag:
        bag.add_pose("/vicon/cf1/cf1", t, true_position(t), true_quaternion(t), message_type="TransformStamped")
        bag.add_imu("/cf1/imu", t_acc, accelerometer_g(t_acc))
    assert_matches_truth(read_flights([tmp_path / "bz2.bag"])[0], acc_interpolation_tolerance())
    monkeypatch.setattr(bag_container, "MAX_EXPANSION", 1)     # sensor data compresses more than 1x
    with pytest.raises(IngestError, match="bz2.bag.*decompression bomb"):
        read_flights([tmp_path / "bz2.bag"])


def _open_with_bz2(open_bag):
    def opened(self):
        self.set_compression(self.CompressionFormat.BZ2)
        return open_bag(self)
    return opened


def test_damaged_and_foreign_files_name_the_file(tmp_path):
    path = swarm_bag(tmp_path, "ros1")
    cut = tmp_path / "cut.bag"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(IngestError, match="cut.bag: cannot open the ROS 1 bag"):
        read_flights([cut])
    import sqlite3
    foreign = tmp_path / "notes.db3"
    with sqlite3.connect(foreign) as db:
        db.execute("create table notes (text)")
    with pytest.raises(IngestError, match="notes.db3: cannot open the ROS 2 sqlite3 bag"):
        read_flights([foreign])


def test_cli_chooses_topics_and_prints_them(tmp_path, capsys):
    path = swarm_bag(tmp_path, "sqlite3")
    assert main(["ingest", str(path)]) == 2
    err = capsys.readouterr().err
    assert "candidate motion-capture pose topics" in err and "/poses:cf2" in err and "--pose-topic" in err
    assert main(["ingest", str(path), "--pose-topic", "/poses:cf2", "--imu-topic", "/cf2/imu"]) == 0
    out = capsys.readouterr().out
    assert "pose from /poses:cf2 (motion_capture_tracking_interfaces/msg/NamedPoseArray, motion capture)" in out
    assert "acceleration from /cf2/imu" in out
    assert main(["ingest", str(path), "--pose-topic", "/cf1/pose"]) == 0
    assert "WARNING: the pose topic /cf1/pose is the vehicle's onboard estimate" in capsys.readouterr().out


def test_cli_refuses_a_bad_topic_before_reading(tmp_path, capsys):
    missing = str(tmp_path / "missing.db3")
    assert main(["ingest", missing, "--pose-topic", "/poses cf1"]) == 2
    err = capsys.readouterr().err
    assert "argument --pose-topic: topic '/poses cf1' is not a topic name" in err and "missing" not in err


def test_upload_with_pose_topic_one_flight_per_vehicle(tmp_path):
    from utils.service import running_app, upload

    path = swarm_bag(tmp_path, "sqlite3")
    with running_app(tmp_path / "home") as client:
        refused = upload(client, path)
        assert refused.status_code == 422 and "/poses:cf1" in refused.json()["detail"] and path.name in \
            refused.json()["detail"]
        first = upload(client, path, pose_topic="/poses:cf1")
        second = upload(client, path, pose_topic="/poses:cf2")
        again = upload(client, path, pose_topic="/poses:cf1")
        assert (first.status_code, second.status_code, again.status_code) == (201, 201, 200), second.text
        assert first.json()["vehicle"] == "cf1" and second.json()["vehicle"] == "cf2"
        assert again.json()["id"] == first.json()["id"] != second.json()["id"]
        detail = client.get(f"/flights/{second.json()['id']}").json()
        assert detail["meta"]["topics"]["pose"] == "/poses:cf2" and detail["meta"]["topics"]["accel"] == "/cf2/imu"
        onboard = upload(client, path, pose_topic="/cf1/pose", imu_topic="/cf1/imu")
        assert onboard.status_code == 201
        page = client.get(f"/ui/flights/{onboard.json()['id']}").text
        assert "/cf1/pose" in page and "onboard estimate, not motion capture" in page
        assert upload(client, path, pose_topic="/poses;rm").status_code == 422


def true_gyro(t):
    """A known body rate (rad/s), slow enough that the 100 Hz grid and the anti-alias filter keep it."""
    return np.column_stack([0.3 * np.sin(2.0 * t), -0.2 * np.cos(1.3 * t), 0.5 * np.sin(0.7 * t) + 0.1])


@pytest.mark.parametrize("storage", ["sqlite3", "ros1", "mcap"])
def test_the_imus_angular_velocity_is_the_gyro_channel_and_a_zero_one_is_noted(tmp_path, storage):
    t, t_acc = mocap_times(), imu_times()
    p, q, acc = true_position(t), true_quaternion(t), accelerometer_g(t_acc)
    paths = {}
    for name, gyro in (("with", true_gyro(t_acc)), ("not_provided", None), ("zeros", np.zeros((len(t_acc), 3)))):
        path = tmp_path / name / (f"{name}.bag" if storage == "ros1" else name)
        path.parent.mkdir()
        with BagWriter(path, storage) as bag:
            bag.add_pose("/mocap/cf1/pose", t, p, q)
            bag.add_imu("/cf1/imu", t_acc, acc, gyro_rad_s=gyro)
        paths[name] = bag.storage_file
    container = "mcap" if storage == "mcap" else "rosbag"
    flight = read_flights([paths["with"]])[0]
    source_t = flight.t + flight.meta["t0_source_s"] + flight.meta.get("flying_window", {}).get("start_s", 0.0)
    np.testing.assert_allclose(flight.channels["gyro"], true_gyro(source_t), atol=1e-4)
    assert flight.meta[container]["inputs"]["gyro"]["topic"] == "/cf1/imu"
    # covariance -1: the driver declares no angular velocity, nothing to say; zeros throughout: said
    not_provided, zeros = (read_flights([paths[name]])[0] for name in ("not_provided", "zeros"))
    assert "gyro" not in not_provided.channels and not_provided.meta[container]["warnings"] == []
    assert "gyro" not in zeros.channels
    assert any("angular_velocity is zero" in note for note in zeros.meta[container]["warnings"])
