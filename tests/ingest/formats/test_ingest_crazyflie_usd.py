"""uSD-card binary logs: real files, write -> decode round trips, damaged files, fuzzing."""
import warnings
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from learnest.ingest.flight import IngestError, sha256_file
from learnest.ingest.formats.crazyflie_usd import decoder as usd_decoder
from learnest.ingest.formats.crazyflie_usd import layout as usd_layout
from learnest.ingest.formats.crazyflie_usd import reader as usd_reader
from learnest.ingest.formats.crazyflie_usd import writer as usd_writer
from learnest.ingest.formats.crazyflie_variables import ACC
from learnest.ingest.frames import GRAVITY, quat_to_matrix

USD_DATA = Path(__file__).parents[3].parent / "shared" / "data" / "crazyswarm2-tools"
REAL_LOGS = ["log182", "log183", "log184"]
INTEGER_TYPES = {"B": np.uint8, "b": np.int8, "H": np.uint16, "h": np.int16, "I": np.uint32, "i": np.int32}


def real_log(name: str) -> Path:
    path = USD_DATA / name
    if not path.exists():
        pytest.skip(f"real uSD logs not available ({USD_DATA} is absent in this checkout)")
    return path


# -- simulated flights ---------------------------------------------------------------------------------------

YAW = 0.5   # rad, constant, so that the body frame differs from the world frame


def yaw_quat(yaw, n):
    return np.tile([0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2)], (n, 1))


def true_position(t):
    return np.column_stack([0.5 * np.sin(1.5 * t), 0.3 * np.sin(3.0 * t), 1.0 + 0.05 * np.sin(t)])


def true_acceleration(t):
    return np.column_stack([-0.5 * 2.25 * np.sin(1.5 * t), -0.3 * 9.0 * np.sin(3.0 * t), -0.05 * np.sin(t)])


def body_specific_force_g(t, quat):
    """What an ideal accelerometer reads (g, body frame) on the trajectory above."""
    world = true_acceleration(t) + [0.0, 0.0, GRAVITY]
    return np.einsum("tji,tj->ti", quat_to_matrix(quat), world) / GRAVITY


def simulated_events(duration=4.0, rate=250.0, mocap_rate=100.0, pose_stream="fixed", with_quat=True):
    """A fixed-frequency stream (acc, compressed estimates, setpoints, gyro) plus locSrv either
    sample-and-hold inside it or as its own event stream."""
    t = np.arange(0.0, duration, 1.0 / rate)
    t_mocap = np.arange(0.003, duration, 1.0 / mocap_rate)
    p, v = true_position(t), np.gradient(true_position(t), t, axis=0)
    fixed = {
        "acc.x": ("f", None), "acc.y": ("f", None), "acc.z": ("f", None),
        "gyro.x": ("f", np.full(len(t), 10.0)), "gyro.y": ("f", np.zeros(len(t))), "gyro.z": ("f", np.full(len(t), -90.0)),
        "stateEstimateZ.x": ("h", 1000 * p[:, 0]), "stateEstimateZ.y": ("h", 1000 * p[:, 1]),
        "stateEstimateZ.z": ("h", 1000 * p[:, 2]),
        "stateEstimateZ.vx": ("h", 1000 * v[:, 0]), "stateEstimateZ.vy": ("h", 1000 * v[:, 1]),
        "stateEstimateZ.vz": ("h", 1000 * v[:, 2]),
        "ctrltargetZ.x": ("h", 1000 * p[:, 0]), "ctrltargetZ.y": ("h", 1000 * p[:, 1]),
        "ctrltargetZ.z": ("h", np.full(len(t), 1000.0)),
        "ctrlLee.rpyx": ("f", np.zeros(len(t))), "ctrlLee.rpyy": ("f", np.zeros(len(t))),
        "ctrlLee.rpyz": ("f", np.full(len(t), YAW)),
    }
    acc = body_specific_force_g(t, yaw_quat(YAW, len(t)))
    for j, axis in enumerate("xyz"):
        fixed[f"acc.{axis}"] = ("f", acc[:, j])
    pose = np.column_stack([true_position(t_mocap), yaw_quat(YAW, len(t_mocap)) * with_quat])
    if pose_stream == "fixed":   # firmware behaviour: zeros until the first frame, then hold the last one
        held = np.searchsorted(t_mocap, t, side="right") - 1
        pose_at_fixed = np.where((held >= 0)[:, None], pose[np.maximum(held, 0)], 0.0)
        fixed.update({name: ("f", pose_at_fixed[:, j]) for j, name in enumerate(usd_reader.POSE)})
        return {"fixedFrequency": {"t": t, "vars": fixed}}
    mocap = {"id": 3, "t": t_mocap, "vars": {name: ("f", pose[:, j]) for j, name in enumerate(usd_reader.POSE)}}
    return {"fixedFrequency": {"t": t, "vars": fixed}, "locSrvEvent": mocap}


