"""The pages' figures: running RMS, the SG reference's clipping against the analytic
Savitzky-Golay gain, the flight page's shading of cut parts, stopped streams and gaps, the per-flight MSE
figure.  The pages themselves: tests/service/api/test_service_evaluations.py."""
from pathlib import Path

import numpy as np
import pytest

from learnest.estimators.estimates import FlightEstimates
from learnest.ingest.flight import Flight

NANOBENCH = Path(__file__).resolve().parents[4] / "shared" / "data" / "nanobench"


def test_running_rms_of_a_constant_and_of_a_sine():
    from learnest.service.web.evaluation_plots import running_rms

    dt = 0.01
    constant = np.full((500, 3), [0.3, -0.3, 0.3])
    np.testing.assert_allclose(running_rms(constant, dt), 0.3)
    t = np.arange(2000) * dt
    sine = np.column_stack([np.sin(2 * np.pi * 2.0 * t)] * 3)   # 1-s window = two whole periods (+ 1 sample)
    assert running_rms(sine, dt)[200:-200] == pytest.approx(1 / np.sqrt(2), abs=0.01)


def sg_velocity_gain(frequency_hz: float, window: int, dt: float) -> float:
    """Analytic gain of the order-2 Savitzky-Golay first derivative on a sine: the central least-squares
    slope c_k = 3k / (m(m+1)(2m+1) dt) over k = -m..m, applied to sin(w k dt), over w."""
    m, w = window // 2, 2 * np.pi * frequency_hz
    k = np.arange(1, m + 1)
    return float(6 * np.sum(k * np.sin(w * k * dt)) / (m * (m + 1) * (2 * m + 1) * dt * w))


def test_reference_clipping_matches_the_analytic_sg_gain():
    from learnest.ingest.baseline import references
    from learnest.service.web.evaluation_plots import reference_clipping

    dt, f = 0.01, 0.5
    t = np.arange(3000) * dt
    p = np.column_stack([np.sin(2 * np.pi * f * t), np.zeros_like(t), np.ones_like(t)])
    flight = Flight(t, p, np.zeros((len(t), 3)), np.tile([0, 0, 0, 1.0], (len(t), 1)))
    reference = references(flight)   # the paper's 150 -> 151 samples
    estimates = FlightEstimates("sine", t, reference, np.column_stack([p, np.zeros((len(t), 3))]),
                                flight.quat, {"ukf": reference})
    clipping = reference_clipping(estimates, 151)
    expected = 1 - sg_velocity_gain(f, 151, dt) / sg_velocity_gain(f, 21, dt)
    assert clipping["axis"] == "x" and clipping["window_s"] == pytest.approx(1.51)
    assert clipping["clipped_pct"] == pytest.approx(100 * expected, abs=0.5)   # ~45 % at 0.5 Hz
    assert clipping["peak_short"] == pytest.approx(np.pi * sg_velocity_gain(f, 21, dt), rel=0.01)


def test_euler_angles_of_known_rotations():
    from learnest.service.web.flight_plots import euler_deg

    half = np.radians(30) / 2
    quats = np.array([[np.sin(half), 0, 0, np.cos(half)], [0, np.sin(half), 0, np.cos(half)],
                      [0, 0, np.sin(half), np.cos(half)]])
    np.testing.assert_allclose(euler_deg(quats), 30 * np.eye(3), atol=1e-9)


def stopped_and_gapped_flight() -> Flight:
    """10 s kept from 2 s into the log; the accelerometer interpolated over 0.4 s at 3-3.4 s of the kept
    flight and stopping (its rows) at 11 s of the log while mocap goes on to 14 s."""
    rng = np.random.default_rng(0)
    t = np.arange(1000) * 0.01
    acc = rng.normal(0, 0.1, (1000, 3)) + [0, 0, 9.81]
    acc[300:341] = np.linspace(acc[300], acc[340], 41)          # 40 steps interpolated: a 0.4-s gap
    meta = {"flying_window": {"start_s": 2.0, "stop_s": 11.99, "rule": "test"},
            "streams": {"mocap": {"t_first_s": 0.0, "t_last_s": 14.0}, "acc": {"t_first_s": 0.0, "t_last_s": 11.0},
                        "gyro": {"t_first_s": 0.0, "t_last_s": 11.1}},
            "gaps": {"acc_longest_gap_airborne_s": 2.5, "mocap_longest_gap_airborne_s": 0.01}}
    p = np.column_stack([np.sin(t), np.cos(t), 1 + 0.01 * rng.normal(size=1000)])
    return Flight(t, p, acc - [0, 0, 9.81], np.tile([0, 0, 0, 1.0], (1000, 1)),
                  {"acc_body": acc, "gyro": rng.normal(0, 0.1, (1000, 3))}, meta)


