"""State estimates leave as data: the per-step estimates an evaluation keeps equal an independent run of the
estimator, and the CSV, Parquet and MCAP writers give them back (pandas, pyarrow, the `mcap` reader) with units
and Foxglove schemas."""
import io
import json

import numpy as np
import pytest
from utils.service import flight_csv

import learnest as le
from learnest.estimators.estimates import STATE_COLUMNS, FlightEstimates, estimates_table
from learnest.estimators.export import format_of, write_estimates

T = 50


def synthetic(name: str = "hover", log_start_ns: int = 1_700_000_000_123_456_789) -> FlightEstimates:
    """Known arrays: reference = a smooth path, method "a" = reference + 0.1, method "b" = reference - 0.2."""
    rng = np.random.default_rng(0)
    t = np.arange(T) * 0.01
    reference = np.column_stack([np.sin(t + k) for k in range(9)])
    measurement = reference[:, [0, 1, 2, 6, 7, 8]] + rng.normal(0, 0.01, (T, 6))
    quat = np.tile([0.0, 0.0, np.sin(0.1), np.cos(0.1)], (T, 1))
    return FlightEstimates(name, t, reference, measurement, quat, {"a": reference + 0.1, "b": reference - 0.2},
                           log_start_ns, flight_id=7, sha256="ab" * 32)


def test_tidy_table_has_units_errors_and_one_row_per_method_and_sample():
    flight = synthetic()
    frame = estimates_table([flight])
    assert len(frame) == 2 * T and list(frame["method"].unique()) == ["a", "b"]
    assert list(frame.columns[:5]) == ["t_s", "t_log_s", "flight_id", "flight", "method"]
    assert {"p_x_m", "v_y_m_s", "a_z_m_s2", "ref_v_x_m_s", "err_a_x_m_s2", "meas_a_z_m_s2"} <= set(frame.columns)
    assert "meas_v_x_m_s" not in frame.columns       # y = [p, a]: no measured velocity
    units = frame.attrs["units"]
    assert (units["t_s"], units["p_x_m"], units["v_x_m_s"], units["err_a_z_m_s2"]) == ("s", "m", "m/s", "m/s^2")
    b = frame[frame["method"] == "b"]
    np.testing.assert_array_equal(b[list(STATE_COLUMNS)].to_numpy(), flight.estimates["b"])
    np.testing.assert_allclose(b[[f"err_{c}" for c in STATE_COLUMNS]].to_numpy(), -0.2, atol=1e-12)
    np.testing.assert_allclose(b["t_log_s"].to_numpy(), 1_700_000_000.123456789 + flight.t, rtol=0, atol=1e-6)


def test_csv_and_parquet_read_back_exactly_with_units():
    import pandas as pd
    import pyarrow.parquet as pq

    flight = synthetic()
    csv = io.BytesIO()
    write_estimates([flight], csv, "csv")
    back = pd.read_csv(io.BytesIO(csv.getvalue()))
    np.testing.assert_array_equal(back.loc[back["method"] == "a", list(STATE_COLUMNS)].to_numpy(),
                                  flight.estimates["a"])
    assert set(back["flight_id"]) == {7} and set(back["flight"]) == {"hover"}

    parquet = io.BytesIO()
    write_estimates([flight], parquet, "parquet")
    table = pq.read_table(io.BytesIO(parquet.getvalue()))
    assert table.schema.field("v_x_m_s").metadata[b"unit"] == b"m/s"
    assert table.schema.field("ref_a_z_m_s2").metadata[b"unit"] == b"m/s^2"
    about = json.loads(table.schema.metadata[b"learnest"])
    assert about["flights"][0]["sha256"] == "ab" * 32 and about["flights"][0]["methods"] == ["a", "b"]
    frame = table.to_pandas()
    np.testing.assert_array_equal(frame.loc[frame["method"] == "b", "ref_v_z_m_s"].to_numpy(), flight.reference[:, 5])


