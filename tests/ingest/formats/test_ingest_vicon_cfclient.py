"""Vicon CSV + cfclient CSV adapter: simulated flights with known truth and clock offset, file variants,
bad inputs, fuzzing."""
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from learnest.ingest import clock
from learnest.ingest.flight import Flight, IngestError, sha256_file
from learnest.ingest.formats.vicon_cfclient import cfclient, vicon
from learnest.ingest.formats.vicon_cfclient import reader as pair_reader
from learnest.ingest.formats.vicon_cfclient import writer as pair_writer
from learnest.ingest.frames import GRAVITY

# -- the simulated flight -------------------------------------------------------------------------------
# One simulation clock τ.  The cfclient log runs from τ = 0 and stamps rows with the Crazyflie's boot
# clock, BOOT_AHEAD_S ahead of τ; the Vicon capture starts later, at τ = VICON_START_S, and counts from 0
# there.  So t_vicon = τ - VICON_START_S = t_cfclient - BOOT_AHEAD_S - VICON_START_S.
BOOT_AHEAD_S = 12.345
VICON_START_S = 1.3
TRUE_OFFSET_S = -(BOOT_AHEAD_S + VICON_START_S)
DURATION_S = 30.0
RATE_HZ = 100.0
MOCAP_NOISE_M = 1e-4           # Vicon: ~0.1 mm
ACC_NOISE_G = 0.01             # per axis, white
SAMPLE_S = 1.0 / RATE_HZ


def smoothstep(u):
    u = np.clip(u, 0.0, 1.0)
    return u ** 3 * (10 - 15 * u + 6 * u * u)


def true_position(tau, kind="figure8"):
    """On the ground, take-off at 2-4 s, figure-eight with a vertical wave, landing 4-2 s before the end
    ("figure8"); the figure-eight alone, airborne throughout ("airborne8"); or a hover ("hover")."""
    tau = np.asarray(tau, dtype=float)
    if kind == "hover":
        return np.column_stack([0.3 + 0 * tau, -0.2 + 0 * tau, 1.0 + 0 * tau])
    envelope = smoothstep((tau - 2.0) / 2.0) * smoothstep((DURATION_S - 2.0 - tau) / 2.0)
    if kind == "airborne8":
        envelope = np.ones_like(tau)
    w = 2 * np.pi / 8.0
    return np.column_stack([0.8 * np.sin(w * tau) * envelope,
                            0.5 * np.sin(2 * w * tau) * envelope,
                            0.03 + (1.0 + 0.1 * np.sin(1.3 * tau)) * envelope])


def true_acceleration(tau, kind="figure8"):
    # Central second difference of the analytic position: truncation h²/12·|p''''| < 1e-5 m/s² and
    # rounding 1e-16/h² ~ 1e-10 m/s², far below every tolerance used here.
    h = 1e-3
    return (true_position(tau + h, kind) - 2 * true_position(tau, kind) + true_position(tau - h, kind)) / h ** 2


def true_attitude(tau, kind="figure8"):
    """Body z along the thrust (a + g ẑ), yaw 0.3 + 0.2 sin(0.5 τ): what a quadrotor flies."""
    thrust = true_acceleration(tau, kind) + [0.0, 0.0, GRAVITY]
    z_b = thrust / np.linalg.norm(thrust, axis=1, keepdims=True)
    yaw = 0.3 + 0.2 * np.sin(0.5 * tau)
    x_c = np.column_stack([np.cos(yaw), np.sin(yaw), 0 * yaw])
    y_b = np.cross(z_b, x_c)
    y_b /= np.linalg.norm(y_b, axis=1, keepdims=True)
    x_b = np.cross(y_b, z_b)
    return Rotation.from_matrix(np.stack([x_b, y_b, z_b], axis=-1)).as_quat()