def all_types_events(n=300, seed=0):
    """One value column per struct code, random over each type's full range."""
    rng = np.random.default_rng(seed)
    columns = {f"test.{code}": (code, rng.integers(np.iinfo(kind).min, np.iinfo(kind).max, n, endpoint=True))
               for code, kind in INTEGER_TYPES.items()}
    columns["test.f"] = ("f", rng.normal(0, 100, n).astype(np.float32))
    columns["test.e"] = ("e", rng.normal(0, 10, n).astype(np.float16))
    return {"fixedFrequency": {"t": 2.0 + np.arange(n) * 0.004, "vars": columns}}


def header_length(data: bytes) -> int:
    return usd_decoder.parse_header(data, "test")[2]


def record_size(data: bytes, event="fixedFrequency") -> int:
    version, event_types, _ = usd_decoder.parse_header(data, "test")
    return next(e for e in event_types if e.name == event).record_dtype(version).itemsize


# -- real files ----------------------------------------------------------------------------------------------

@pytest.mark.parametrize("name", REAL_LOGS)
def test_real_log_decodes_with_expected_layout(name):
    log = usd_decoder.decode(real_log(name))
    assert log.version == 2
    assert log.crc_ok and log.warnings == []
    assert [event.name for event in log.event_types] == ["fixedFrequency"]
    assert log.event_types[0].id == usd_layout.FIXED_FREQUENCY_ID
    stream = log.events["fixedFrequency"]
    assert len(stream) == 1 + 44
    assert set(ACC + usd_reader.POSE) <= set(stream)
    assert 3700 < len(stream["t"]) < 4000
    assert stream["stateEstimateZ.z"].dtype == np.int16


@pytest.mark.parametrize("name", REAL_LOGS)
def test_real_log_timing_is_250_hz_for_about_16_s(name):
    t = usd_decoder.decode(real_log(name)).events["fixedFrequency"]["t"]
    assert np.all(np.diff(t) > 0)
    assert 245 < 1.0 / np.median(np.diff(t)) < 255
    assert 15.0 < t[-1] - t[0] < 18.0


@pytest.mark.parametrize("name", REAL_LOGS)
def test_real_log_accelerometer_reads_one_g_at_the_start(name):
    # The recordings start in hover, not on the ground: still ~1 g of specific force, mostly on body z.
    stream = usd_decoder.decode(real_log(name)).events["fixedFrequency"]
    acc = np.column_stack([stream[axis] for axis in ACC])[:125]
    assert np.linalg.norm(acc, axis=1).mean() == pytest.approx(1.0, abs=0.03)
    assert acc[:, 2].mean() > 0.95