def read_mcap(data: bytes):
    from mcap.reader import make_reader

    reader = make_reader(io.BytesIO(data))
    summary = reader.get_summary()
    channels = {c.topic: c for c in summary.channels.values()}
    schemas = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
    messages: dict[str, list] = {}
    for _schema, channel, message in reader.iter_messages():
        messages.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
    return channels, schemas, messages, summary


def test_mcap_has_foxglove_schemas_one_topic_per_source_and_the_estimates():
    flight = synthetic()
    out = io.BytesIO()
    write_estimates([flight], out, "mcap")
    channels, schemas, messages, summary = read_mcap(out.getvalue())
    every = ("position", "velocity", "acceleration", "pose")
    sources = {"reference": every, "measurement": ("position", "acceleration", "pose"), "a": every, "b": every}
    expected = {f"/learnest/{s}/{q}" for s, quantities in sources.items() for q in quantities}
    assert set(channels) == expected
    assert summary.statistics.message_count == T * len(expected)
    assert {schemas[t].name for t in expected} == {"foxglove.Vector3", "foxglove.PoseInFrame"}
    assert schemas["/learnest/a/pose"].name == "foxglove.PoseInFrame" and schemas["/learnest/a/pose"].encoding == \
        "jsonschema"
    assert json.loads(schemas["/learnest/b/velocity"].data)["title"] == "foxglove.Vector3"
    assert channels["/learnest/b/velocity"].message_encoding == "json"
    assert channels["/learnest/b/velocity"].metadata["unit"] == "m/s"
    assert channels["/learnest/reference/acceleration"].metadata["unit"] == "m/s^2"

    k = 17
    log_time, velocity = messages["/learnest/b/velocity"][k]
    np.testing.assert_array_equal([velocity["x"], velocity["y"], velocity["z"]], flight.estimates["b"][k, 3:6])
    assert log_time == flight.log_start_ns + round(flight.t[k] * 1e9)
    _, reference = messages["/learnest/reference/position"][k]
    np.testing.assert_array_equal([reference[a] for a in "xyz"], flight.reference[k, 0:3])
    stamp, pose = messages["/learnest/a/pose"][k]
    np.testing.assert_array_equal([pose["pose"]["position"][a] for a in "xyz"], flight.estimates["a"][k, 0:3])
    np.testing.assert_array_equal([pose["pose"]["orientation"][a] for a in "xyzw"], flight.quat[k])
    assert pose["timestamp"]["sec"] * 10**9 + pose["timestamp"]["nsec"] == stamp and pose["frame_id"] == "world"
    _, measured = messages["/learnest/measurement/acceleration"][k]
    np.testing.assert_array_equal([measured[a] for a in "xyz"], flight.measurement[k, 3:6])


def test_mcap_of_several_flights_keeps_them_apart():
    out = io.BytesIO()
    write_estimates([synthetic("rep 1"), synthetic("rep-2", log_start_ns=0)], out, "mcap")
    channels, _, messages, _ = read_mcap(out.getvalue())
    assert "/learnest/rep_1/a/velocity" in channels and "/learnest/rep_2/reference/pose" in channels
    assert not any(topic.startswith("/learnest/a/") for topic in channels)
    assert messages["/learnest/rep_2/a/position"][3][0] == round(0.03 * 1e9)


