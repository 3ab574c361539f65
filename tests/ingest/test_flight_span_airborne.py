"""Recordings airborne from their first to their last sample, as uSD logs of real flights hold them: the motors
(and the rpm deck's rotor speeds) run throughout and the accelerometer never rests, so the vehicle never stood
on anything and the whole recording is the flight, whatever the height does.

The two simulated logs reproduce real uSD logs the height rule alone cut to nothing: a 51-s hover at 0.5 m
(a brushed Crazyflie with an rpm deck) that climbs 0.16 m near its end, and a 6.3-s flight at 0.47-0.59 m (a
Crazyflie Brushless) that sinks 0.12 m below its starting height.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from learnest.ingest import read_flights
from learnest.ingest.align import flying_window
from learnest.ingest.formats.crazyflie_usd import writer as usd_writer
from learnest.ingest.frames import GRAVITY
from learnest.ingest.sim import simulate
from learnest.ingest.sim.export import LOCSRV_POSE, USD_BOOT_S
from learnest.ingest.sim.recordings import recording
from learnest.ingest.sim.trajectories import Timing, Trajectory

RATE_HZ = 100.0
RPM_PER_PWM = 0.4          # a rotor speed that follows the PWM (rpm): only its being non-zero matters here
SHORT_GROUND = Timing(sit_before_s=0.5, takeoff_s=1.5, hover_s=0.5, land_s=1.5, sit_after_s=0.5)


@dataclass(kw_only=True)
class Heights(Trajectory):
    """Held above the origin at heights interpolated linearly between ``knots`` ((s, m) pairs): a hover whose
    height changes as the real logs' did."""
    knots: tuple = ((0.0, 0.5),)
    ramp_s: float = 0.5

    def path(self, s):
        """(p, dp/ds, d²p/ds²), each (N, 3), m: the closed loop smooths the corners."""
        s = np.asarray(s, float)
        when, height = np.array(self.knots, float).T
        p = np.column_stack([np.zeros_like(s), np.zeros_like(s), np.interp(s, when, height)])
        return p, np.zeros_like(p), np.zeros_like(p)


def airborne_usd(directory, stem: str, trajectory: Heights, seconds: float, rotor_speeds: bool, seed: int):
    """The simulated flight recorded from 1 s into the trajectory for ``seconds`` (airborne throughout, motors
    running, the accelerometer vibrating), written as a uSD log: acc, motor PWM, rpm (when asked) and the
    received pose rounded to 1 mm (locSrv), as the firmware logs them."""
    sim = simulate(trajectory, timing=SHORT_GROUND, seed=seed)
    start = sim.phases.fly + 1.0
    rec = recording(sim, start_s=start, stop_s=start + seconds, seed=seed)
    fixed = {f"acc.{axis}": ("f", rec.channels["acc_body"][:, j] / GRAVITY) for j, axis in enumerate("xyz")}
    pwm = rec.channels["motors"]
    assert pwm.min() > 0                                           # the motors run from first to last sample
    fixed.update({f"motor.m{k + 1}": ("I", pwm[:, k]) for k in range(4)})
    if rotor_speeds:
        fixed.update({f"rpm.m{k + 1}": ("H", RPM_PER_PWM * pwm[:, k]) for k in range(4)})
    pose = np.column_stack([np.round(rec.p, 3), rec.quat])
    fixed.update({name: ("f", pose[:, j]) for j, name in enumerate(LOCSRV_POSE)})
    path = directory / stem
    usd_writer.write(path, {"fixedFrequency": {"t": USD_BOOT_S + rec.t, "vars": fixed}})
    return path


@pytest.fixture(scope="module")
def hover_51s(tmp_path_factory):
    """A 53.5-s recording of a hover at 0.5 m that climbs to 0.66 m at 50 s and comes back at 52.5 s."""
    knots = ((0.0, 0.5), (49.56, 0.5), (51.06, 0.66), (52.4, 0.66), (53.4, 0.5), (60.0, 0.5))
    return airborne_usd(tmp_path_factory.mktemp("hover"), "log51", Heights(duration_s=56.0, knots=knots), 53.5,
                        rotor_speeds=True, seed=1)


@pytest.fixture(scope="module")
def low_6s(tmp_path_factory):
    """A 6.3-s recording starting at 0.59 m that sinks to 0.47 m from 4.4 s on."""
    knots = ((0.0, 0.59), (4.42, 0.59), (5.42, 0.47), (20.0, 0.47))
    return airborne_usd(tmp_path_factory.mktemp("low"), "log63", Heights(duration_s=9.0, knots=knots), 6.3,
                        rotor_speeds=False, seed=2)


def _height_rule_alone(flight) -> tuple[float, float, str]:
    """What the height rule would keep of the whole recording (s from its start) and why."""
    whole = read_flights([flight.meta["sources"][0]["path"]], cut="none")[0]
    start, stop, rule = flying_window(whole.t, whole.p, RATE_HZ)
    return float(whole.t[start]), float(whole.t[stop - 1]), rule


def test_the_simulated_logs_are_the_ones_the_height_rule_cut_to_nothing(hover_51s, low_6s):
    """The height rule alone gives the cuts quoted from the real logs: 51.11-51.37 s of the hover (it takes the
    climb for a take-off) and 0.00-3.14 s of the low flight (it takes the dip for a landing)."""
    hover, = read_flights([hover_51s])
    start, stop, rule = _height_rule_alone(hover)
    assert (start, stop) == (pytest.approx(51.11, abs=0.03), pytest.approx(51.37, abs=0.03))
    assert rule.startswith("kept 1 s after first rising 0.1 m above the resting height")
    low, = read_flights([low_6s])
    start, stop, rule = _height_rule_alone(low)
    assert (start, stop) == (pytest.approx(0.0), pytest.approx(3.14, abs=0.03))
    assert rule.endswith("to 1 s before last coming down below it")


@pytest.mark.parametrize(("log", "seconds", "power"), [("hover_51s", 53.5, "motor PWM, rotor speeds"),
                                                       ("low_6s", 6.3, "motor PWM")])
def test_a_recording_airborne_throughout_is_kept_whole(request, log, seconds, power):
    """Motors running from the first to the last sample and an accelerometer that never rests: nothing cut, the
    reason names both, and the flight passes the quality checks."""
    flight, = read_flights([request.getfixturevalue(log)])
    window = flight.meta["flying_window"]
    assert window["start_s"] == 0.0
    assert window["stop_s"] == pytest.approx(window["recording_s"]) == pytest.approx(seconds, abs=0.03)
    rule = window["rule"]
    assert rule.startswith("whole recording kept: airborne throughout"), rule
    assert f"the motors run from its first to its last sample ({power})" in rule
    assert "the accelerometer never rests" in rule and "height" not in rule      # the height did not decide
    assert flight.quality["ok"], flight.quality
