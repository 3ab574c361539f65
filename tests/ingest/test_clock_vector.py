"""Clock alignment from the specific-force vector, against the simulator's truth with a known clock offset.

A Vicon export and a cfclient log of one simulated flight are written on two clocks 40 ms apart (on top of the
cfclient's boot time and the Vicon's later start); the accelerometer goes through the Crazyflie firmware's
2-pole 30 Hz low-pass on its 1 kHz samples before it is logged at 100 Hz, as a real cfclient log's acc.x/y/z.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from learnest.ingest import clock
from learnest.ingest.formats.vicon_cfclient import reader as pair_reader
from learnest.ingest.formats.vicon_cfclient.writer import write_cfclient_csv, write_vicon_csv
from learnest.ingest.frames import GRAVITY
from learnest.ingest.sim import simulate
from learnest.ingest.sim.trajectories import Circle, Figure8, Timing

BOOT_S = 41.237                 # the cfclient log stamps ms since the Crazyflie booted
EXTRA_OFFSET_S = 0.040          # the clocks' offset beyond the boot time: what the alignment must find
TRUE_OFFSET_S = -BOOT_S + EXTRA_OFFSET_S   # t_vicon = t_cfclient + TRUE_OFFSET_S (the Vicon counts from sim 0)
MOCAP_SAMPLE_S = 0.01           # Vicon at 100 Hz
ACC_NOISE_G = 0.02              # per axis, white, at the log's 100 Hz
MOCAP_NOISE_M = 5e-4


def logged_pair(sim, start_s: float, stop_s: float, seed: int = 0):
    """(t_vicon (N,) s, p (N, 3) m, quat (N, 4), t_cfclient (M,) s, acc (M, 3) g) of the flight between
    ``start_s`` and ``stop_s`` (simulation time): the mocap from the truth with noise, the accelerometer through
    the firmware's filter at 1 kHz, sampled at 100 Hz 3 ms after the Vicon frames, with noise."""
    rng = np.random.default_rng(seed)
    truth = sim.truth                                            # 1 kHz
    body = Rotation.from_quat(truth.quat).inv().apply(truth.a + [0.0, 0.0, GRAVITY]) / GRAVITY
    lowpass = clock.CRAZYFLIE_ACCEL_LOWPASS
    filtered = lfilter(*lowpass.coefficients(), body - body[0], axis=0) + body[0]
    frames = np.round(np.arange(start_s, stop_s, MOCAP_SAMPLE_S) * 1000).astype(int)
    rows = frames[:-1] + 3
    p = truth.p[frames] + rng.normal(0.0, MOCAP_NOISE_M, (len(frames), 3))
    acc = filtered[rows] + rng.normal(0.0, ACC_NOISE_G, (len(rows), 3))
    return truth.t[frames], p, truth.quat[frames], truth.t[rows] - TRUE_OFFSET_S, acc


def write_pair(directory, stem: str, sim, start_s: float, stop_s: float, seed: int = 0):
    t_vicon, p, quat, t_cf, acc = logged_pair(sim, start_s, stop_s, seed)
    vicon, cfclient = directory / f"{stem}_vicon.csv", directory / f"{stem}_cfclient.csv"
    write_vicon_csv(vicon, t_vicon - t_vicon[0], p, quat, rate_hz=100.0)
    write_cfclient_csv(cfclient, t_cf, acc)
    return vicon, cfclient, t_vicon[0]


@pytest.fixture(scope="module")
def circle():
    """40 s of a 0.5-m circle at 1.5 m/s, recorded in the air from the hover before the speed ramps up to the
    hover after it ramps down: no take-off or landing to time the clocks by."""
    sim = simulate(Circle(radius=0.5, speed=1.5, duration_s=40.0), timing=Timing(), seed=3)
    return sim, sim.phases.fly - 0.3, sim.phases.fly_end + 0.3


