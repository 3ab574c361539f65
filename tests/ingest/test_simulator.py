"""ingest.sim: every format written and read back against the simulator's truth, the sensor effects,
the trajectories' geometry, the take-off/landing cut, and the bundled sample_logs/."""
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from learnest.ingest import read_flights
from learnest.ingest.align import anti_alias
from learnest.ingest.formats.nanobench import reader as nanobench_reader
from learnest.ingest.formats.nanobench import writer as nanobench_writer
from learnest.ingest.formats.vicon_cfclient.reader import read_pair
from learnest.ingest.frames import GRAVITY
from learnest.ingest.sim import (
    FORMATS,
    Circle,
    Figure8,
    RandomWaypoints,
    SensorModel,
    sim_times,
    simulate,
    write_flight,
)
from learnest.ingest.sim.export import CFCLIENT_CLOCK_OFFSET_S
from learnest.ingest.sim.samples import REAL_FLIGHTS, REAL_FLIGHTS_README, SAMPLE_FLIGHTS, sample_flight

SAMPLE_LOGS = Path(__file__).resolve().parents[2] / "sample_logs"
MOCAP_RATE_HZ = 100.0
CIRCLE = dict(radius=0.5, speed=0.6, altitude=1.0, duration_s=6.0)

# a_meas vs the true world acceleration, effects and noise off: what remains is each format's quantisation.
ACC_TOLERANCE_M_S2 = {
    # t is Unix time with 9 decimals: float64 resolves 2.4e-7 s at 1.7e9 s, so rows and the grid disagree
    # by that much; times |jerk| (< 40 m/s³ here) ≈ 1e-5.  The 9 printed decimals of acc (g) and the
    # quaternion add < 1e-8.
    "nanobench": 1e-5,
    # float32 acc (g) and locSrv quaternion: 6e-8 relative on 1 g and on the rotation ≈ 1e-6 m/s².
    "usd": 1e-5,
    "usd-v1": 1e-5,
    # float64 throughout (ROS Imu carries m/s²: one multiplication and division by g); the IMU runs at 500 Hz,
    # so the reader low-passes it in the body frame (anti-aliasing) while the reference below is low-passed in
    # the world frame: the attitude turns during the filter's ~20 ms, which leaves ~4e-6 m/s².
    "mcap-ros2": 1e-5,
    "mcap-json": 1e-5,
    # cfclient (with locSrv): acc printed with repr (float64, exact), every 5th 500 Hz sample on the mocap frames.
    "cfclient": 1e-9,
    # vicon+cfclient: see test_vicon_cfclient_acceleration_follows_the_clock_offset_error.
}


def mocap_index(flight, fmt):
    """The mocap sample (simulation time · 100 Hz) every Flight row lies on, and how far off it is (s)."""
    t = sim_times(flight, fmt)
    index = np.round(t * MOCAP_RATE_HZ).astype(int)
    return index, np.abs(t - index / MOCAP_RATE_HZ)


def rotation_angle(q1, q2):
    return (Rotation.from_quat(q1).inv() * Rotation.from_quat(q2)).magnitude()


@pytest.fixture(scope="module")
def ideal_sim():
    """No sensor noise or effects; yaw turning, so that body and world axes differ."""
    return simulate(Circle(**CIRCLE), sensors=SensorModel.ideal(), yaw_rad=0.5, yaw_rate=0.3, seed=1)


@pytest.fixture(scope="module")
def read_back(ideal_sim, tmp_path_factory):
    directory = tmp_path_factory.mktemp("formats")
    flights = {}
    for fmt in FORMATS:
        files = write_flight(ideal_sim, fmt, directory, fmt.replace("+", "_"))
        # the ideal accelerometer has no low-pass of its own: none is declared to the clock alignment
        (flights[fmt],) = [read_pair(*files, accel_lowpass=None)] if fmt == "vicon+cfclient" else read_flights(files)
    return flights


