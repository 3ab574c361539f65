"""MCAP recordings: ROS 2 and JSON round trips against an analytic flight, topic choice, damaged files,
fuzzing."""
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from utils.analytic_flight import (  # noqa: E402  (shared with the bag tests)
    DURATION,
    IMU_RATE,
    MOCAP_RATE,
    Z_UP,
    acc_interpolation_tolerance,
    accelerometer_g,
    assert_matches_truth,
    imu_times,
    mocap_times,
    source_times,
    true_acceleration,
    true_position,
    true_quaternion,
    true_rotation,
)

from learnest.ingest.flight import IngestError, sha256_file
from learnest.ingest.formats.mcap import container as mcap_container
from learnest.ingest.formats.mcap import reader as mcap_reader
from learnest.ingest.formats.mcap import schemas as mcap_schemas
from learnest.ingest.formats.mcap import writer as mcap_writer
from learnest.ingest.frames import GRAVITY, quat_to_matrix


def write_flight(path, variant, **options):
    t, t_acc = mocap_times(), imu_times()
    p, quat, acc = true_position(t), true_quaternion(t), accelerometer_g(t_acc)
    if variant == "json":
        mcap_writer.write_json(path, t, p, quat, acc, t_acc=t_acc, **options)
    else:
        pose_type, accel_type = variant.split("+")
        mcap_writer.write_ros2(path, t, p, quat, acc, t_acc=t_acc, pose_type=pose_type, accel_type=accel_type,
                               **options)


def test_truth_is_consistent():
    t = mocap_times()
    np.testing.assert_allclose(quat_to_matrix(true_quaternion(t)), true_rotation(t), atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(accelerometer_g(t), axis=1),
                               np.linalg.norm(true_acceleration(t) + GRAVITY * Z_UP, axis=1) / GRAVITY)
    assert np.all(np.abs(accelerometer_g(t)) > 0.05)         # all three axes carry signal
    # The specific force changes slowly in the body frame (only its magnitude varies), so linear
    # interpolation between 250 Hz samples is accurate to ~1e-7 m/s²: the tolerance is that tight.
    assert acc_interpolation_tolerance() < 1e-6


# -- round trips -------------------------------------------------------------------------------------------

@pytest.mark.parametrize("variant, adapter, pose_topic, accel_topic", [
    ("PoseStamped+Imu", "mcap-ros2", "/mocap/cf1/pose", "/cf1/imu"),
    ("TransformStamped+LogDataGeneric", "mcap-ros2", "/vicon/cf1/cf1", "/cf1/acc"),
    ("json", "mcap-json", "/cf1/mocap_pose", "/cf1/acceleration"),
])
def test_round_trip_recovers_the_flight(tmp_path, variant, adapter, pose_topic, accel_topic):
    path = tmp_path / "flight.mcap"
    write_flight(path, variant)
    flight = mcap_reader.read(path)
    assert_matches_truth(flight, acc_interpolation_tolerance())
    assert flight.duration_s == pytest.approx(DURATION)
    assert flight.meta["adapter"] == adapter
    assert flight.meta["sources"] == [{"path": str(path), "sha256": sha256_file(path)}]
    assert flight.meta["clock_offset_s"] is None
    assert flight.meta["original_rates"]["mocap"] == pytest.approx(MOCAP_RATE)
    assert flight.meta["original_rates"]["acc"] == pytest.approx(IMU_RATE)
    mcap_meta = flight.meta["mcap"]
    assert (mcap_meta["pose_topic"], mcap_meta["accel_topic"]) == (pose_topic, accel_topic)
    stamp = "timestamp" if variant == "json" else "header.stamp"
    assert mcap_meta["time_source"] == {"pose": stamp, "accel": stamp}
    assert mcap_meta["time_origin_ns"] == mcap_writer.DEFAULT_START_NS
    assert mcap_meta["warnings"] == []
    assert mcap_meta["streams"]["accel"]["kept"] == len(imu_times())