def test_flight_figure_shades_the_cut_the_stopped_streams_and_the_gaps():
    from learnest.service.web.flight_plots import CUT_COLOUR, GAP_COLOUR, MISSING_COLOUR, flight_figure

    spec = flight_figure(stopped_and_gapped_flight())
    layout = spec["layout"]
    bands = {(s["fillcolor"], round(s["x0"], 2), round(s["x1"], 2)) for s in layout["shapes"]}
    assert (CUT_COLOUR, 0.0, 2.0) in bands                 # take-off cut
    assert (CUT_COLOUR, 11.99, 14.0) in bands              # landing cut, to mocap's last row
    assert (MISSING_COLOUR, 11.0, 14.0) in bands           # acc and gyro stopped together: one band
    assert (GAP_COLOUR, 5.0, 5.4) in bands                 # kept t 3.0-3.4 s + the 2-s offset
    texts = [a["text"] for a in layout["annotations"]]
    assert "no acc, gyro samples after 11.0 s" in texts and "acc gap 0.40 s" in texts
    assert layout["title"]["text"] == "acc: 2.50 s without samples while airborne"
    assert layout["xaxis"]["range"] == [0.0, 14.0] and spec["t"][0] == 2.0
    labels = [layout["yaxis" if row == 1 else f"yaxis{row}"]["title"]["text"] for row in range(1, 6)]
    assert "yaxis6" not in layout                          # no motors, no battery in this flight
    assert labels == ["position (m)", "accelerometer (m/s²)", "gyro (rad/s)", "velocity (m/s)", "attitude (deg)"]


@pytest.mark.skipif(not NANOBENCH.is_dir(), reason="../shared/data/nanobench not present (a fresh clone)")
def test_the_real_accelerometer_gap_of_circle_medium_rep3_is_drawn():
    """The 6.9-s accelerometer gap that fails NanoBench B2_circle_medium_rep3 is drawn and named in the title."""
    import learnest as le
    from learnest.service.web.flight_plots import MISSING_COLOUR, flight_figure

    [flight] = le.read_flights([NANOBENCH / "B2_circle_medium_rep3.csv"])
    layout = flight_figure(flight)["layout"]
    assert "acc: 6.91 s without samples while airborne" in layout["title"]["text"]
    missing = [s for s in layout["shapes"] if s["fillcolor"] == MISSING_COLOUR]
    assert len(missing) == 1 and missing[0]["x0"] == pytest.approx(31.15, abs=0.05)
    assert missing[0]["x1"] == pytest.approx(42.26, abs=0.05)


def test_paired_mse_draws_a_line_per_flight_and_boxes_only_from_ten_flights():
    from learnest.service.local.figures import BOX_MIN_FLIGHTS, paired_mse

    def report(n):
        flights = [{"flight": f"f{i}", "mse": {"ukf": 0.02 + 0.001 * i, "knode-ukf": 0.01 + 0.002 * i}}
                   for i in range(n)]
        return {"model": "m:1", "flights": flights}

    few = paired_mse(report(2)).axes[0]
    assert len([line for line in few.lines if len(line.get_xdata()) == 2]) == 2 and not few.patches
    assert few.get_ylim()[0] == 0 and "1e-3" in few.get_ylabel()
    np.testing.assert_allclose(few.lines[0].get_ydata(), [20.0, 10.0])   # x 1e3: the table's units
    many = paired_mse(report(BOX_MIN_FLIGHTS)).axes[0]
    assert len(many.lines) > BOX_MIN_FLIGHTS + 2    # the boxes' whiskers and caps are lines too
