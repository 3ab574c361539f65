"""Logs as labs really have them: a cfclient log with the received pose, sidecars and
folders, logs that start in the air, poses rounded to 1 mm, fast accelerometers, the vehicle profile a model
records, and every channel a format carries.  Every log is written here, with known truth."""
import io
import json
from contextlib import redirect_stderr, redirect_stdout

import numpy as np
import pytest

from learnest.ingest import IngestError, collect_logs, read_flights
from learnest.ingest.align import parse_cut
from learnest.ingest.flight import UNITS, Flight
from learnest.ingest.formats.crazyflie_usd import writer as usd_writer
from learnest.ingest.formats.nanobench import writer as nanobench_writer
from learnest.ingest.formats.vicon_cfclient.writer import write_cfclient_csv
from learnest.ingest.profile import flight_profile, profile_mismatches
from learnest.ingest.sim import Circle, SensorModel, sim_times, simulate, write_flight
from learnest.ingest.sim.export import USD_BOOT_S
from learnest.service.cli import main

LOCSRV = ("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw")


def run_cli(*argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with redirect_stdout(out), redirect_stderr(err):
        status = main([str(a) for a in argv])
    return status, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def circle():
    """A 6-s circle with take-off and landing, default sensors (500 Hz IMU, 0.5 mm mocap noise)."""
    return simulate(Circle(radius=0.5, speed=0.8, duration_s=6.0), seed=3, name="circle")


# -- a cfclient "Log to file" CSV with locSrv.* is a flight of its own -----------------------------------------
def test_cfclient_log_with_the_received_pose_is_a_flight(circle, tmp_path):
    (path,) = write_flight(circle, "cfclient", tmp_path, "own")
    flight, = read_flights([path])
    assert flight.meta["adapter"] == "cfclient" and flight.quality["ok"], flight.quality
    assert flight.meta["attitude_source"] == "mocap (locSrv quaternion)"
    t = sim_times(flight, "cfclient")
    index = np.round(t * 100).astype(int)                 # the rows lie on the mocap frames
    np.testing.assert_allclose(flight.p, circle.mocap.p[index], atol=1e-9)
    rms = np.sqrt(np.mean((flight.a_meas - circle.truth.at(t).a) ** 2))
    assert rms < 0.25             # the sensor's 0.02 g = 0.196 m/s² noise (test_simulator: exact without noise)


def test_cfclient_position_only_pose_takes_the_onboard_attitude(circle, tmp_path):
    t = np.arange(0.0, circle.imu.t[-1], 0.01)
    acc = np.column_stack([np.interp(t, circle.imu.t, circle.imu.acc_g[:, j]) for j in range(3)])
    frame = np.searchsorted(circle.mocap.t, t + 1e-9, side="right") - 1
    extra = {name: circle.mocap.p[frame, j] for j, name in enumerate(LOCSRV[:3])}      # no locSrv.q*
    extra.update({f"stateEstimate.q{axis}": circle.mocap.quat[frame, j] for j, axis in enumerate("xyzw")})
    write_cfclient_csv(tmp_path / "posonly.csv", 5.0 + t, acc, extra)
    flight, = read_flights([tmp_path / "posonly.csv"])
    assert flight.meta["attitude_source"].startswith("onboard estimate (stateEstimate.q*)")
    assert "quat_onboard" in flight.channels
    assert flight.quality["ok"], flight.quality


def test_cfclient_log_without_a_pose_still_needs_its_vicon_export(circle, tmp_path):
    files = write_flight(circle, "vicon+cfclient", tmp_path, "pair")
    with pytest.raises(IngestError, match="pair_cfclient.csv: needs a Vicon export"):
        read_flights(files[1:])
    flight, = read_flights(files)                     # the pair is still a pair
    assert flight.meta["adapter"] == "vicon+cfclient"


# -- sidecars and folders ----------------------------------------------------------------------------------
def write_nanobench(sim, path, vehicle="CF_01"):
    t = sim.mocap.t
    acc = np.column_stack([np.interp(t, sim.imu.t, sim.imu.acc_g[:, j]) for j in range(3)])
    nanobench_writer.write(path, 1.7e9 + t, sim.mocap.p, sim.mocap.quat, acc, metadata={"crazyflie_id": vehicle})
    return path


def test_a_folder_and_its_sidecars_are_ingested(circle, tmp_path):
    folder = tmp_path / "lab"
    folder.mkdir()
    write_nanobench(circle, folder / "B1_rep1.csv")
    write_nanobench(circle, folder / "B1_rep2.csv", vehicle="CF_02")
    (folder / "README.md").write_text("flights of the lab\n")
    (folder / "LICENSE").write_text("BSD\n")
    logs, notes = collect_logs([folder])
    assert [p.name for p in logs] == ["B1_rep1.csv", "B1_rep2.csv"]
    assert any("B1_rep1_metadata.yaml: metadata of B1_rep1.csv" in n for n in notes)
    assert any("README.md" in n for n in notes) and any("LICENSE" in n for n in notes)

    status, out, err = run_cli("ingest", folder)                 # `ingest` of a folder, as `demo` accepts
    assert status == 0, err
    assert "B1_rep1: nanobench" in out and "B1_rep2: nanobench" in out
    assert "metadata of B1_rep2.csv, read with it" in err

    # what a shell glob gives: every file, sidecars included (`learnest ingest nanobench/*`)
    status, out, err = run_cli("ingest", "--json", *sorted(folder.iterdir()))
    assert status == 0, err
    flights = json.loads(out)["flights"]
    assert [f["profile"]["vehicle"] for f in flights] == ["CF_01", "CF_02"]
    flight, = read_flights([folder / "B1_rep1.csv", folder / "B1_rep1_metadata.yaml"])   # the Python API too
    assert flight.meta["vehicle"] == "CF_01"
    with pytest.raises(IngestError, match="a metadata sidecar, not a flight log: give the log it belongs to"):
        read_flights([folder / "B1_rep1_metadata.yaml"])


def test_crazyswarm2_info_sidecar_gives_mass_and_controller(circle, tmp_path):
    write_flight(circle, "usd", tmp_path, "log7")
    (tmp_path / "info7.yaml").write_text("experiment: 7\nmass: 0.034\ncontroller: mellinger\nKpos_Px: 17.0\n")
    flight, = read_flights([tmp_path / "log7"])
    assert flight.meta["mass_kg"] == pytest.approx(0.034) and flight.meta["controller"] == "mellinger"
    assert flight.meta["vehicle_info"]["Kpos_Px"] == 17.0
    assert [s["path"] for s in flight.meta["sources"]] == [str(tmp_path / "log7"), str(tmp_path / "info7.yaml")]
    assert flight.meta["profile"]["mass_kg"] == pytest.approx(0.034)

    # uploaded together (the web form, POST /flights): staged where the reader looks for it
    from learnest.service.jobs.reading import read_uploaded_flight
    from learnest.service.operations.uploads import LocalFile, stage_uploads

    staging = tmp_path / "staging"
    staging.mkdir()
    with open(tmp_path / "log7", "rb") as log, open(tmp_path / "info7.yaml", "rb") as info:
        staged = stage_uploads([LocalFile("info7.yaml", info), LocalFile("log7", log)], staging)
    assert [f.role for f in staged] == ["sidecar", "log"]
    uploaded = read_uploaded_flight(staged)
    assert uploaded.meta["mass_kg"] == pytest.approx(0.034)
    assert [s["path"] for s in uploaded.meta["sources"]] == ["log7", "info7.yaml"]   # the client's names


def test_a_broken_info_sidecar_is_a_warning_not_a_failure(circle, tmp_path):
    write_flight(circle, "usd", tmp_path, "log8")
    (tmp_path / "info8.yaml").write_text("mass: [unclosed\n")
    flight, = read_flights([tmp_path / "log8"])
    assert "mass_kg" not in flight.meta
    assert any("info8.yaml: unreadable YAML" in w for w in flight.meta["usd"]["warnings"])


# -- a log that starts in the air ------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def airborne_start(circle, tmp_path_factory):
    """The circle's NanoBench log without its first 4 s: logging starts hovering at 1 m (take-off done),
    then the circle, the landing and 1 s on the ground."""
    import pandas as pd

    directory = tmp_path_factory.mktemp("airborne")
    full = write_nanobench(circle, directory / "full.csv")
    table = pd.read_csv(full)
    start = table["t"].iloc[0] + 4.0
    table[table["t"] >= start - 1e-6].to_csv(directory / "in_air.csv", index=False, float_format="%.9f")
    return directory / "in_air.csv", start - table["t"].iloc[0]


def test_a_log_that_starts_in_the_air_keeps_its_start(circle, airborne_start):
    path, skipped = airborne_start
    flight, = read_flights([path])
    window = flight.meta["flying_window"]
    assert window["start_s"] == 0.0 and "starts in the air" in window["rule"]
    # the end: 1 s before last coming down through 10 cm above the ground (the truth says when)
    airborne = circle.truth.t[circle.truth.p[:, 2] > circle.truth.p[-1, 2] + 0.10]
    assert window["stop_s"] == pytest.approx(airborne[-1] - skipped - 1.0, abs=0.03)
    assert flight.quality["ok"], flight.quality
    assert flight.p[:, 2].min() > 0.5                  # before: the whole log, landing and ground included


def test_the_cut_can_be_chosen_and_is_shown(airborne_start):
    path, _ = airborne_start
    flight, = read_flights([path], cut="2:7.5")
    assert flight.meta["flying_window"]["start_s"] == pytest.approx(2.0)
    assert flight.duration_s == pytest.approx(5.5)
    assert flight.meta["cut_choice"] == "2:7.5"
    whole, = read_flights([path], cut="none")
    assert whole.duration_s == pytest.approx(whole.meta["flying_window"]["recording_s"])
    status, out, _ = run_cli("ingest", path)
    assert status == 0 and "kept 0.00-" in out and "starts in the air" in out and "--cut" in out
    status, _, err = run_cli("ingest", "--cut", "5:2", path)
    assert status == 2 and "START must come before STOP" in err
    with pytest.raises(Exception, match="give auto, none or START:STOP"):
        parse_cut("from 2 s")


def test_the_upload_takes_a_cut_and_keys_on_it(airborne_start, tmp_path):
    from utils.service import running_app, upload

    path, _ = airborne_start
    with running_app(tmp_path / "home") as client:
        auto = upload(client, path)
        chosen = upload(client, path, cut="1:6")
        assert auto.status_code == 201 and chosen.status_code == 201      # another stretch, another flight
        assert chosen.json()["duration_s"] == pytest.approx(5.0)
        detail = client.get(f"/flights/{chosen.json()['id']}").json()
        assert detail["meta"]["cut_choice"] == "1:6" and detail["meta"]["flying_window"]["start_s"] == 1.0
        assert upload(client, path, cut="1:6").status_code == 200        # the same stretch again: stored once
        refused = upload(client, path, cut="6:1")
        assert refused.status_code == 422 and "START must come before STOP" in refused.text


# -- poses rounded to 1 mm -------------------------------------------------------------------------------------
def rounded_usd(sim, directory, stem, hold=None):
    """A uSD log whose locSrv is rounded to 1 mm (crazyswarm2's int16 mm extpos), sample-and-hold in the
    250 Hz fixed stream; ``hold`` = (start, stop) s: the pose stops updating then (a frozen mocap)."""
    p = np.round(sim.mocap.p * 1000.0) / 1000.0
    t_imu = np.arange(0.0, sim.imu.t[-1], 1 / 250)
    frame = np.searchsorted(sim.mocap.t, t_imu + 1e-9, side="right") - 1
    if hold is not None:
        held = (t_imu >= hold[0]) & (t_imu < hold[1])
        frame[held] = frame[np.argmax(held)]
    acc = np.column_stack([np.interp(t_imu, sim.imu.t, sim.imu.acc_g[:, j]) for j in range(3)])
    pose = np.column_stack([p, sim.mocap.quat])[frame]
    fixed = {f"acc.{a}": ("f", acc[:, j]) for j, a in enumerate("xyz")}
    fixed.update({name: ("f", pose[:, j]) for j, name in enumerate(LOCSRV)})
    usd_writer.write(directory / stem, {"fixedFrequency": {"t": USD_BOOT_S + t_imu, "vars": fixed}})
    return directory / stem


def rounded_event_usd(sim, directory, stem, hold=None):
    """The pose rounded to 1 mm in an event stream of its own (one record per mocap frame); ``hold``: frames
    that repeat the last one (the mocap froze)."""
    p = np.round(sim.mocap.p * 1000.0) / 1000.0
    frame = np.arange(len(sim.mocap.t))
    if hold is not None:
        held = (sim.mocap.t >= hold[0]) & (sim.mocap.t < hold[1])
        frame[held] = frame[np.argmax(held)]
    pose = np.column_stack([p, sim.mocap.quat])[frame]
    fixed = {f"acc.{a}": ("f", sim.imu.acc_g[:, j]) for j, a in enumerate("xyz")}
    events = {"fixedFrequency": {"t": USD_BOOT_S + sim.imu.t, "vars": fixed},
              "locSrvPose": {"t": USD_BOOT_S + sim.mocap.t,
                             "vars": {name: ("f", pose[:, j]) for j, name in enumerate(LOCSRV)}}}
    usd_writer.write(directory / stem, events)
    return directory / stem


def test_a_clean_hover_rounded_to_a_millimetre_is_not_frozen_or_gappy(tmp_path):
    hover = simulate(Circle(radius=0.005, speed=0.002, duration_s=8.0), seed=4, name="hover",
                     sensors=SensorModel(imu_rate_hz=500.0, mocap_position_noise_m=0.0001))
    flight, = read_flights([rounded_usd(hover, tmp_path, "hover")])
    assert flight.meta["mocap_resolution_m"] == pytest.approx(0.001)
    assert flight.quality["ok"], flight.quality       # before: "mocap position frozen ... (held/occluded)"
    assert flight.meta["gaps"]["mocap_samples_in_gaps"] == 0
    flight, = read_flights([rounded_event_usd(hover, tmp_path, "hover_events")])   # every frame, repeats too
    assert flight.quality["ok"], flight.quality


def test_a_frozen_mocap_is_still_frozen_at_a_millimetre(circle, tmp_path):
    flight, = read_flights([rounded_event_usd(circle, tmp_path, "frozen", hold=(7.0, 7.3))])
    assert flight.meta["mocap_resolution_m"] == pytest.approx(0.001)
    assert any(issue.startswith("mocap position frozen for 0.3") for issue in flight.quality["issues"]), \
        flight.quality


def test_a_held_pose_while_the_vehicle_moves_is_still_a_gap(circle, tmp_path):
    """The fixed stream repeats the last frame received: 0.8 s of one pose while the vehicle flies on at
    0.8 m/s is a stretch without mocap (the pose jumps 0.6 m when it resumes), rounding or not."""
    flight, = read_flights([rounded_usd(circle, tmp_path, "held", hold=(7.0, 7.8))])
    assert flight.meta["mocap_resolution_m"] == pytest.approx(0.001)
    assert any(issue.startswith("mocap stream missing for 0.8") for issue in flight.quality["issues"]), \
        flight.quality


# -- accelerometers faster than the grid: anti-aliasing ----------------------------------------------------------
@pytest.fixture(scope="module")
def tone_flights(tmp_path_factory):
    """The same noise-free 500 Hz flight written twice as a uSD log: clean, and with vibration tones added
    to acc.x (a 90 Hz tone folds to 10 Hz on a 100 Hz grid, a 70 Hz one to 30 Hz) and a 5 Hz one (in band)."""
    directory = tmp_path_factory.mktemp("tones")
    sim = simulate(Circle(radius=0.5, speed=0.5, duration_s=6.0), sensors=SensorModel.ideal(imu_rate_hz=500.0),
                   seed=2, name="tones")
    clean, = read_flights(write_flight(sim, "usd", directory, "clean", usd_pose_stream="event"))
    t = sim.imu.t
    sim.imu.acc_g[:, 0] += 0.5 * np.sin(2 * np.pi * 90.0 * t) + 0.3 * np.sin(2 * np.pi * 70.0 * t)
    sim.imu.acc_g[:, 0] += 0.01 * np.sin(2 * np.pi * 5.0 * t)
    shaken, = read_flights(write_flight(sim, "usd", directory, "shaken", usd_pose_stream="event"))
    return clean, shaken


def amplitudes(signal, dt):
    """One-sided amplitude spectrum (m/s² per bin) and its frequencies (Hz)."""
    return np.abs(np.fft.rfft(signal)) * 2 / len(signal), np.fft.rfftfreq(len(signal), dt)


def test_vibration_above_the_nyquist_frequency_does_not_fold_into_the_band(tone_flights):
    clean, shaken = tone_flights
    added = shaken.channels["acc_body"][:, 0] - clean.channels["acc_body"][:, 0]
    spectrum, freq = amplitudes(added * np.hanning(len(added)) * 2, clean.dt)
    five_hz = spectrum[np.argmin(np.abs(freq - 5.0))]
    assert five_hz == pytest.approx(0.01 * 9.80665, rel=0.03)          # the band passes (0.098 m/s²)
    # plain interpolation would put 4.9 m/s² at 10 Hz (the 90 Hz tone folded); the low-pass leaves < 1e-3
    assert spectrum[(freq < 20.0) & (np.abs(freq - 5.0) > 1.0)].max() < 1e-3
    assert spectrum[(freq > 25.0) & (freq < 35.0)].max() < 3e-3         # the 70 Hz tone folded to 30 Hz
    assert shaken.meta["anti_alias"]["streams"] == ["acc", "gyro"]
    assert shaken.meta["anti_alias"]["cutoff_hz"] == pytest.approx(40.0)


def test_a_100_hz_accelerometer_is_not_filtered(circle, tmp_path):
    flight, = read_flights(write_flight(circle, "cfclient", tmp_path, "slow"))
    assert "anti_alias" not in flight.meta


# -- the vehicle and its sensors: recorded by the model, checked at evaluation ----------------------------------
def test_models_record_the_vehicle_and_warn_on_another(circle, tmp_path):
    from learnest.models.knode import HybridModel
    from learnest.models.presets import TrainingConfig
    from learnest.service.cli import format_report
    from learnest.workflows.flights import evaluate_flights, train_on_flight

    twin = simulate(Circle(radius=0.5, speed=0.8, duration_s=6.0), seed=5, name="twin")
    trained, = read_flights([write_nanobench(circle, tmp_path / "train.csv", vehicle="CF_01")])
    same, = read_flights([write_nanobench(twin, tmp_path / "same.csv", vehicle="CF_01")])
    other, = read_flights([write_nanobench(twin, tmp_path / "other.csv", vehicle="CF_07")])
    fast, = read_flights(write_flight(twin, "usd", tmp_path, "fast"))        # 500 Hz IMU, no vehicle name
    model = train_on_flight(trained, TrainingConfig(hidden=8, epochs=2, validation_fraction=0.0)).model
    assert model.meta["training_profile"]["vehicle"] == "CF_01"
    assert model.meta["training_profile"]["rates_hz"]["acc"] == pytest.approx(100.0, abs=1.0)
    model.save(tmp_path / "m.json")
    model = HybridModel.load(tmp_path / "m.json")                 # stored with the model

    report = evaluate_flights(model, [same, other, fast], ["ukf"])
    warnings = {f["flight"]: f["warnings"] for f in report["flights"]}
    assert warnings["same"] == []
    assert warnings["other"] == ["another vehicle: flight from CF_07, model trained on CF_01"]
    # a 500 Hz IMU reaches the model low-passed onto the same 100 Hz grid: no rate warning
    assert not any("rate" in w for w in warnings["fast"])
    assert "WARNING other: another vehicle" in format_report(report)


def test_profile_mismatches_name_each_difference():
    base = {"vehicle": "cf1", "rates_hz": {"acc": 100.0, "mocap": 100.0, "grid": 100.0},
            "attitude_source": "mocap (locSrv quaternion)", "mass_kg": 0.032, "controller": "lee"}
    assert profile_mismatches(base, dict(base)) == []
    assert profile_mismatches(None, base) == []                    # a model stored before profiles: silent
    other = {**base, "attitude_source": "onboard estimate (ctrlLee.rpy), locSrv quaternion is zero",
             "mass_kg": 0.037, "controller": "mellinger", "rates_hz": {"acc": 105.0, "mocap": 50.0, "grid": 100.0}}
    text = " | ".join(profile_mismatches(base, other))
    assert "another attitude source" in text and "another mass: 37.0 g" in text and "another controller" in text
    assert "another mocap rate: 50 Hz" in text and "acc rate" not in text      # 5 % is the same setting
    faster = {**base, "rates_hz": {"acc": 500.0, "mocap": 250.0, "grid": 100.0}}
    assert profile_mismatches(base, faster) == []                   # above the grid: the same input to the model
    slower = {**base, "rates_hz": {"acc": 50.0, "mocap": 100.0, "grid": 100.0}}
    assert profile_mismatches(base, slower) == ["another acc rate: 50 Hz, model trained at 100 Hz"]
    assert profile_mismatches(slower, base) == ["another acc rate: 100 Hz, model trained at 50 Hz"]


# -- every channel a format carries ----------------------------------------------------------------------------
def test_onboard_estimates_and_commands_are_kept_with_units(circle, tmp_path):
    t = np.arange(0.0, circle.imu.t[-1], 0.004)
    frame = np.searchsorted(circle.mocap.t, t + 1e-9, side="right") - 1
    truth = circle.truth.at(t)
    acc = np.column_stack([np.interp(t, circle.imu.t, circle.imu.acc_g[:, j]) for j in range(3)])
    pose = np.column_stack([circle.mocap.p, circle.mocap.quat])[frame]
    fixed = {f"acc.{a}": ("f", acc[:, j]) for j, a in enumerate("xyz")}
    fixed.update({name: ("f", pose[:, j]) for j, name in enumerate(LOCSRV)})
    fixed.update({f"stateEstimate.q{a}": ("f", truth.quat[:, j]) for j, a in enumerate("xyzw")})
    fixed.update({f"stateEstimate.a{a}": ("f", truth.a[:, j] / 9.80665) for j, a in enumerate("xyz")})  # g
    fixed.update({f"ctrlLee.torque{a}": ("f", np.full(len(t), 1e-4 * (j + 1))) for j, a in enumerate("xyz")})
    usd_writer.write(tmp_path / "rich", {"fixedFrequency": {"t": USD_BOOT_S + t, "vars": fixed}})
    flight, = read_flights([tmp_path / "rich"])
    assert {"quat_onboard", "acc_onboard", "torque_cmd"} <= set(flight.channels)
    t_sim = sim_times(flight, "usd")
    assert np.abs(flight.channels["acc_onboard"] - circle.truth.at(t_sim).a).max() < 0.02     # g -> m/s²
    np.testing.assert_allclose(flight.channels["torque_cmd"][0], [1e-4, 2e-4, 3e-4], rtol=1e-5)

    frame = flight.to_dataframe()
    assert {"quat_onboard_w", "acc_onboard_z", "torque_cmd_y"} <= set(frame.columns)
    assert frame.attrs["units"]["acc_onboard_x"] == "m/s^2" and frame.attrs["units"]["torque_cmd_x"] == "N m"
    back = Flight.from_dataframe(frame)
    np.testing.assert_array_equal(back.channels["quat_onboard"], flight.channels["quat_onboard"])
    assert set(UNITS) >= set(flight.channels)                      # every channel has its unit