def test_json_vector3_without_unit_in_m_s2_is_inferred(tmp_path):
    t, t_acc = mocap_times(), imu_times()
    with mcap_writer.JsonMcapWriter(tmp_path / "flight.mcap") as recording:
        recording.add_pose("/mocap", t, true_position(t), true_quaternion(t))
        recording.add_acceleration("/imu/acc", t_acc, accelerometer_g(t_acc), unit=None, schema_name="foxglove.Vector3")
    with mcap_writer.JsonMcapWriter(tmp_path / "si.mcap") as recording:
        recording.add_pose("/mocap", t, true_position(t), true_quaternion(t))
        recording.add_acceleration("/imu/acc", t_acc, accelerometer_g(t_acc) * GRAVITY, unit=None,
                                   schema_name="foxglove.Vector3")
    for name, unit in (("flight.mcap", "g"), ("si.mcap", "m/s^2")):
        flight = mcap_reader.read(tmp_path / name)
        assert_matches_truth(flight, acc_interpolation_tolerance())
        assert any(f"read as {unit}" in note for note in flight.meta["mcap"]["warnings"])


def test_json_frame_transform_pose(tmp_path):
    t, t_acc = mocap_times(), imu_times()
    with mcap_writer.JsonMcapWriter(tmp_path / "flight.mcap") as recording:
        recording.add_pose("/tf/cf1", t, true_position(t), true_quaternion(t), message_type="FrameTransform")
        recording.add_acceleration("/cf1/acceleration", t_acc, accelerometer_g(t_acc))
    flight = mcap_reader.read(tmp_path / "flight.mcap")
    assert flight.meta["mcap"]["pose_type"] == "foxglove.FrameTransform"
    assert_matches_truth(flight, acc_interpolation_tolerance())


def test_json_acceleration_in_m_s2(tmp_path):
    write_flight(tmp_path / "flight.mcap", "json", unit="m/s^2")
    assert_matches_truth(mcap_reader.read(tmp_path / "flight.mcap"), acc_interpolation_tolerance())


def test_zero_header_stamps_fall_back_to_log_time(tmp_path):
    write_flight(tmp_path / "flight.mcap", "PoseStamped+Imu", stamp_headers=False)
    flight = mcap_reader.read(tmp_path / "flight.mcap")
    assert flight.meta["mcap"]["time_source"] == {"pose": "log_time", "accel": "log_time"}
    assert_matches_truth(flight, acc_interpolation_tolerance())


def test_stamps_on_one_topic_only_use_log_time_for_both(tmp_path):
    t, t_acc = mocap_times(), imu_times()
    with mcap_writer.Ros2BagWriter(tmp_path / "flight.mcap") as bag:
        bag.add_pose("/vicon/cf1/cf1", t, true_position(t), true_quaternion(t), message_type="TransformStamped")
        bag.add_imu("/cf1/imu", t_acc, accelerometer_g(t_acc), stamp_headers=False)
    flight = mcap_reader.read(tmp_path / "flight.mcap")
    assert flight.meta["mcap"]["time_source"] == {"pose": "log_time", "accel": "log_time"}
    assert any("log_time" in note for note in flight.meta["mcap"]["warnings"])


def test_float32_log_data_definition_is_decoded(tmp_path):
    # some crazyswarm2 releases declare float32[] values; the reader uses the definition in the file
    t, t_acc = mocap_times(), imu_times()
    definition = mcap_schemas.LOG_DATA_GENERIC_DEFINITION.replace("float64[] values", "float32[] values")
    assert definition != mcap_schemas.LOG_DATA_GENERIC_DEFINITION
    with mcap_writer.Ros2BagWriter(tmp_path / "flight.mcap") as bag:
        bag.add_pose("/vicon/cf1/cf1", t, true_position(t), true_quaternion(t), message_type="TransformStamped")
        bag.add_log_data("/cf1/acc", t_acc, accelerometer_g(t_acc), definition=definition)
    flight = mcap_reader.read(tmp_path / "flight.mcap")
    float32_rounding = GRAVITY * 2.0**-24 * np.abs(accelerometer_g(t_acc)).max() * np.sqrt(3)
    assert_matches_truth(flight, acc_interpolation_tolerance() + float32_rounding)