# -- every format against the truth ---------------------------------------------------------------------
@pytest.mark.parametrize("fmt", FORMATS)
def test_position_and_attitude_equal_the_truth_at_mocap_samples(fmt, ideal_sim, read_back):
    flight = read_back[fmt]
    index, off_grid = mocap_index(flight, fmt)
    assert off_grid.max() < 1e-6          # the 100 Hz grid lies on the mocap frames
    truth = ideal_sim.mocap.truth
    np.testing.assert_allclose(flight.p, truth.p[index], rtol=0, atol=1e-6)
    assert rotation_angle(flight.quat, truth.quat[index]).max() < 1e-6


@pytest.mark.parametrize("fmt", sorted(ACC_TOLERANCE_M_S2))
def test_a_meas_equals_the_true_world_acceleration(fmt, ideal_sim, read_back):
    """Against the truth as the grid can hold it: where a format logs the IMU faster than the grid (uSD, MCAP:
    500 Hz), band-limited by the reader's anti-alias low-pass (the simulated closed loop has content above the
    grid's 50 Hz Nyquist: 0.0094 m/s² here, which plain decimation would fold into the band)."""
    flight = read_back[fmt]
    t = sim_times(flight, fmt)
    # NanoBench: acc on the mocap rows; cfclient: every 5th IMU sample (100 Hz, on the mocap frames)
    stamps = ideal_sim.mocap.t if fmt in ("nanobench", "cfclient") else ideal_sim.imu.t
    t_source, a_source, _ = anti_alias(stamps, ideal_sim.truth.at(stamps).a, flight.rate_hz)
    reference = np.column_stack([np.interp(t, t_source, a_source[:, j]) for j in range(3)])
    error = np.abs(flight.a_meas - reference).max()
    assert error < ACC_TOLERANCE_M_S2[fmt], f"{fmt}: {error:.3g} m/s²"


def test_vicon_cfclient_clock_offset_is_recovered_within_one_sample(read_back):
    flight = read_back["vicon+cfclient"]
    assert flight.meta["clock_offset_s"] == pytest.approx(CFCLIENT_CLOCK_OFFSET_S, abs=1.0 / MOCAP_RATE_HZ)


def test_vicon_cfclient_acceleration_follows_the_clock_offset_error(ideal_sim, read_back):
    """The estimated offset misplaces every cfclient sample by δ = true − estimated, so a_meas(t) is the
    truth at t + δ, linearly interpolated between the 100 Hz log rows (h = 10 ms): within h²/8·|a''| of the
    shifted truth, and within |jerk|·|δ| more of the truth itself (both bounds taken over the flight)."""
    flight = read_back["vicon+cfclient"]
    delta = CFCLIENT_CLOCK_OFFSET_S - flight.meta["clock_offset_s"]
    t = sim_times(flight, "vicon+cfclient")
    truth = ideal_sim.truth
    near = (truth.t > t[0] - 0.05) & (truth.t < t[-1] + 0.05)
    a, h = truth.a[near], 10
    interpolation = np.abs(a[2 * h:] - 2 * a[h:-h] + a[:-2 * h]).max() / 8
    jerk = np.abs(np.diff(a, axis=0)).max() * 1000.0
    assert np.abs(flight.a_meas - truth.at(t + delta).a).max() < interpolation + 1e-5
    assert np.abs(flight.a_meas - truth.at(t).a).max() < interpolation + jerk * abs(delta) + 1e-5


@pytest.mark.parametrize("fmt", FORMATS)
def test_the_cut_keeps_the_flying_part(fmt, ideal_sim, read_back):
    t = sim_times(read_back[fmt], fmt)
    phases = ideal_sim.phases
    assert phases.takeoff < t[0] <= phases.fly and phases.fly_end <= t[-1] < phases.touchdown


# -- sensor effects -------------------------------------------------------------------------------------
def imu_error_m_s2(sim):
    """Accelerometer minus the ideal body specific force at its stamps (m/s²)."""
    return sim.imu.acc_g * GRAVITY - sim.imu.truth.specific_force_body()


def best_lag_s(t, signal, t_truth, truth_signal, lags_s):
    """Lag (s) where the signal stamped t correlates best with the truth delayed by it."""
    scores = []
    for lag in lags_s:
        delayed = np.column_stack([np.interp(t - lag, t_truth, truth_signal[:, j])
                                   for j in range(truth_signal.shape[1])])
        a, b = signal - signal.mean(0), delayed - delayed.mean(0)
        scores.append(np.sum(a * b) / np.sqrt(np.sum(a * a) * np.sum(b * b)))
    return lags_s[int(np.argmax(scores))]