@pytest.mark.parametrize("name", REAL_LOGS)
def test_real_log_becomes_a_plausible_flight(name):
    path = real_log(name)
    flight = usd_reader.read(path)
    assert 13.0 < flight.duration_s < 17.0
    assert flight.rate_hz == pytest.approx(100.0)
    assert np.all(np.abs(flight.p[:, :2]) < 1.2) and np.all((flight.p[:, 2] > 0.9) & (flight.p[:, 2] < 1.1))
    assert np.all(np.isfinite(flight.a_meas))
    assert np.abs(flight.a_meas.mean(axis=0)).max() < 0.3            # gravity removed, bounded trajectory
    assert np.abs(flight.channels["p_onboard"] - flight.p).max() < 0.05   # onboard estimate tracks mocap
    assert flight.meta["adapter"] == "usd"
    info = path.with_name(f"info{name[3:]}.yaml")   # crazyswarm2's sidecar: mass and controller gains
    assert flight.meta["sources"] == [{"path": str(path), "sha256": sha256_file(path)},
                                      {"path": str(info), "sha256": sha256_file(info)}]
    assert flight.meta["mass_kg"] == pytest.approx(0.032) and flight.meta["controller"] == "lee"
    assert flight.meta["vehicle_info"]["Kpos_Px"] == pytest.approx(17.0)
    assert flight.meta["clock_offset_s"] is None
    assert 245 < flight.meta["original_rates"]["acc"] < 255
    assert 60 < flight.meta["original_rates"]["mocap"] < 110
    assert flight.meta["usd"]["version"] == 2 and flight.meta["usd"]["crc_ok"] is True
    assert flight.meta["attitude_source"].startswith("onboard")      # the real locSrv quaternions are zero
    assert any("pause" in note for note in flight.meta["usd"]["warnings"])


def test_real_figure_eight_acceleration_matches_mocap():
    """The whole chain (decode, attitude fallback, rotation, gravity) against mocap's second derivative."""
    flight = usd_reader.read(real_log("log182"))
    smooth = np.ones(9) / 9
    p = np.column_stack([np.convolve(flight.p[:, j], smooth, "same") for j in range(3)])
    a = np.column_stack([np.convolve(flight.a_meas[:, j], smooth, "same") for j in range(3)])
    a_mocap = np.gradient(np.gradient(p, flight.t, axis=0), flight.t, axis=0)
    for axis in (0, 1):   # the horizontal axes carry the figure-eight
        assert np.corrcoef(a_mocap[20:-20, axis], a[20:-20, axis])[0, 1] > 0.8


# -- write -> decode round trips -----------------------------------------------------------------------------

@pytest.mark.parametrize("version", [1, 2])
def test_round_trip_is_exact_for_every_type(tmp_path, version):
    events = all_types_events()
    usd_writer.write(tmp_path / "log", events, version=version)
    log = usd_decoder.decode(tmp_path / "log")
    assert log.version == version and log.crc_ok and log.warnings == []
    decoded = log.events["fixedFrequency"]
    tick = {1: 1e-3, 2: 1e-6}[version]
    np.testing.assert_array_equal(np.rint(decoded["t"] / tick), np.rint(events["fixedFrequency"]["t"] / tick))
    for name, (code, values) in events["fixedFrequency"]["vars"].items():
        assert decoded[name].dtype == np.dtype(usd_layout.VALUE_TYPES[code]).newbyteorder("=")
        np.testing.assert_array_equal(decoded[name], values)


@pytest.mark.parametrize("version", [1, 2])
def test_interleaved_event_streams_round_trip(tmp_path, version):
    events = simulated_events(pose_stream="event")
    usd_writer.write(tmp_path / "log", events, version=version)
    log = usd_decoder.decode(tmp_path / "log")
    assert [(e.id, e.name) for e in log.event_types] == [(0xFFFF, "fixedFrequency"), (3, "locSrvEvent")]
    for event, spec in events.items():
        assert len(log.events[event]["t"]) == len(spec["t"])
        for name, (code, values) in spec["vars"].items():
            expected = np.rint(values) if code in INTEGER_TYPES else np.asarray(values, np.float32)
            np.testing.assert_array_equal(log.events[event][name], expected)


def test_writer_refuses_values_that_do_not_fit():
    with pytest.raises(ValueError, match="do not fit"):
        usd_writer.encode({"fixedFrequency": {"t": [0.0], "vars": {"a.b": ("h", [40000])}}})
    with pytest.raises(ValueError, match="values for"):
        usd_writer.encode({"fixedFrequency": {"t": [0.0, 1.0], "vars": {"a.b": ("f", [1.0])}}})


