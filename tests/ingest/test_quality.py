"""Quality checks: each fires for its defect and stays quiet on clean data (simulated and NanoBench)."""
import dataclasses
from pathlib import Path

import numpy as np
import pytest

from learnest.ingest import quality
from learnest.ingest.align import build_flight
from learnest.ingest.formats.nanobench import reader as nanobench_reader
from learnest.ingest.frames import GRAVITY
from learnest.ingest.sim import Circle, SensorModel, Timing, simulate

NANOBENCH = Path(__file__).resolve().parents[2].parent / "shared" / "data" / "nanobench"
# Found by inspecting all 17 flights (see ingest/formats/nanobench/reader.py and the report): the onboard link of this
# one died at 31.3 s while the vehicle flew on until 38.2 s, so 6.9 s of flight have no accelerometer.
BAD_NANOBENCH_FLIGHTS = {"B2_circle_medium_rep3"}

RATE = 100.0


# -- a simulated flight, and defects made by breaking it ------------------------------------------------
# The simulator (ingest.sim) flies clean physics only; every defect below is made by breaking its raw
# streams (or the Flight built from them) the way a broken logger, exporter or unit mix-up would.
TIMING = Timing(sit_before_s=2.0, takeoff_s=2.0, hover_s=0.5, land_s=2.0, sit_after_s=2.0)   # take-off at 2 s
# Mocap and accelerometer both at 100 Hz, so sample k of either stream is at k / 100 s; 0.005 g of
# accelerometer noise, like a real Crazyflie.
SENSORS = SensorModel(imu_rate_hz=RATE, acc_noise_g=0.005)


def raw_circle_flight(duration=30.0, radius=1.0, speed=1.0, seed=0):
    """Mocap + body-frame accelerometer (g) of a simulated take-off, circle (1 rad/s by default; speed 0 is
    a hover), landing: the raw streams `build_flight` takes."""
    circling = duration - (TIMING.sit_before_s + TIMING.takeoff_s + 2 * TIMING.hover_s + TIMING.land_s
                           + TIMING.sit_after_s)
    sim = simulate(Circle(radius=radius, speed=speed, altitude=1.0, duration_s=circling, ramp_s=3.0),
                   timing=TIMING, sensors=SENSORS, seed=seed)
    return {"t_mocap": sim.mocap.t, "p": sim.mocap.p, "quat": sim.mocap.quat, "t_acc": sim.imu.t,
            "acc_body_g": sim.imu.acc_g}


def build(raw, **changes):
    return build_flight("synthetic", **{**raw, **changes}, rate_hz=RATE)


@pytest.fixture(scope="module")
def raw():
    return raw_circle_flight()


@pytest.fixture(scope="module")
def clean(raw):
    return build(raw)


def issues_of(flight):
    return quality.assess(flight)["issues"]


def assert_flags(flight, *words):
    issues = issues_of(flight)
    assert any(all(w in issue for w in words) for issue in issues), issues


# -- clean data -----------------------------------------------------------------------------------------
def test_clean_simulated_flight_passes(clean):
    result = quality.assess(clean)
    assert result == {"ok": True, "issues": []}
    assert quality.acc_mocap_correlation(clean) > 0.95


# -- each defect ----------------------------------------------------------------------------------------
def test_acc_in_ms2_read_as_g(raw):
    flight = build(raw, acc_body_g=raw["acc_body_g"] * GRAVITY)
    assert_flags(flight, "m/s² read as g")


def test_implausible_mean_acc(raw):
    flight = build(raw, acc_body_g=raw["acc_body_g"] * 0.6)   # e.g. wrong scale factor
    assert_flags(flight, "implausible accelerometer", "0.6")


def test_impossible_values_on_some_rows_fail_the_flight(clean):
    """pz = 1e308 on every 7th row: the median looks fine, the rows do not."""
    from learnest.ingest.flight import Flight

    p = clean.p.copy()
    p[::7, 2] = 1e308
    flight = Flight(clean.t, p, clean.a_meas, clean.quat, clean.channels, dict(clean.meta))
    assert_flags(flight, "physically impossible positions", f"{len(p[::7])} sample(s)", "1e+308")
    a = clean.a_meas.copy()
    a[100, 0] = 400.0                                  # 41 g
    flight = Flight(clean.t, clean.p, a, clean.quat, clean.channels, dict(clean.meta))
    assert_flags(flight, "physically impossible accelerations", "1 sample(s)")


def test_saturation_repeated_rail(raw):
    acc = raw["acc_body_g"].copy()
    acc[1500:1506, 0] = 2.5           # stuck at a ±2.5 g rail for 60 ms
    assert_flags(build(raw, acc_body_g=acc), "saturation on x", "2.50 g")


def test_saturation_hard_rail(raw):
    acc = raw["acc_body_g"].copy()
    acc[1500, 2] = -16.0
    assert_flags(build(raw, acc_body_g=acc), "saturation on z")


def test_spike(raw):
    acc = raw["acc_body_g"].copy()
    acc[1400, 1] += 6.0
    flight = build(raw, acc_body_g=acc)
    assert_flags(flight, "spike")
    assert not any("saturation" in issue for issue in issues_of(flight))