def accelerometer_g(tau, kind="figure8"):
    """Ideal body-frame specific force in g: R^T (a + g ẑ) / g."""
    world = true_acceleration(tau, kind) + [0.0, 0.0, GRAVITY]
    return Rotation.from_quat(true_attitude(tau, kind)).inv().apply(world) / GRAVITY


class Scenario:
    """Both files of one simulated flight plus the truth written into them."""

    def __init__(self, directory: Path, kind="figure8", seed=0, occluded=(), vicon_kwargs=None,
                 duration=DURATION_S, name="flight", lowpass: clock.SensorLowPass | None = None):
        self.lowpass = lowpass     # the accelerometer's own filter, run on its samples before they are logged
        rng = np.random.default_rng(seed)
        self.kind = kind
        # Vicon frames on its own clock: 0, 10 ms, ... (capture ends 1.7 s before the log does).
        self.t_vicon = np.arange(int(round((duration - VICON_START_S - 0.4) * RATE_HZ))) / RATE_HZ
        tau_frames = self.t_vicon + VICON_START_S
        self.p_written = true_position(tau_frames, kind) + rng.normal(0.0, MOCAP_NOISE_M, (len(tau_frames), 3))
        self.quat_written = true_attitude(tau_frames, kind)
        self.occluded = np.zeros(len(self.t_vicon), dtype=bool)
        self.occluded[list(occluded)] = True
        self.vicon = directory / f"{name}_vicon.csv"
        pair_writer.write_vicon_csv(self.vicon, self.t_vicon, self.p_written, self.quat_written, RATE_HZ,
                                  self.occluded, **(vicon_kwargs or {}))
        # cfclient: ~100 Hz packets with ±2 ms jitter in the sample instants, 1 % of packets lost.
        tau_acc = np.arange(0.0, duration, SAMPLE_S) + rng.uniform(-0.002, 0.002, int(round(duration * RATE_HZ)))
        tau_acc = tau_acc[rng.random(len(tau_acc)) > 0.01]
        acc = self._sensed_g(tau_acc, kind, duration) + rng.normal(0.0, ACC_NOISE_G, (len(tau_acc), 3))
        gyro_deg_s = np.tile([10.0, -20.0, 30.0], (len(tau_acc), 1))
        self.cfclient = directory / f"{name}_cfclient.csv"
        pair_writer.write_cfclient_csv(self.cfclient, tau_acc + BOOT_AHEAD_S, acc, extra={
            "gyro.x": gyro_deg_s[:, 0], "gyro.y": gyro_deg_s[:, 1], "gyro.z": gyro_deg_s[:, 2],
            "pm.vbat": np.full(len(tau_acc), 3.9)})

    def _sensed_g(self, tau_acc, kind, duration):
        """The accelerometer at the log's instants: ideal, or through ``lowpass`` run on its own samples."""
        if self.lowpass is None:
            return accelerometer_g(tau_acc, kind)
        from scipy.signal import lfilter

        tau_fine = np.arange(-1.0, duration + 0.01, 1.0 / self.lowpass.rate_hz)
        fine = accelerometer_g(tau_fine, kind)
        filtered = lfilter(*self.lowpass.coefficients(), fine - fine[0], axis=0) + fine[0]
        return np.column_stack([np.interp(tau_acc, tau_fine, filtered[:, j]) for j in range(3)])

    def read(self, **kwargs):
        # the written accelerometer is unfiltered unless the scenario says otherwise
        kwargs.setdefault("accel_lowpass", self.lowpass)
        return pair_reader.read_pair(self.vicon, self.cfclient, **kwargs)


def vicon_times(flight):
    """The Vicon-clock time of every sample of a Flight (grid start + the cut + time in the flight)."""
    return flight.meta["t0_source_s"] + flight.meta["flying_window"]["start_s"] + flight.t


# A long occlusion (0.4 s) in flight, a 3-frame and a 1-frame one.
LONG_GAP = range(1200, 1240)
OCCLUDED = list(LONG_GAP) + [800, 801, 802, 1500]


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return Scenario(tmp_path_factory.mktemp("pair"), occluded=OCCLUDED)