def test_bias_is_the_mean_error():
    bias = np.array([0.15, -0.1, 0.2])
    sim = simulate(Circle(**CIRCLE), sensors=SensorModel(bias=tuple(bias)), seed=2)
    error = imu_error_m_s2(sim)
    standard_error = SensorModel().acc_noise_g * GRAVITY / np.sqrt(len(error))
    np.testing.assert_allclose(error.mean(axis=0), bias, atol=5 * standard_error)
    assert error.std(axis=0) == pytest.approx([SensorModel().acc_noise_g * GRAVITY] * 3, rel=0.05)


def test_scale_multiplies_each_axis():
    scale = (1.03, 0.97, 1.05)
    sim = simulate(Circle(**CIRCLE), sensors=SensorModel.ideal(scale=scale), yaw_rad=0.4, yaw_rate=0.5)
    truth = sim.imu.truth.specific_force_body()
    slopes = np.sum(sim.imu.acc_g * GRAVITY * truth, axis=0) / np.sum(truth * truth, axis=0)
    np.testing.assert_allclose(slopes, scale, rtol=1e-9)


def test_delay_is_the_cross_correlation_peak():
    delay = 0.023
    sim = simulate(Circle(**CIRCLE), sensors=SensorModel.ideal(delay_s=delay), yaw_rad=0.4, yaw_rate=0.5)
    lags = np.arange(0.0, 0.06, 0.001)
    truth = sim.truth
    assert best_lag_s(sim.imu.t, sim.imu.acc_g, truth.t, truth.specific_force_body(), lags) == pytest.approx(delay)
    assert best_lag_s(sim.imu.t, sim.imu.gyro, truth.t, truth.omega, lags) == pytest.approx(delay)


def test_lowpass_lags_a_slow_signal_by_its_time_constant():
    """A first-order low-pass delays a sinusoid of ω ≪ ωc by atan(ω/ωc)/ω ≈ 1/ωc (53 ms at 3 Hz); the
    body-frame circle acceleration (constant yaw) is such a sinusoid at ω = 1.2 rad/s."""
    cutoff = 3.0
    sim = simulate(Circle(**CIRCLE), sensors=SensorModel.ideal(lowpass_hz=cutoff))
    steady = (sim.imu.t > sim.phases.fly + 2.0) & (sim.imu.t < sim.phases.fly_end - 2.0)
    omega, omega_c = CIRCLE["speed"] / CIRCLE["radius"], 2 * np.pi * cutoff
    lags = np.arange(0.0, 0.1, 0.001)
    lag = best_lag_s(sim.imu.t[steady], sim.imu.acc_g[steady, :2], sim.truth.t,
                     sim.truth.specific_force_body()[:, :2], lags)
    assert lag == pytest.approx(np.arctan(omega / omega_c) / omega, abs=0.002)


def test_misalignment_tilts_the_gravity_seen_at_rest():
    roll, pitch = 0.03, -0.02
    sim = simulate(Circle(**CIRCLE), sensors=SensorModel.ideal(misalignment=(roll, pitch)))
    fx, fy, fz = sim.imu.acc_g[0]             # on the ground, level, before take-off
    assert np.arctan2(fy, fz) == pytest.approx(roll, abs=1e-12)
    assert np.arctan2(-fx, np.hypot(fy, fz)) == pytest.approx(pitch, abs=1e-12)
    body = Rotation.from_euler("ZYX", [0.0, pitch, roll]).apply(sim.imu.acc_g * GRAVITY)
    np.testing.assert_allclose(body, sim.imu.truth.specific_force_body(), atol=1e-12)


def test_ideal_gyro_reads_the_true_body_rates(ideal_sim):
    np.testing.assert_allclose(ideal_sim.imu.gyro, ideal_sim.imu.truth.omega, atol=1e-12)