def test_log_variables_map_a_custom_log_block(tmp_path):
    t, t_acc = mocap_times(), imu_times()
    gyro = np.full((len(t_acc), 3), 7.0)
    with mcap_writer.Ros2BagWriter(tmp_path / "flight.mcap") as bag:
        bag.add_pose("/vicon/cf1/cf1", t, true_position(t), true_quaternion(t), message_type="TransformStamped")
        bag.add_log_data("/cf1/imu_block", t_acc, np.column_stack([gyro, accelerometer_g(t_acc)]))
    with pytest.raises(IngestError, match="no usable acceleration topic"):
        mcap_reader.read(tmp_path / "flight.mcap")
    with pytest.raises(IngestError, match="log_variables"):
        mcap_reader.read(tmp_path / "flight.mcap", accel_topic="/cf1/imu_block")
    names = {"/cf1/imu_block": ["gyro.x", "gyro.y", "gyro.z", "acc.x", "acc.y", "acc.z"]}
    flight = mcap_reader.read(tmp_path / "flight.mcap", log_variables=names)
    assert flight.meta["mcap"]["accel_topic"] == "/cf1/imu_block"
    assert_matches_truth(flight, acc_interpolation_tolerance())


def test_acc_topic_with_more_than_three_values_needs_a_mapping(tmp_path):
    t, t_acc = mocap_times(), imu_times()
    with mcap_writer.Ros2BagWriter(tmp_path / "flight.mcap") as bag:
        bag.add_pose("/vicon/cf1/cf1", t, true_position(t), true_quaternion(t), message_type="TransformStamped")
        bag.add_log_data("/cf1/acc", t_acc, np.column_stack([accelerometer_g(t_acc)] * 2))
    with pytest.raises(IngestError, match="6 values instead of 3"):
        mcap_reader.read(tmp_path / "flight.mcap")


def test_unsorted_duplicated_and_non_finite_messages_are_cleaned(tmp_path):
    t, t_acc = mocap_times(), imu_times()
    order = np.arange(len(t))
    order[[100, 101]] = order[[101, 100]]                       # two stamps arrive swapped
    order = np.insert(order, 200, 200)                          # one message recorded twice
    p, quat = true_position(t)[order], true_quaternion(t)[order]
    p[order == 300] = np.nan                                    # one unusable pose
    receive = np.arange(len(order)) / MOCAP_RATE               # log_time increases in file order
    with mcap_writer.JsonMcapWriter(tmp_path / "flight.mcap") as recording:
        recording.add_pose("/mocap", t[order], p, quat, log_t=receive)
        recording.add_acceleration("/acc", t_acc, accelerometer_g(t_acc))
    flight = mcap_reader.read(tmp_path / "flight.mcap")
    report = flight.meta["mcap"]["streams"]["pose"]
    assert report["non_finite"] == 1 and report["duplicate_time"] == 1 and report["out_of_order"] >= 1
    assert report["kept"] == len(t) - 1
    measured = np.abs(source_times(flight) - 3.0) > 1e-9          # t = 3.0 s is now interpolated
    np.testing.assert_allclose(flight.p[measured], true_position(source_times(flight))[measured], atol=1e-6)


# -- topic choice ------------------------------------------------------------------------------------------