# -- adapter -------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("pose_stream", ["fixed", "event"])
@pytest.mark.parametrize("version", [1, 2])
def test_read_simulated_flight(tmp_path, pose_stream, version):
    usd_writer.write(tmp_path / "log", simulated_events(pose_stream=pose_stream), version=version)
    flight = usd_reader.read(tmp_path / "log")
    t_source = flight.t + flight.meta["t0_source_s"]
    # sample-and-hold delays each frame by up to one fixed-stream period (4 ms): a few mm at ~1 m/s
    np.testing.assert_allclose(flight.p, true_position(t_source), atol=0.006)
    np.testing.assert_allclose(flight.a_meas, true_acceleration(t_source), atol=0.05)
    assert flight.meta["attitude_source"] == "mocap (locSrv quaternion)"
    assert flight.meta["original_rates"]["acc"] == pytest.approx(250.0, rel=0.01)
    assert flight.meta["original_rates"]["mocap"] == pytest.approx(100.0, rel=0.01)   # distinct frames only
    assert flight.meta["usd"] == {"version": version, "crc_ok": True, "warnings": [],
                                  "records": flight.meta["usd"]["records"]}


def test_read_converts_compressed_and_degree_channels(tmp_path):
    usd_writer.write(tmp_path / "log", simulated_events())
    flight = usd_reader.read(tmp_path / "log")
    t_source = flight.t + flight.meta["t0_source_s"]
    np.testing.assert_allclose(flight.channels["p_onboard"], true_position(t_source), atol=0.002)
    velocity = np.gradient(true_position(t_source), t_source, axis=0)
    np.testing.assert_allclose(flight.channels["v_onboard"][5:-5], velocity[5:-5], atol=0.01)
    np.testing.assert_allclose(flight.channels["setpoint"][:, 2], 1.0)
    np.testing.assert_allclose(flight.channels["gyro"][0], np.radians([10.0, 0.0, -90.0]), rtol=1e-6)


def test_position_only_mocap_uses_onboard_attitude(tmp_path):
    usd_writer.write(tmp_path / "log", simulated_events(with_quat=False))
    flight = usd_reader.read(tmp_path / "log")
    assert flight.meta["attitude_source"].startswith("onboard")
    np.testing.assert_allclose(flight.quat, yaw_quat(YAW, len(flight.t)), atol=1e-6)
    np.testing.assert_allclose(flight.a_meas, true_acceleration(flight.t + flight.meta["t0_source_s"]), atol=0.05)


def test_position_only_mocap_without_onboard_attitude_is_refused(tmp_path):
    events = simulated_events(with_quat=False)
    for axis in "xyz":
        del events["fixedFrequency"]["vars"][f"ctrlLee.rpy{axis}"]
    usd_writer.write(tmp_path / "log", events)
    with pytest.raises(IngestError, match="quaternion"):
        usd_reader.read(tmp_path / "log")


def test_fragment_before_a_long_pause_is_skipped(tmp_path):
    events = simulated_events(duration=5.0)
    fixed = events["fixedFrequency"]
    keep = (fixed["t"] < 0.01) | (fixed["t"] > 1.5)          # like the real logs: 3 records, then a pause
    fixed["t"] = fixed["t"][keep]
    fixed["vars"] = {name: (code, values[keep]) for name, (code, values) in fixed["vars"].items()}
    usd_writer.write(tmp_path / "log", events)
    flight = usd_reader.read(tmp_path / "log")
    assert flight.meta["t0_source_s"] > 1.5
    assert flight.meta["gaps"]["acc_samples_in_gaps"] == 0
    assert any("skipped the first 3" in note for note in flight.meta["usd"]["warnings"])