@pytest.fixture(scope="module")
def flight(scenario):
    return scenario.read()


# -- the main round trip --------------------------------------------------------------------------------
def test_clock_offset_is_recovered_within_one_sample(flight):
    assert flight.meta["clock_offset_s"] == pytest.approx(TRUE_OFFSET_S, abs=SAMPLE_S)
    # Observed: ~2 ms with this noise; the sub-sample (parabolic) refinement is what makes that possible.
    assert abs(flight.meta["clock_offset_s"] - TRUE_OFFSET_S) < 0.005
    assert flight.meta["clock_offset_score"] > 0.95
    assert flight.meta["clock_alignment"]["runner_up"] < 0.8 * flight.meta["clock_offset_score"]
    assert "quality" not in flight.meta and flight.meta["warnings"] == []


def test_the_accelerometer_low_pass_delay_is_not_taken_for_a_clock_offset(tmp_path):
    # The Crazyflie firmware's 2-pole 30 Hz filter at 1 kHz delays the logged accelerometer by
    # sqrt(2)/(2 pi 30 Hz) = 7.5 ms: uncorrected, the correlation takes it for the clocks' offset.
    lowpass = clock.CRAZYFLIE_ACCEL_LOWPASS
    assert lowpass.group_delay_s() == pytest.approx(np.sqrt(2) / (2 * np.pi * 30.0), abs=1e-4)
    scenario = Scenario(tmp_path, lowpass=lowpass)
    corrected, uncorrected = scenario.read(), scenario.read(accel_lowpass=None)
    assert corrected.meta["clock_alignment"]["sensor_delay_s"] == pytest.approx(0.0075, abs=1e-4)
    assert abs(corrected.meta["clock_offset_s"] - TRUE_OFFSET_S) < 0.003
    assert uncorrected.meta["clock_offset_s"] - TRUE_OFFSET_S == pytest.approx(-0.0075, abs=0.003)
    # the default is the Crazyflie firmware's filter: a cfclient log's acc.x/y/z have been through it
    assert pair_reader.read_pair(scenario.vicon, scenario.cfclient).meta["clock_offset_s"] == \
        corrected.meta["clock_offset_s"]


def test_parser_returns_the_written_positions_and_attitudes(scenario):
    track = vicon.read_vicon_csv(scenario.vicon)
    seen = ~scenario.occluded
    np.testing.assert_array_equal(track.t, scenario.t_vicon[seen])
    assert np.abs(track.p - scenario.p_written[seen]).max() < 1e-6                     # m (written to 1 nm)
    dots = np.abs(np.sum(track.quat * scenario.quat_written[seen], axis=1))           # q and -q: same attitude
    assert np.abs(dots - 1.0).max() < 1e-9
    assert track.subject == "cf1" and track.segment == "cf1:cf1" and track.rate_hz == RATE_HZ


def test_flight_positions_equal_the_mocap_frames_on_the_grid(flight, scenario):
    # The cfclient log starts first, so the grid starts at the first Vicon frame and every grid point is a
    # frame: the Flight's p there is the parsed frame itself, not an interpolation.
    assert flight.meta["t0_source_s"] == 0.0
    frame = np.round(vicon_times(flight) * RATE_HZ).astype(int)
    assert np.abs(vicon_times(flight) - frame / RATE_HZ).max() < 1e-9
    seen = ~scenario.occluded[frame]
    assert np.abs(flight.p[seen] - scenario.p_written[frame[seen]]).max() < 1e-6