def two_pose_topics(path):
    t, t_acc = mocap_times(), imu_times()
    with mcap_writer.Ros2BagWriter(path) as bag:
        bag.add_pose("/vicon/cf1/cf1", t, true_position(t), true_quaternion(t), message_type="TransformStamped")
        bag.add_pose("/cf1/pose", t, true_position(t) + 0.01, true_quaternion(t))   # the onboard estimate
        bag.add_imu("/cf1/imu", t_acc, accelerometer_g(t_acc))


def test_motion_capture_is_preferred_over_the_onboard_estimate(tmp_path):
    two_pose_topics(tmp_path / "flight.mcap")
    flight = mcap_reader.read(tmp_path / "flight.mcap")
    assert flight.meta["topics"]["pose"] == "/vicon/cf1/cf1"
    assert flight.meta["topics"]["pose_source"] == "motion capture" and flight.meta["warnings"] == []
    assert any("preferred over /cf1/pose (onboard estimate)" in note for note in flight.meta["mcap"]["warnings"])
    assert_matches_truth(flight, acc_interpolation_tolerance())


def test_two_motion_capture_topics_are_ambiguous_and_listed(tmp_path):
    t, t_acc = mocap_times(), imu_times()
    with mcap_writer.Ros2BagWriter(tmp_path / "flight.mcap") as bag:
        bag.add_pose("/vicon/cf1/cf1", t, true_position(t), true_quaternion(t), message_type="TransformStamped")
        bag.add_pose("/vicon/cf2/cf2", t, true_position(t) + 1.0, true_quaternion(t), message_type="TransformStamped")
        bag.add_pose("/cf1/pose", t, true_position(t) + 0.01, true_quaternion(t))
        bag.add_imu("/cf1/imu", t_acc, accelerometer_g(t_acc))
    with pytest.raises(IngestError, match="pose_topic=") as error:
        mcap_reader.read(tmp_path / "flight.mcap")
    message = str(error.value)
    assert "flight.mcap" in message and "--pose-topic" in message
    for topic in ("/vicon/cf1/cf1", "/vicon/cf2/cf2", "/cf1/pose"):
        assert topic in message
    assert f"/vicon/cf2/cf2 (geometry_msgs/msg/TransformStamped, cdr, {len(t)} messages, motion capture)" in message
    assert "/cf1/pose (geometry_msgs/msg/PoseStamped, cdr" in message and "onboard estimate" in message


def test_explicit_topic_choice(tmp_path):
    two_pose_topics(tmp_path / "flight.mcap")
    flight = mcap_reader.read(tmp_path / "flight.mcap", pose_topic="/vicon/cf1/cf1")
    assert flight.meta["mcap"]["pose_topic"] == "/vicon/cf1/cf1"
    assert_matches_truth(flight, acc_interpolation_tolerance())
    onboard = mcap_reader.read(tmp_path / "flight.mcap", pose_topic="/cf1/pose", accel_topic="/cf1/imu")
    np.testing.assert_allclose(onboard.p, flight.p + 0.01, atol=1e-9)
    with pytest.raises(IngestError, match="no topic '/nope'.*/cf1/imu"):
        mcap_reader.read(tmp_path / "flight.mcap", pose_topic="/nope")
    with pytest.raises(IngestError, match="cannot be read as motion-capture pose"):
        mcap_reader.read(tmp_path / "flight.mcap", pose_topic="/cf1/imu")


def test_topics_helper_lists_every_channel(tmp_path):
    two_pose_topics(tmp_path / "flight.mcap")
    n, n_acc = len(mocap_times()), len(imu_times())
    assert mcap_container.topics(tmp_path / "flight.mcap") == [
        ("/cf1/imu", "sensor_msgs/msg/Imu", "cdr", n_acc),
        ("/cf1/pose", "geometry_msgs/msg/PoseStamped", "cdr", n),
        ("/vicon/cf1/cf1", "geometry_msgs/msg/TransformStamped", "cdr", n),
    ]