@pytest.mark.parametrize("drop, missing", [(ACC, "acc.x"), (usd_reader.POSE, "locSrv.qw")])
def test_missing_variables_are_named(tmp_path, drop, missing):
    events = simulated_events()
    for name in drop:
        del events["fixedFrequency"]["vars"][name]
    usd_writer.write(tmp_path / "log", events)
    with pytest.raises(IngestError, match=missing) as error:
        usd_reader.read(tmp_path / "log")
    assert "log" in str(error.value)


def test_rpy_to_quat_matches_the_z_y_x_convention():
    roll, pitch, yaw = 0.3, -0.2, 2.5
    c, s = np.cos, np.sin
    rx = np.array([[1, 0, 0], [0, c(roll), -s(roll)], [0, s(roll), c(roll)]])
    ry = np.array([[c(pitch), 0, s(pitch)], [0, 1, 0], [-s(pitch), 0, c(pitch)]])
    rz = np.array([[c(yaw), -s(yaw), 0], [s(yaw), c(yaw), 0], [0, 0, 1]])
    np.testing.assert_allclose(quat_to_matrix(usd_reader.rpy_to_quat([[roll, pitch, yaw]]))[0], rz @ ry @ rx,
                               atol=1e-12)


def test_decoding_a_minute_at_500_hz_keeps_every_record(tmp_path):
    """A minute at 500 Hz with a 100-Hz mocap stream decodes whole (how fast: benchmarks/bench_ingest.py)."""
    t, t_mocap = np.arange(0, 60, 1 / 500), np.arange(0.001, 60, 1 / 100)
    fixed = {f"group.v{i}": ("f", np.sin(t + i)) for i in range(40)}
    mocap = {name: ("f", np.full(len(t_mocap), 0.5)) for name in usd_reader.POSE}
    usd_writer.write(tmp_path / "log", {"fixedFrequency": {"t": t, "vars": fixed},
                                        "mocap": {"t": t_mocap, "vars": mocap}})
    log = usd_decoder.decode(tmp_path / "log")
    assert len(log.events["fixedFrequency"]["t"]) == 30000 and len(log.events["mocap"]["t"]) == 6000


# -- damaged files -------------------------------------------------------------------------------------------