# -- the simulated truth and the trajectories -------------------------------------------------------------
def test_truth_is_self_consistent(ideal_sim):
    """a is the second difference of p (semi-implicit Euler) and integrating omega gives the attitudes."""
    truth, n = ideal_sim.truth, int(ideal_sim.phases.touchdown * 1000)
    np.testing.assert_allclose(np.diff(truth.p[:n], 2, axis=0) * 1e6, truth.a[1:n - 1], atol=1e-6)
    stepped = Rotation.from_quat(truth.quat[:n - 1]) * Rotation.from_rotvec(truth.omega[:n - 1] / 1000.0)
    assert rotation_angle(stepped.as_quat(), truth.quat[1:n]).max() < 1e-9


def test_circle_has_the_requested_radius_and_speed(ideal_sim):
    """Reference exact; the flown path within the tracking error (drag 0.2 m/s² at 0.6 m/s against the
    PD gains leaves a few mm, mostly a lag along the track)."""
    truth, phases = ideal_sim.truth, ideal_sim.phases
    ramp = ideal_sim.trajectory.ramp_s
    steady = (truth.t > phases.fly + ramp + 0.5) & (truth.t < phases.fly_end - ramp)
    reference = ideal_sim.reference
    np.testing.assert_allclose(np.linalg.norm(reference.p[steady, :2], axis=1), CIRCLE["radius"], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(reference.v[steady], axis=1), CIRCLE["speed"], atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(truth.p[steady, :2], axis=1), CIRCLE["radius"], atol=0.01)
    assert np.linalg.norm(truth.v[steady], axis=1).mean() == pytest.approx(CIRCLE["speed"], rel=0.01)
    np.testing.assert_allclose(truth.p[steady, 2], CIRCLE["altitude"], atol=0.005)


def test_figure8_has_the_requested_size_and_period():
    size, period = 0.6, 4.0
    sim = simulate(Figure8(size=size, period=period, duration_s=3 + 2 * period), sensors=SensorModel.ideal())
    ref, truth = sim.reference, sim.truth
    steady = np.flatnonzero((ref.t > sim.phases.fly + 1.5) & (ref.t < sim.phases.fly_end - 1.5 - period))
    np.testing.assert_allclose(ref.p[steady + int(period * 1000)], ref.p[steady], atol=1e-12)
    lap = np.flatnonzero((truth.t > sim.phases.fly + 1.5) & (truth.t < sim.phases.fly + 1.5 + period))
    x, y = truth.p[lap, 0], truth.p[lap, 1]
    assert np.ptp(x) == pytest.approx(2 * size, abs=0.02) and np.ptp(y) == pytest.approx(size, abs=0.02)


def test_random_waypoints_are_seeded_in_the_box_and_visited():
    box = ((-1.0, 1.0), (-0.5, 0.5), (0.5, 1.5))
    trajectory = RandomWaypoints(count=4, box=box, speed=0.5, seed=11)
    assert np.array_equal(trajectory.points, RandomWaypoints(count=4, box=box, speed=0.5, seed=11).points)
    assert not np.allclose(trajectory.points, RandomWaypoints(count=4, box=box, speed=0.5, seed=12).points)
    low, high = np.array(box).T
    assert np.all((trajectory.points >= low) & (trajectory.points <= high))
    sim = simulate(trajectory, sensors=SensorModel.ideal())
    distances = np.linalg.norm(sim.truth.p[:, None, :] - trajectory.points[None], axis=2).min(axis=0)
    assert distances.max() < 0.03


def test_simulation_is_deterministic():
    first, second = (simulate(Circle(**CIRCLE), seed=4) for _ in range(2))
    assert np.array_equal(first.mocap.p, second.mocap.p) and np.array_equal(first.imu.acc_g, second.imu.acc_g)
    assert not np.array_equal(first.imu.acc_g, simulate(Circle(**CIRCLE), seed=5).imu.acc_g)


def test_flight_rests_on_the_ground_before_and_after(ideal_sim):
    truth, phases = ideal_sim.truth, ideal_sim.phases
    before, after = truth.t < phases.takeoff, truth.t >= phases.touchdown
    assert np.all(truth.v[before] == 0) and np.all(truth.v[after] == 0) and np.all(truth.a[after] == 0)
    assert np.abs(truth.p[after, 2]).max() < 0.005 and truth.p[before, 2].max() == 0