def test_no_usable_topics_names_the_file_and_lists_topics(tmp_path):
    t = mocap_times()
    with mcap_writer.Ros2BagWriter(tmp_path / "battery.mcap") as bag:
        bag.add_log_data("/cf1/battery", t, np.full((len(t), 1), 3.9))
    with pytest.raises(IngestError, match="no usable topics") as error:
        mcap_reader.read(tmp_path / "battery.mcap")
    assert "battery.mcap" in str(error.value)
    assert "/cf1/battery (crazyflie_interfaces/msg/LogDataGeneric, cdr" in str(error.value)


def test_missing_acceleration_is_named(tmp_path):
    t = mocap_times()
    with mcap_writer.Ros2BagWriter(tmp_path / "pose_only.mcap") as bag:
        bag.add_pose("/vicon/cf1/cf1", t, true_position(t), true_quaternion(t), message_type="TransformStamped")
    with pytest.raises(IngestError, match="pose_only.mcap: no usable acceleration topic.*/vicon/cf1/cf1"):
        mcap_reader.read(tmp_path / "pose_only.mcap")


# -- damaged and foreign files -----------------------------------------------------------------------------

def record_spans(data: bytes):
    """(opcode, start, end) of each top-level record after the magic."""
    spans, offset = [], len(mcap_container.MAGIC)
    while offset + 9 <= len(data):
        length = int.from_bytes(data[offset + 1:offset + 9], "little")
        spans.append((data[offset], offset, offset + 9 + length))
        offset += 9 + length
    return spans


CHUNK_OPCODE = 0x06