def test_cut_mid_record_keeps_complete_records(tmp_path):
    data = usd_writer.encode(all_types_events(n=50))
    (tmp_path / "cut").write_bytes(data[:-4 - record_size(data) // 2])
    with pytest.warns(usd_decoder.UsdLogWarning, match="cut"):
        log = usd_decoder.decode(tmp_path / "cut")
    assert not log.crc_ok
    assert len(log.events["fixedFrequency"]["t"]) == 49
    assert any("complete record" in note for note in log.warnings)
    np.testing.assert_array_equal(log.events["fixedFrequency"]["test.f"],
                                  all_types_events(n=50)["fixedFrequency"]["vars"]["test.f"][1][:49])


def test_cut_at_a_record_boundary_keeps_every_record(tmp_path):
    data = usd_writer.encode(all_types_events(n=50))
    (tmp_path / "cut").write_bytes(data[:-4])        # lost only the trailer
    with pytest.warns(usd_decoder.UsdLogWarning, match="CRC"):
        log = usd_decoder.decode(tmp_path / "cut")
    assert not log.crc_ok and len(log.events["fixedFrequency"]["t"]) == 50


def test_crc_mismatch_keeps_records_and_warns(tmp_path):
    usd_writer.write(tmp_path / "log", simulated_events(pose_stream="event"), corrupt_crc=True)
    with pytest.warns(usd_decoder.UsdLogWarning, match="CRC"):
        log = usd_decoder.decode(tmp_path / "log")
    assert not log.crc_ok
    assert len(log.events["fixedFrequency"]["t"]) == 1000 and len(log.events["locSrvEvent"]["t"]) == 400
    with pytest.warns(usd_decoder.UsdLogWarning):
        flight = usd_reader.read(tmp_path / "log")
    assert flight.meta["usd"]["crc_ok"] is False and flight.meta["usd"]["warnings"]


def test_unknown_event_id_stops_decoding_and_names_the_offset(tmp_path):
    data = bytearray(usd_writer.encode(all_types_events(n=50)))
    offset = header_length(bytes(data)) + 20 * record_size(bytes(data))
    data[offset:offset + 2] = (0x1234).to_bytes(2, "little")
    data[-4:] = zlib.crc32(bytes(data[:-4])).to_bytes(4, "little")   # a consistent file, just an odd id
    (tmp_path / "log").write_bytes(bytes(data))
    with pytest.warns(usd_decoder.UsdLogWarning, match=f"0x1234 at byte offset {offset}"):
        log = usd_decoder.decode(tmp_path / "log")
    assert log.crc_ok and len(log.events["fixedFrequency"]["t"]) == 20


VALID = usd_writer.encode(simulated_events(duration=1.0, pose_stream="event"))


@pytest.mark.parametrize("content, problem", [
    (b"", "empty"),
    (bytes([0x00]) + np.random.default_rng(1).bytes(4000), "first byte"),
    (b"time,x,y,z\n0,1,2,3\n", "first byte is 0x74"),
    (bytes([0xBC]) + (3).to_bytes(2, "little") + VALID[3:], "version 3"),
    (bytes([0xBC]) + (0).to_bytes(2, "little") + VALID[3:], "version 0"),
    (bytes([0xBC, 0x02, 0x00, 0x00, 0x00]), "no event types"),
    (VALID[:1], "cut off"),
    (VALID[:4], "cut off"),
    (VALID[:12], "cut off"),
    (VALID[:header_length(VALID) - 1], "cut off"),
])
def test_bad_input_is_an_ingest_error_naming_the_file(tmp_path, content, problem):
    path = tmp_path / "flight_0042.usd"
    path.write_bytes(content)
    with pytest.raises(IngestError, match=problem) as error:
        usd_decoder.decode(path)
    assert "flight_0042.usd" in str(error.value)
    with pytest.raises(IngestError, match="flight_0042.usd"):
        usd_reader.read(path)
    assert usd_reader.sniff(path) is False


def test_missing_file_is_an_ingest_error(tmp_path):
    with pytest.raises(IngestError, match="nothing_here"):
        usd_decoder.decode(tmp_path / "nothing_here")


def test_sniff_looks_at_content_not_extension(tmp_path):
    (tmp_path / "flight.csv").write_bytes(VALID)
    (tmp_path / "log01").write_bytes(VALID[:header_length(VALID)])
    (tmp_path / "log02.bin").write_text("t,x\n0,1\n")
    assert usd_reader.sniff(tmp_path / "flight.csv") is True
    assert usd_reader.sniff(tmp_path / "log01") is True       # header alone: a log cut off before its first record
    assert usd_reader.sniff(tmp_path / "log02.bin") is False
    assert usd_reader.sniff(tmp_path / "absent") is False


# -- fuzzing -------------------------------------------------------------------------------------------------

FUZZ_BASES = [usd_writer.encode(simulated_events(duration=1.0, rate=100.0, mocap_rate=50.0, pose_stream="event"),
                         version=version) for version in (1, 2)]


@st.composite
def damaged_logs(draw):
    base = bytearray(draw(st.sampled_from(FUZZ_BASES)))
    header_end = header_length(bytes(base))
    position = st.one_of(st.integers(0, header_end + 40), st.integers(0, len(base) - 1))  # headers are dense
    for index, value in draw(st.lists(st.tuples(position, st.integers(0, 255)), max_size=8)):
        base[index] = value
    cut = draw(st.one_of(st.just(len(base)), st.integers(0, len(base))))
    return bytes(base[:cut])


@pytest.fixture(scope="module")
def fuzz_path(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz") / "fuzzed.usd"


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=damaged_logs())
def test_damaged_logs_raise_only_ingest_errors(fuzz_path, data):
    fuzz_path.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")      # damaged files warn by design; only exceptions matter here
        assert isinstance(usd_reader.sniff(fuzz_path), bool)
        for attempt in (usd_decoder.decode, usd_reader.read):
            try:
                attempt(fuzz_path)
            except IngestError as error:
                assert "fuzzed.usd" in str(error)