def test_a_meas_equals_the_true_acceleration_within_the_accelerometer_noise(flight):
    error = flight.a_meas - true_acceleration(vicon_times(flight) + VICON_START_S)
    noise = ACC_NOISE_G * GRAVITY   # 0.098 m/s² per axis, rotated into the world: same per-axis rms
    # Linear interpolation between two noisy samples has rms <= noise; the deterministic parts (offset
    # error ~1 ms x jerk < 3 m/s³, interpolation h²/8 x snap) are < 0.005 m/s².  Over ~7000 samples per
    # axis the mean is noise/√N ~ 0.002 and the largest |error| ~ 4.3 noise.
    assert np.sqrt(np.mean(error ** 2, axis=0)).max() < 1.1 * noise
    assert np.abs(error.mean(axis=0)).max() < 0.01
    assert np.abs(error).max() < 6 * noise


def test_meta_names_both_sources_rates_and_the_vicon_subject(flight, scenario):
    meta = flight.meta
    assert meta["adapter"] == "vicon+cfclient"
    assert meta["sources"] == [{"path": str(scenario.vicon), "sha256": sha256_file(scenario.vicon)},
                               {"path": str(scenario.cfclient), "sha256": sha256_file(scenario.cfclient)}]
    assert meta["original_rates"]["mocap"] == RATE_HZ
    # the rate is the logger's, from the stamps; the 1 % of packets lost are gaps, not a slower rate
    assert meta["original_rates"]["acc"] == pytest.approx(100.0, abs=0.5)
    assert meta["timing"]["acc"]["delivered"] == pytest.approx(0.99, abs=0.006)
    assert meta["timing"]["acc"]["gaps"] > 0
    assert meta["vicon"]["subject"] == "cf1"
    assert meta["vicon"]["units"] == {"position": "mm", "rotation": "rad", "from": "units line"}
    assert flight.name == "flight_vicon"
    assert Flight.from_bytes(flight.to_bytes()).meta == meta      # JSON-safe, survives save/load


def test_optional_cfclient_variables_become_channels_on_the_vicon_clock(flight):
    np.testing.assert_allclose(flight.channels["gyro"], np.deg2rad([10.0, -20.0, 30.0]) + 0 * flight.p)
    np.testing.assert_allclose(flight.channels["vbat"], 3.9)
    assert flight.channels["acc_body"].shape == flight.p.shape


# -- occlusions -----------------------------------------------------------------------------------------
def test_occluded_frames_are_counted_and_left_out(flight, scenario):
    track = vicon.read_vicon_csv(scenario.vicon)
    assert track.occluded_frames == len(OCCLUDED) == flight.meta["vicon"]["occluded_frames"]
    assert len(track.t) == len(scenario.t_vicon) - len(OCCLUDED)
    assert not np.isin(np.round(track.t * RATE_HZ).astype(int), OCCLUDED).any()
    # build_flight counts the grid points inside the long gap (it ignores gaps of <= 5 frames); it also
    # counts the grid point that lands exactly on the first frame after the gap (searchsorted side), hence +1.
    assert len(LONG_GAP) <= flight.meta["gaps"]["mocap_samples_in_gaps"] <= len(LONG_GAP) + 1


def test_occluded_stretch_is_bridged_not_invented(flight, scenario):
    """Inside the 0.4 s gap the Flight holds the straight line between the frames either side — the
    interpolation the quality check recognises — and not the (unknown) true path."""
    frame = np.round(vicon_times(flight) * RATE_HZ).astype(int)
    before, after = LONG_GAP.start - 1, LONG_GAP.stop
    inside = np.isin(frame, LONG_GAP)
    weight = ((frame[inside] - before) / (after - before))[:, None]
    line = scenario.p_written[before] + weight * (scenario.p_written[after] - scenario.p_written[before])
    assert np.abs(flight.p[inside] - line).max() < 1e-9
    assert np.abs(flight.p[inside] - scenario.p_written[frame[inside]]).max() > 1e-3


# -- file variants --------------------------------------------------------------------------------------
def assert_same_track(path, reference, atol=1e-6):
    track = vicon.read_vicon_csv(path)
    np.testing.assert_array_equal(track.t, reference.t)
    assert np.abs(track.p - reference.p).max() < atol
    return track