@pytest.mark.parametrize("stream", ["acc", "mocap"])
def test_long_gap_found_from_interpolated_stretch(raw, stream):
    t_key, value_keys = ("t_acc", ["acc_body_g"]) if stream == "acc" else ("t_mocap", ["p", "quat"])
    keep = ~((raw[t_key] > 15.0) & (raw[t_key] < 16.2))        # 1.2 s of samples lost mid-air
    flight = build(raw, **{t_key: raw[t_key][keep]}, **{k: raw[k][keep] for k in value_keys})
    assert_flags(flight, f"{stream} stream missing for 1.2")


def test_many_short_gaps_as_a_fraction(raw):
    keep = np.arange(len(raw["t_acc"])) % 10 < 3                 # 7 of every 10 samples lost
    flight = build(raw, t_acc=raw["t_acc"][keep], acc_body_g=raw["acc_body_g"][keep])
    assert_flags(flight, "acc:", "fall into gaps")


def test_gaps_while_sitting_on_the_ground_do_not_count_against_the_flight(raw):
    keep = ~(raw["t_mocap"] < 1.8)                               # mocap starts late, before take-off at 2 s
    keep[:1] = True                                              # one early sample: the grid still starts at 0
    flight = build(raw, t_mocap=raw["t_mocap"][keep], p=raw["p"][keep], quat=raw["quat"][keep])
    assert flight.meta["gaps"]["mocap_samples_in_gaps"] == 0     # the cut removed the ground time
    assert issues_of(flight) == issues_of(build(raw))


def test_gap_reported_by_adapter_meta(clean):
    flight = dataclasses.replace(clean, meta={**clean.meta, "gaps": {**clean.meta["gaps"],
                                                                    "acc_longest_gap_airborne_s": 6.9}})
    assert_flags(flight, "acc stream missing for 6.90 s")


def test_frozen_mocap_while_accelerometer_moves(raw):
    p = raw["p"].copy()
    p[1200:1230] = p[1200]             # exporter holds the last pose for 0.3 s during an occlusion
    assert_flags(build(raw, p=p), "mocap position frozen", "0.30 s")


def test_frozen_mocap_needs_a_live_accelerometer(clean):
    p, acc = clean.p.copy(), clean.channels["acc_body"].copy()
    p[1000:1030], acc[1000:1030] = p[1000], acc[1000]             # whole recorder stalled
    flight = dataclasses.replace(clean, p=p, channels={**clean.channels, "acc_body": acc})
    assert not any("frozen" in issue for issue in issues_of(flight))


def test_non_monotonic_time(clean):
    t = clean.t.copy()
    t[500] = t[498]
    assert_flags(dataclasses.replace(clean, t=t), "not strictly increasing")


def test_too_short(clean):
    assert_flags(clean.slice(0, 300), "too short")


def test_positions_in_millimetres(clean):
    assert_flags(dataclasses.replace(clean, p=clean.p * 1000.0), "millimetres")


def test_axes_swapped_disagree_with_mocap(clean):
    swapped = dataclasses.replace(clean, a_meas=clean.a_meas[:, [1, 0, 2]])
    assert_flags(swapped, "disagree")


def test_attitude_misaligned_in_time_disagrees_with_mocap(raw):
    # On a quadrotor the horizontal a_meas comes from tilting the thrust, i.e. from the mocap attitude.
    flight = build(raw, quat=np.roll(raw["quat"], 160, axis=0))   # 1.6 s ≈ a quarter turn at 1 rad/s
    assert_flags(flight, "disagree", "correlation")


def test_quaternion_scalar_first_mixup_disagrees_with_mocap(raw):
    flight = build(raw, quat=raw["quat"][:, [3, 0, 1, 2]])        # [w, x, y, z] passed as [x, y, z, w]
    assert_flags(flight, "disagree", "mean a_meas")


def test_gravity_not_removed_is_a_mean_offset(clean):
    flight = dataclasses.replace(clean, a_meas=clean.a_meas + np.array([0.0, 0.0, GRAVITY]))
    assert_flags(flight, "disagree", "mean a_meas")


def test_hover_is_not_judged_by_correlation(raw):
    hover = raw_circle_flight(speed=0.0)
    assert quality.acc_mocap_correlation(build(hover)) is None
    assert quality.assess(build(hover))["ok"]


def test_interpolated_stretch_measure():
    rng = np.random.default_rng(1)
    noisy = rng.normal(size=(200, 3))
    assert quality.interpolated_stretch_s(noisy, 0.01) == 0.0
    noisy[50:71] = np.linspace(noisy[50], noisy[70], 21)          # 20 intervals drawn as a straight line
    assert quality.interpolated_stretch_s(noisy, 0.01) == pytest.approx(0.20)


# -- real data ------------------------------------------------------------------------------------------
needs_data = pytest.mark.data  # skipped by conftest.py when ../shared/data is absent


@needs_data
def test_quality_flags_exactly_the_bad_nanobench_flights():
    verdicts = {path.stem: quality.assess(nanobench_reader.read(path)) for path in sorted(NANOBENCH.glob("*.csv"))}
    assert len(verdicts) == 17
    flagged = {name for name, verdict in verdicts.items() if not verdict["ok"]}
    assert flagged == BAD_NANOBENCH_FLIGHTS, {name: verdicts[name]["issues"] for name in flagged}
    assert any("acc stream missing for 6.9" in issue for issue in verdicts["B2_circle_medium_rep3"]["issues"])