def test_a_constant_speed_circle_is_timed_by_the_vector_where_the_magnitude_fails(circle):
    """The magnitude barely changes on the circle (its centripetal acceleration is constant): its estimate is off
    by more than a mocap sample and its own spread says it cannot tell.  The body-frame vector (the rotor drag
    turning with the velocity) finds the 40 ms within a sample and pins it."""
    sim, start, stop = circle
    t_vicon, p, quat, t_cf, acc = logged_pair(sim, start, stop)
    kwargs = {"accel_lowpass": clock.CRAZYFLIE_ACCEL_LOWPASS}
    vector = clock.align_mocap_and_accelerometer(t_vicon, p, t_cf, acc, quat=quat, **kwargs)
    magnitude = clock.align_mocap_and_accelerometer(t_vicon, p, t_cf, acc, **kwargs)     # no attitude: fallback
    assert (vector.signal, magnitude.signal) == ("specific-force vector", "specific-force magnitude")
    assert magnitude.note == "the mocap has no attitude"
    vector_error, magnitude_error = abs(vector.offset_s - TRUE_OFFSET_S), abs(magnitude.offset_s - TRUE_OFFSET_S)
    assert vector_error < MOCAP_SAMPLE_S, vector
    assert magnitude_error > MOCAP_SAMPLE_S and magnitude_error > 2 * vector_error, magnitude
    assert vector.pins_one_sample(MOCAP_SAMPLE_S) and not magnitude.pins_one_sample(MOCAP_SAMPLE_S)
    assert vector.uncertainty_s < magnitude.uncertainty_s / 2
    assert vector.runner_up < pair_reader.MAX_RUNNER_UP_RATIO * vector.score


def test_the_circle_read_as_a_vicon_and_cfclient_pair_is_aligned_within_a_sample(circle, tmp_path):
    """The files, read as a user's: the offset within one mocap sample, its uncertainty in the metadata, no
    warning."""
    sim, start, stop = circle
    vicon, cfclient, vicon_start = write_pair(tmp_path, "circle", sim, start, stop)
    flight = pair_reader.read_pair(vicon, cfclient, cut=False)
    expected = TRUE_OFFSET_S - vicon_start                       # the Vicon export counts from its first frame
    assert flight.meta["clock_offset_s"] == pytest.approx(expected, abs=MOCAP_SAMPLE_S)
    alignment = flight.meta["clock_alignment"]
    assert alignment["signal"] == "specific-force vector" and "body frame" in alignment["method"]
    assert 0 < flight.meta["clock_offset_uncertainty_s"] == alignment["uncertainty_s"] <= MOCAP_SAMPLE_S / 2
    assert flight.meta["warnings"] == [] and "quality" not in flight.meta


def test_a_hover_cannot_pin_the_offset_and_the_flight_is_flagged_by_name(tmp_path):
    """20 s of hovering still: nothing times the clocks; the quality flag names the two files and says why."""
    sim = simulate(Figure8(size=0.0, duration_s=24.0), timing=Timing(), seed=5)
    vicon, cfclient, _ = write_pair(tmp_path, "hover", sim, sim.phases.fly + 2.0, sim.phases.fly_end - 2.0)
    flight = pair_reader.read_pair(vicon, cfclient, cut=False)
    alignment = flight.meta["clock_alignment"]
    assert alignment["signal"] == "specific-force vector"
    assert not flight.meta["clock_offset_uncertainty_s"] <= MOCAP_SAMPLE_S
    issue, = flight.meta["quality"]["issues"]
    assert issue.startswith("clock offset") and "(hover_vicon.csv + hover_cfclient.csv)" in issue
    assert issue in flight.meta["warnings"]


def test_an_upside_down_mocap_object_falls_back_to_the_magnitude(circle):
    """A mocap object whose z axis points down (axes the IMU's do not share): the vector cannot be compared, the
    magnitude stands in, and the alignment says why."""
    sim, start, stop = circle
    t_vicon, p, quat, t_cf, acc = logged_pair(sim, start, stop)
    flipped = (Rotation.from_quat(quat) * Rotation.from_euler("x", np.pi)).as_quat()
    alignment = clock.align_mocap_and_accelerometer(t_vicon, p, t_cf, acc, quat=flipped)
    assert alignment.signal == "specific-force magnitude"
    assert "disagree by 180°" in alignment.note