def test_metres_crlf_trailing_commas_and_marker_section_read_the_same(tmp_path, scenario):
    reference = vicon.read_vicon_csv(scenario.vicon)
    variants = {"metres": {"units": "m"}, "crlf": {"newline": "\r\n"}, "markers": {"marker_section": True}}
    for name, kwargs in variants.items():
        path = tmp_path / f"{name}.csv"
        pair_writer.write_vicon_csv(path, scenario.t_vicon, scenario.p_written, scenario.quat_written, RATE_HZ,
                                  scenario.occluded, **kwargs)
        assert assert_same_track(path, reference).warnings == []
    trailing = tmp_path / "trailing.csv"
    trailing.write_text("".join(line + ",\r\n" for line in scenario.vicon.read_text().splitlines()))
    assert_same_track(trailing, reference)


def test_segment_section_after_a_marker_section_is_found(tmp_path, scenario):
    markers = "Trajectories\n100\n,,cf1:m1,,\nFrame,Sub Frame,X,Y,Z\n,,mm,mm,mm\n1,0,1.0,2.0,3.0\n2,0,1.0,2.0,3.0\n\n"
    path = tmp_path / "markers_first.csv"
    path.write_text(markers + scenario.vicon.read_text())
    assert_same_track(path, vicon.read_vicon_csv(scenario.vicon))


def test_degrees_in_the_units_line_are_converted(tmp_path):
    path = tmp_path / "deg.csv"
    path.write_text("Segments\n100\n,,cf1:cf1,,,,,\nFrame,Sub Frame,RX,RY,RZ,TX,TY,TZ\n,,deg,deg,deg,mm,mm,mm\n"
                    "1,0,0,0,90,1000,0,0\n2,0,0,0,90,1000,0,0\n")
    track = vicon.read_vicon_csv(path)
    np.testing.assert_allclose(Rotation.from_quat(track.quat).as_rotvec(), [[0, 0, np.pi / 2]] * 2)
    np.testing.assert_allclose(track.p, [[1.0, 0, 0]] * 2)


@pytest.mark.parametrize("units", ["mm", "m"])
def test_units_decided_by_magnitude_without_units_line_with_a_warning(tmp_path, scenario, units):
    path = tmp_path / f"no_units_{units}.csv"
    pair_writer.write_vicon_csv(path, scenario.t_vicon, scenario.p_written, scenario.quat_written, RATE_HZ,
                              units=units, units_line=False)
    track = vicon.read_vicon_csv(path)
    assert np.abs(track.p - scenario.p_written).max() < 1e-6
    assert track.units == {"position": units, "rotation": "rad", "from": "magnitude"}
    assert any(f"assumed {units}" in warning for warning in track.warnings)


def test_several_segments_pick_by_name(tmp_path):
    path = tmp_path / "two.csv"
    path.write_text("Segments\n100\n,,cf1:cf1,,,,,,cf2:cf2,,,,,\n"
                    "Frame,Sub Frame,RX,RY,RZ,TX,TY,TZ,RX,RY,RZ,TX,TY,TZ\n,,rad,rad,rad,mm,mm,mm,rad,rad,rad,m,m,m\n"
                    "1,0,0,0,0,1000,0,0,0,0,0,2,0,0\n2,0,0,0,0,1000,0,0,0,0,0,2,0,0\n")
    assert vicon.read_vicon_csv(path).p[0, 0] == pytest.approx(1.0)
    track = vicon.read_vicon_csv(path, segment="cf2")
    assert track.p[0, 0] == pytest.approx(2.0) and track.subject == "cf2"
    assert any("2 segments" in warning for warning in track.warnings)