# -- the NanoBench writer ---------------------------------------------------------------------------------
def test_nanobench_write_layout_and_metadata(ideal_sim, tmp_path):
    path = tmp_path / "flight.csv"
    mocap, imu, n = ideal_sim.mocap, ideal_sim.imu, len(ideal_sim.mocap.t)
    on_mocap = np.searchsorted(imu.t, mocap.t)
    nanobench_writer.write(path, 1.7e9 + mocap.t, mocap.p, mocap.quat, imu.acc_g[on_mocap], gyro=imu.gyro[on_mocap],
                    vbat=np.full(n, 4.0), metadata={"crazyflie_id": "SIM"})
    header = path.read_text().splitlines()[0].split(",")
    assert header == ["t", *nanobench_reader.MOCAP_COLUMNS, *nanobench_reader.ACC_COLUMNS, "imu_gyro_x", "imu_gyro_y",
                      "imu_gyro_z", "pwr_pm_vbat"]
    flight = nanobench_reader.read(path)
    assert flight.meta["vehicle"] == "SIM" and {"gyro", "vbat"} <= set(flight.channels)
    with pytest.raises(ValueError, match="acc"):
        nanobench_writer.write(path, mocap.t, mocap.p, mocap.quat, np.zeros((n - 1, 3)))


# -- sample_logs/ -----------------------------------------------------------------------------------------
def sample_files():
    """Every file of sample_logs/ but its README (logs, NanoBench sidecars, the NanoBench licence)."""
    files = sorted(path for path in SAMPLE_LOGS.iterdir() if path.name != "README.md")
    if not files:
        pytest.skip("sample_logs/ is empty: run python -m learnest.ingest.sim.samples sample_logs")
    return files


def is_real(path) -> bool:
    return path.name.split(".")[0].removesuffix("_metadata") in REAL_FLIGHTS or path.name == "LICENSE-nanobench.txt"


def test_sample_logs_are_small_documented_and_clean():
    files = sample_files()
    real = [path for path in files if is_real(path)]
    assert sum(path.stat().st_size for path in files if path not in real) < 5e6
    assert sum(path.stat().st_size for path in real) < 1.2e7                # a few MB of real flights
    readme = (SAMPLE_LOGS / "README.md").read_text(encoding="utf-8")
    assert all(f"`{path.name}`" in readme for path in files)
    assert readme.startswith(REAL_FLIGHTS_README)                            # what make_sample_logs writes
    assert "BSD 3-Clause" in (SAMPLE_LOGS / "LICENSE-nanobench.txt").read_text() and "arXiv:2603.09908" in readme
    flights = read_flights([path for path in files if path.suffix in (".csv", ".mcap", "")
                            and path.name != "LICENSE-nanobench.txt"])
    assert len(flights) == len(SAMPLE_FLIGHTS) + len(REAL_FLIGHTS)
    assert all(flight.quality["ok"] for flight in flights), [f.quality for f in flights]
    real_flights = [f for f in flights if f.name in REAL_FLIGHTS]
    assert [f.meta["vehicle"] for f in real_flights] == ["CF_01"] * len(REAL_FLIGHTS)   # the sidecars were read
    circles = [f for f in flights if f.meta["adapter"] == "nanobench" and f.name.startswith("circle_rep")]
    assert len(circles) >= 4 and {f.meta["adapter"] for f in flights} >= {"nanobench", "usd", "vicon+cfclient",
                                                                        "mcap-ros2", "mcap-json"}


def test_sample_logs_match_the_code():
    """circle_rep1.csv is what sample_flight('circle_rep1') writes (the logs are up to date)."""
    sample_files()
    written = np.loadtxt(SAMPLE_LOGS / "circle_rep1.csv", delimiter=",", skiprows=1)
    sim = sample_flight("circle_rep1")
    np.testing.assert_allclose(written[:, 1:4], sim.mocap.p, atol=1e-9)
    np.testing.assert_allclose(written[:, 0] - written[0, 0], sim.mocap.t, atol=1e-6)