def test_cut_off_file_keeps_complete_chunks(tmp_path):
    write_flight(tmp_path / "full.mcap", "PoseStamped+Imu", chunk_size=16 << 10)
    data = (tmp_path / "full.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(data[:int(len(data) * 0.6)])
    assert mcap_reader.sniff(tmp_path / "cut.mcap")
    flight = mcap_reader.read(tmp_path / "cut.mcap")
    assert 2.0 < flight.duration_s < 0.7 * DURATION
    assert any("cut off" in note for note in flight.meta["mcap"]["warnings"])
    assert_matches_truth(flight, acc_interpolation_tolerance())


def test_damaged_chunk_is_skipped(tmp_path):
    write_flight(tmp_path / "flight.mcap", "PoseStamped+Imu", chunk_size=16 << 10)
    data = bytearray((tmp_path / "flight.mcap").read_bytes())
    chunks = [(start, end) for opcode, start, end in record_spans(bytes(data)) if opcode == CHUNK_OPCODE]
    assert len(chunks) > 4
    start, end = chunks[len(chunks) // 2]
    data[end - 50] ^= 0xFF                                      # inside the compressed payload
    (tmp_path / "flight.mcap").write_bytes(bytes(data))
    flight = mcap_reader.read(tmp_path / "flight.mcap")
    assert any("damaged chunk" in note for note in flight.meta["mcap"]["warnings"])
    assert flight.meta["gaps"]["acc_samples_in_gaps"] > 0       # the lost chunk is a gap, not invented data
    kept = flight.meta["mcap"]["streams"]["accel"]["kept"]
    assert 0.5 * len(imu_times()) < kept < len(imu_times())


def small_valid_mcap(tmp_path) -> bytes:
    write_flight(tmp_path / "small.mcap", "PoseStamped+Imu")
    return (tmp_path / "small.mcap").read_bytes()


@pytest.mark.parametrize("make, problem", [
    (lambda valid: b"", "empty"),
    (lambda valid: np.random.default_rng(3).bytes(5000), "not an MCAP file"),
    (lambda valid: b"t,x,y,z\n0,1,2,3\n", "not an MCAP file"),
    (lambda valid: valid[:5], "cut off inside its magic"),
    (lambda valid: valid[:8], "no usable topics"),
    (lambda valid: valid[:200], "no usable topics"),
    (lambda valid: mcap_container.MAGIC + np.random.default_rng(4).bytes(5000), "no usable topics"),
])
def test_bad_input_is_an_ingest_error_naming_the_file(tmp_path, make, problem):
    path = tmp_path / "flight_0042.mcap"
    path.write_bytes(make(small_valid_mcap(tmp_path)))
    with pytest.raises(IngestError, match=problem) as error:
        mcap_reader.read(path)
    assert "flight_0042.mcap" in str(error.value)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(IngestError, match="no such file"):
        mcap_reader.read(tmp_path / "absent.mcap")
    bag = tmp_path / "rosbag2_2024"
    bag.mkdir()
    (bag / "rosbag2_2024_0.mcap").write_bytes(b"")
    with pytest.raises(IngestError, match="rosbag2_2024_0.mcap"):
        mcap_reader.read(bag)


def test_sniff_looks_at_content_not_extension(tmp_path):
    valid = small_valid_mcap(tmp_path)
    (tmp_path / "flight.csv").write_bytes(valid)
    (tmp_path / "header_only").write_bytes(valid[:8])
    (tmp_path / "flight.mcap").write_text("t,x\n0,1\n")
    assert mcap_reader.sniff(tmp_path / "flight.csv") is True
    assert mcap_reader.sniff(tmp_path / "header_only") is True
    assert mcap_reader.sniff(tmp_path / "flight.mcap") is False
    assert mcap_reader.sniff(tmp_path / "absent") is False


# -- fuzzing -----------------------------------------------------------------------------------------------

def _fuzz_base(variant, **options) -> bytes:
    import tempfile
    t, t_acc = mocap_times(1.5, 50.0), imu_times(1.5, 100.0)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "base.mcap"
        p, quat, acc = true_position(t), true_quaternion(t), accelerometer_g(t_acc)
        if variant == "json":   # no CRCs, no compression: flipped bytes reach the decoders
            with mcap_writer.JsonMcapWriter(path, chunk_size=2048, compression="none", enable_crcs=False) as recording:
                recording.add_pose("/mocap", t, p, quat)
                recording.add_acceleration("/acc", t_acc, acc)
        else:
            mcap_writer.write_ros2(path, t, p, quat, acc, t_acc=t_acc, pose_type="TransformStamped",
                                accel_type="LogDataGeneric", chunk_size=2048, **options)
        return path.read_bytes()


FUZZ_BASES = [_fuzz_base("ros2"), _fuzz_base("ros2", compression="lz4"), _fuzz_base("json")]


@st.composite
def damaged_files(draw):
    base = bytearray(draw(st.sampled_from(FUZZ_BASES)))
    for index, value in draw(st.lists(st.tuples(st.integers(0, len(base) - 1), st.integers(0, 255)), max_size=6)):
        base[index] = value
    cut = draw(st.one_of(st.just(len(base)), st.integers(0, len(base))))
    return bytes(base[:cut])


@pytest.fixture(scope="module")
def fuzz_path(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz") / "fuzzed.mcap"


@settings(max_examples=100, deadline=None, database=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=damaged_files())
def test_damaged_files_raise_only_ingest_errors(fuzz_path, data):
    fuzz_path.write_bytes(data)
    assert isinstance(mcap_reader.sniff(fuzz_path), bool)
    for attempt in (mcap_container.topics, mcap_reader.read):
        try:
            attempt(fuzz_path)
        except IngestError as error:
            assert "fuzzed.mcap" in str(error)


def test_ingest_package_detects_reads_and_saves_mcap(tmp_path):
    import learnest.ingest as ingest
    from learnest.ingest.flight import Flight

    write_flight(tmp_path / "flight.bag", "TransformStamped+LogDataGeneric")
    assert ingest.detect(tmp_path / "flight.bag") == "mcap"
    [flight] = ingest.read_flights([tmp_path / "flight.bag"])
    assert flight.meta["adapter"] == "mcap-ros2" and "quality" in flight.meta
    restored = Flight.from_bytes(flight.to_bytes())              # meta is plain JSON
    assert restored.meta["mcap"] == flight.meta["mcap"]
    np.testing.assert_array_equal(restored.p, flight.p)


def _bomb(path: Path, chunks: int, uncompressed: int, compression: str = "zstd") -> Path:
    """A valid MCAP header followed by chunks of zeros that each expand to `uncompressed` bytes."""
    import zlib

    import lz4.frame
    import zstandard
    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk, Header

    zeros = bytes(uncompressed)
    data = zstandard.ZstdCompressor().compress(zeros) if compression == "zstd" else lz4.frame.compress(zeros)
    builder = RecordBuilder()
    Header(profile="ros2", library="bomb").write(builder)
    for _ in range(chunks):
        Chunk(compression=compression, data=data, message_start_time=0, message_end_time=0,
              uncompressed_crc=zlib.crc32(zeros), uncompressed_size=uncompressed).write(builder)
    path.write_bytes(mcap_container.MAGIC + builder.end())
    return path


@pytest.mark.parametrize("compression", ["zstd", "lz4"])
def test_a_decompression_bomb_is_refused_before_it_is_decompressed(tmp_path, compression):
    """64 MiB of zeros in a few kB: past the 100x expansion cap, refused from the chunk headers alone."""
    import tracemalloc

    path = _bomb(tmp_path / "bomb.mcap", chunks=4, uncompressed=16 << 20, compression=compression)
    assert path.stat().st_size < 1 << 20  # 64 MiB of zeros in < 1 MiB (zstd: kB)
    tracemalloc.start()
    with pytest.raises(IngestError, match=r"bomb.mcap: chunks expand to more than \d+ bytes \(the cap is 100x"):
        mcap_reader.read(path)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    # memory is bounded by the budget (100 x the file's size), not by the 64 MiB the chunks claim
    budget = mcap_container.MAX_EXPANSION * path.stat().st_size
    assert peak < 2 * budget + (4 << 20), (peak, budget)


def test_chunks_within_the_expansion_cap_are_read(tmp_path):
    """A well-compressing but honest recording (the simulator's, zstd) stays well inside the cap."""
    path = tmp_path / "flight.mcap"
    write_flight(path, "PoseStamped+Imu")
    content = mcap_container.scan(path)
    assert content.warnings == [] and content.channels


def test_chunk_records_must_end_where_their_length_field_says():
    """A message shorter than its 22-byte header would swallow the rest of its chunk, a channel longer than its
    length field would desynchronise every record after it: both make the chunk damaged, by name.  A record
    longer than the fields read (a later spec version's) is read and its extra bytes skipped."""
    import struct

    from mcap.data_stream import RecordBuilder
    from mcap.records import Channel, Chunk

    def chunk(data: bytes) -> Chunk:
        return Chunk(compression="", data=data, message_start_time=0, message_end_time=0, uncompressed_crc=0,
                     uncompressed_size=len(data))

    short_message = b"\x05" + struct.pack("<Q", 5) + bytes(5)
    with pytest.raises(ValueError, match="claims 5 bytes, less than its header"):
        mcap_container._records_of(chunk(short_message))
    builder = RecordBuilder()
    Channel(id=1, schema_id=0, topic="/cf1/imu", message_encoding="cdr", metadata={}).write(builder)
    record = builder.end()
    (size,) = struct.unpack_from("<Q", record, 1)
    truncated = record[:1] + struct.pack("<Q", size - 4) + record[9:]
    with pytest.raises(ValueError, match=f"ends at byte {9 + size}, its length field says {5 + size}"):
        mcap_container._records_of(chunk(truncated))
    extended = record[:1] + struct.pack("<Q", size + 4) + record[9:] + b"new!"
    [channel, again] = mcap_container._records_of(chunk(extended + record))
    assert channel.topic == again.topic == "/cf1/imu"