def test_cfclient_crlf_and_sniffers(tmp_path, scenario):
    crlf = tmp_path / "crlf_cfclient.csv"
    crlf.write_bytes(scenario.cfclient.read_bytes().replace(b"\n", b"\r\n"))
    reference, log = cfclient.read_cfclient_csv(scenario.cfclient), cfclient.read_cfclient_csv(crlf)
    np.testing.assert_array_equal(log.t, reference.t)
    np.testing.assert_array_equal(log.acc_g, reference.acc_g)
    assert vicon.sniff_vicon(scenario.vicon) and not vicon.sniff_vicon(scenario.cfclient)
    assert cfclient.sniff_cfclient(crlf) and not cfclient.sniff_cfclient(scenario.vicon)
    nanobench_like = tmp_path / "nb.csv"
    nanobench_like.write_text("t,px,py,pz\n0,1,2,3\n")
    assert not vicon.sniff_vicon(nanobench_like) and not cfclient.sniff_cfclient(nanobench_like)
    assert not vicon.sniff_vicon(tmp_path / "absent") and not cfclient.sniff_cfclient(tmp_path / "absent")


# -- clock alignment quality ----------------------------------------------------------------------------
def test_hover_gives_a_low_score_and_a_warning(tmp_path):
    flight = Scenario(tmp_path, kind="hover").read()
    assert flight.meta["clock_offset_score"] < pair_reader.MIN_CLOCK_SCORE
    assert any("clock offset ambiguous" in warning for warning in flight.meta["warnings"])
    assert flight.quality["ok"] is False and "clock offset ambiguous" in flight.quality["issues"][0]


def test_repetitive_motion_without_take_off_is_flagged_ambiguous(tmp_path):
    # An endless figure-eight matches itself one period (8 s) later as well as at the true lag.
    flight = Scenario(tmp_path, kind="airborne8").read()
    alignment = flight.meta["clock_alignment"]
    assert alignment["runner_up"] > pair_reader.MAX_RUNNER_UP_RATIO * alignment["score"]
    assert flight.quality["ok"] is False


def test_given_clock_offset_skips_the_estimate(scenario, flight):
    given_offset = scenario.read(clock_offset_s=TRUE_OFFSET_S)
    assert given_offset.meta["clock_offset_s"] == TRUE_OFFSET_S
    assert given_offset.meta["clock_offset_score"] is None
    assert given_offset.meta["clock_alignment"]["method"] == "given"
    np.testing.assert_array_equal(given_offset.p, flight.p)


def test_estimate_clock_offset_on_plain_signals():
    rng = np.random.default_rng(3)
    t = np.arange(0.0, 40.0, 0.01)
    signal = np.convolve(rng.normal(size=len(t)), np.ones(30) / 30, mode="same")
    t_other = np.sort(rng.uniform(0.0, 40.0, 3000))
    other = np.interp(t_other - 0.2345, t, signal)   # what the reference shows at t, other shows 0.2345 s later
    offset, score = clock.estimate_clock_offset(t, signal, t_other + 1000.0, other, max_lag_s=5.0)
    # t_ref = t_other_clock + offset with t_other_clock = t + 0.2345 + 1000
    assert offset == pytest.approx(-1000.2345, abs=0.002) and score > 0.9