def test_formats_suffixes_and_storage_bytes():
    assert (format_of("x.CSV"), format_of("a/b.parquet"), format_of("c.pq"), format_of("d.mcap")) == \
        ("csv", "parquet", "parquet", "mcap")
    with pytest.raises(le.InvalidInput, match=r"x\.txt.*\.csv, \.parquet, \.pq, \.mcap"):
        format_of("x.txt")
    with pytest.raises(le.InvalidInput, match="unknown export format 'xlsx'; choose one of csv, parquet, mcap"):
        write_estimates([synthetic()], io.BytesIO(), "xlsx")
    with pytest.raises(le.InvalidInput, match="no estimates"):
        write_estimates([], io.BytesIO(), "csv")
    flight = synthetic()
    back = FlightEstimates.from_bytes(flight.to_bytes())
    assert back.methods == ["a", "b"] and back.log_start_ns == flight.log_start_ns and back.flight == "hover"
    for name in ("t", "reference", "measurement", "quat"):
        np.testing.assert_array_equal(getattr(back, name), getattr(flight, name))
    np.testing.assert_array_equal(back.estimates["b"], flight.estimates["b"])
    with pytest.raises(le.InvalidInput, match=r"hover: estimates\['a'\] has shape \(50, 3\), expected \(50, 9\)"):
        FlightEstimates("hover", flight.t, flight.reference, flight.measurement, flight.quat,
                        {"a": flight.reference[:, :3]})
    with pytest.raises(le.InvalidInput, match="stored estimates are unreadable"):
        FlightEstimates.from_bytes(b"not an npz")


def test_evaluation_keeps_the_estimates_an_independent_ukf_run_gives(tmp_path):
    """The estimates handed out equal le.ukf on the same flight, the reference the SG baseline, the
    measurement y = [p, a_meas]; t = 0 sits where the flight's grid starts on the log's clock."""
    from learnest.ingest.baseline import references
    from learnest.workflows.flights import evaluate_flights

    [flight] = le.read_flights([flight_csv(tmp_path, seed=3)])
    prior = le.HybridModel(le.make_system("quadrotor"))
    kept = []
    report = evaluate_flights(prior, [flight], ["ukf"], on_estimates=lambda i, e: kept.append((i, e)))
    [(index, estimates)] = kept
    assert index == 0 and estimates.flight == flight.name and estimates.methods == ["ukf"]
    # evaluations run the UKF's loop in C (Cholesky solve of S), le.ukf the numpy filter: equal to the rounding
    # that the α = 1e-3 sigma weights amplify (8.7e-8 at most, benchmarks/results/mhe_speed.md)
    np.testing.assert_allclose(estimates.estimates["ukf"], le.ukf(prior, flight).means, rtol=0, atol=2e-7)
    np.testing.assert_array_equal(estimates.reference, references(flight))
    np.testing.assert_array_equal(estimates.measurement, flight.measurements())
    start_s = flight.meta["t0_source_s"] + flight.meta["flying_window"]["start_s"]
    assert estimates.log_start_ns == pytest.approx(start_s * 1e9, abs=1e3)
    mse = np.mean((estimates.estimates["ukf"] - estimates.reference) ** 2)
    assert report["flights"][0]["mse"]["ukf"] == pytest.approx(mse, rel=1e-12)
    assert report["units"]["groups"] == {"p": "m^2", "v": "m^2/s^2", "a": "m^2/s^4"}


def test_flight_dataframe_names_four_wide_channels_by_index_and_keeps_every_channel():
    t = np.arange(5) * 0.01
    channels = {"motors": np.full((5, 4), 30000.0), "rotor_speed": np.full((5, 4), 2000.0), "vbat": np.full(5, 3.9),
                "gyro": np.zeros((5, 3)), "thrust_cmd": np.full(5, 40000.0)}
    flight = le.Flight(t, np.zeros((5, 3)), np.zeros((5, 3)), np.tile([0.0, 0, 0, 1], (5, 1)), channels)
    frame = flight.to_dataframe()
    assert {"motors_0", "motors_3", "rotor_speed_2", "quat_w", "gyro_z", "vbat", "thrust_cmd"} <= set(frame.columns)
    assert "motors_w" not in frame.columns and "rotor_speed_x" not in frame.columns
    units = frame.attrs["units"]
    assert (units["motors_0"], units["rotor_speed_1"], units["vbat"], units["gyro_x"]) == \
        ("PWM (0-65535)", "rad/s", "V", "rad/s")
    back = le.Flight.from_dataframe(frame)
    assert back.channels.keys() == channels.keys()
    for name, values in channels.items():
        np.testing.assert_array_equal(back.channels[name], values)