# -- bad inputs -----------------------------------------------------------------------------------------
VICON_HEAD = "Segments\n100\n,,cf1:cf1,,,,,\nFrame,Sub Frame,RX,RY,RZ,TX,TY,TZ\n,,rad,rad,rad,mm,mm,mm\n"
GOOD_ROWS = "".join(f"{k},0,0,0,0.5,1,2,{1000 + k}\n" for k in range(1, 400))
BAD_VICON = {
    "empty": ("", "empty file"),
    "blank lines only": ("\n\n,,\n", "empty file"),
    "marker header": ("Trajectories\n100\n,,cf1:m1,,\nFrame,Sub Frame,X,Y,Z\n,,mm,mm,mm\n1,0,1,2,3\n",
                      "expected a section .* 'Frame,Sub Frame,RX,RY,RZ,TX,TY,TZ'"),
    "no rate": (VICON_HEAD.replace("100", "fast") + GOOD_ROWS, "line 2: expected the capture rate"),
    "non-numeric": (VICON_HEAD + GOOD_ROWS + "400,0,0,0,0.5,1,abc,2\n",
                    r"line 405: non-numeric value 'abc' in column TY"),
    "all occluded": (VICON_HEAD + "".join(f"{k},0,,,,,,\n" for k in range(1, 50)), "all 49 frames occluded"),
    "frames repeat": (VICON_HEAD + GOOD_ROWS + "399,0,0,0,0.5,1,2,3\n", "frames must increase"),
    "no data": (VICON_HEAD, "no data rows"),
    "unknown units": (VICON_HEAD.replace("mm,mm,mm", "in,in,in") + GOOD_ROWS, "position units .* not understood"),
    "mm without units line, undecidable": (
        VICON_HEAD.replace(",,rad,rad,rad,mm,mm,mm\n", "") + "".join(f"{k},0,0,0,0.5,20,10,30\n" for k in range(1, 50)),
        "neither metres .* nor millimetres"),
    "millimetres labelled m": (VICON_HEAD.replace("mm,mm,mm", "m,m,m") + GOOD_ROWS, "not a capture volume"),
    "fractional frame": (VICON_HEAD + "1.5,0,0,0,0,1,2,3\n", "frame number '1.5' is not an integer"),
}


CF_HEAD = "Timestamp,acc.x,acc.y,acc.z\n"
CF_ROWS = "".join(f"{10000 + 10 * k},0.01,-0.02,1.0\n" for k in range(500))
BAD_CFCLIENT = {
    "empty": ("", "empty file"),
    "wrong header": ("Timestamp,gyro.x,gyro.y,gyro.z\n1,2,3,4\n", "must hold Timestamp,acc.x,acc.y,acc.z"),
    "vicon file": (VICON_HEAD + GOOD_ROWS, "not a cfclient log"),
    "non-numeric": (CF_HEAD + CF_ROWS + "15000,0.1,x1,1.0\n", "line 502: non-numeric value 'x1' in column acc.y"),
    "m/s²": (CF_HEAD + "".join(f"{10 * k},0.1,0.2,9.81\n" for k in range(100)), "must be in g"),
    "one row": (CF_HEAD + "10,0,0,1\n", "too few rows"),
    "header only": (CF_HEAD, "no data rows"),
    "seconds of hours": (CF_HEAD + "0,0,0,1\n9000000,0,0,1\n", "Timestamp must be milliseconds"),
}


BAD_FILES = {**{f"vicon, {case}": (vicon.read_vicon_csv, *bad) for case, bad in BAD_VICON.items()},
             **{f"cfclient, {case}": (cfclient.read_cfclient_csv, *bad) for case, bad in BAD_CFCLIENT.items()}}


@pytest.mark.parametrize("case", BAD_FILES)
def test_bad_files_raise_ingest_error_naming_the_file(tmp_path, case):
    reader, content, reason = BAD_FILES[case]
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(IngestError, match=reason) as info:
        reader(path)
    assert info.value.path == str(path) and str(path) in str(info.value)


def test_no_overlap_after_alignment_names_the_cfclient_file(scenario):
    with pytest.raises(IngestError, match="no overlap with flight_vicon.csv after clock alignment") as info:
        scenario.read(clock_offset_s=TRUE_OFFSET_S + 1000.0)
    assert info.value.path == str(scenario.cfclient)


def test_log_too_short_to_align_is_an_ingest_error(tmp_path, scenario):
    short = tmp_path / "short_cfclient.csv"
    short.write_text(CF_HEAD + "".join(f"{10000 + 10 * k},0,0,1\n" for k in range(100)))   # 1 s
    with pytest.raises(IngestError, match="cannot align its clock .* too short") as info:
        pair_reader.read_pair(scenario.vicon, short)
    assert info.value.path == str(short)


def test_vicon_export_too_short_to_align_names_the_vicon_file(tmp_path, scenario):
    lines = scenario.vicon.read_text().splitlines(keepends=True)
    short = tmp_path / "short_vicon.csv"
    short.write_text("".join(lines[:len(VICON_HEAD.splitlines()) + 150]))          # 1.5 s of frames
    with pytest.raises(IngestError, match="cannot align its clock .* mocap: .* too short") as info:
        pair_reader.read_pair(short, scenario.cfclient)
    assert info.value.path == str(short)


def test_truncated_last_row_is_dropped_with_a_warning(tmp_path, scenario):
    text = scenario.vicon.read_text()
    cut = tmp_path / "cut_vicon.csv"
    cut.write_text(text[:text.rindex("\n") - 7])          # the last row loses its last digits and line end
    track = vicon.read_vicon_csv(cut)
    assert len(track.t) == (~scenario.occluded).sum() - 1
    assert any("truncated" in warning for warning in track.warnings)


# -- fuzzing --------------------------------------------------------------------------------------------
def small_vicon_text() -> str:
    t = np.arange(300) / RATE_HZ
    lines = [VICON_HEAD.rstrip("\n")]
    lines += [f"{k + 1},0,0.01,-0.02,0.3,{100 * np.sin(x):.3f},{50 * np.cos(x):.3f},{1000 + x:.3f}"
              if k % 37 else f"{k + 1},0,,,,,," for k, x in enumerate(t)]
    return "\n".join(lines) + "\n\nTrajectories\n100\n,,cf1:m1,,\nFrame,Sub Frame,X,Y,Z\n,,mm,mm,mm\n1,0,1,2,3\n"


def small_cfclient_text() -> str:
    return "Timestamp,acc.x,acc.y,acc.z,gyro.x,gyro.y,gyro.z\n" + "".join(
        f"{5000 + 10 * k + k % 3},0.0{k % 7},-0.01,0.98{k % 5},1.5,-2,0.25\n" for k in range(300))


CELLS = st.sampled_from(["", "0", "1", "-2.5", "100", "1e308", "-1e-300", "nan", "inf", "abc", "Frame",
                         "Sub Frame", "RX", "RY", "RZ", "TX", "TY", "TZ", "mm", "m", "rad", "deg", "Segments",
                         "Timestamp", "acc.x", "acc.y", "acc.z", "gyro.x", '"', "\t", "é", "\x00"])
CSV_LIKE = st.lists(st.lists(CELLS, max_size=10).map(",".join), max_size=30).map("\n".join)


def mutated(text: str):
    """Truncations, a replaced span, or random CSV-like lines spliced into a valid file."""
    return st.one_of(
        st.integers(0, len(text)).map(lambda n: text[:n]),
        st.tuples(st.integers(0, len(text)), st.integers(0, 40), st.text(max_size=20)).map(
            lambda c: text[:c[0]] + c[2] + text[c[0] + c[1]:]),
        st.tuples(st.integers(0, len(text)), CSV_LIKE).map(lambda c: text[:c[0]] + c[1] + text[c[0]:]),
    )


FUZZ = settings(max_examples=100, deadline=None, database=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def only_ingest_errors(reader, path: Path, content) -> None:
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content, encoding="utf-8", newline="")
    try:
        reader(path)
    except IngestError as err:
        assert err.path == str(path)


@FUZZ
@given(content=st.one_of(mutated(small_vicon_text()), CSV_LIKE, st.text(max_size=300), st.binary(max_size=300)))
def test_fuzzed_vicon_files_raise_nothing_but_ingest_error(tmp_path, content):
    only_ingest_errors(vicon.read_vicon_csv, tmp_path / "fuzz_vicon.csv", content)


@FUZZ
@given(content=st.one_of(mutated(small_cfclient_text()), CSV_LIKE, st.text(max_size=300), st.binary(max_size=300)))
def test_fuzzed_cfclient_files_raise_nothing_but_ingest_error(tmp_path, content):
    only_ingest_errors(cfclient.read_cfclient_csv, tmp_path / "fuzz_cfclient.csv", content)
