"""Savitzky–Golay references: known answers, even windows, bad arguments."""
import numpy as np
import pytest

from learnest.ingest.align import build_flight
from learnest.ingest.baseline import centred_window, references, sg_references

DT = 0.01


def test_quadratic_is_reproduced_exactly_including_edges():
    # An order-2 fit reproduces any quadratic exactly, so v and a have closed forms everywhere.
    t = np.arange(0.0, 5.0, DT)
    p = 1.0 + 2.0 * t - 3.0 * t ** 2
    ref = sg_references(p, DT)
    np.testing.assert_allclose(ref["p"], p, atol=1e-9)
    np.testing.assert_allclose(ref["v"], 2.0 - 6.0 * t, atol=1e-8)
    np.testing.assert_allclose(ref["a"], np.full_like(t, -6.0), atol=1e-7)


def test_sinusoid_v_and_a_within_the_known_smoothing_loss():
    # A quadratic LS fit over ±h passes sin(ωt) with derivative gains ≈ 1 - x²/10 (v) and
    # ≈ 1 - x²/14 (a), x = ωh.  Here h = 0.75 s, ω = 0.5 rad/s: x = 0.375 -> 1.4 % and 1.0 %.
    omega, t = 0.5, np.arange(0.0, 20.0, DT)
    ref = sg_references(np.column_stack([np.sin(omega * t), np.cos(omega * t)]), DT)
    x = 0.75 * omega
    inner = slice(200, -200)   # away from the polynomial-fitted edges
    v_true = omega * np.column_stack([np.cos(omega * t), -np.sin(omega * t)])
    a_true = -omega ** 2 * np.column_stack([np.sin(omega * t), np.cos(omega * t)])
    assert np.max(np.abs(ref["v"] - v_true)[inner]) <= 1.05 * x ** 2 / 10 * omega
    assert np.max(np.abs(ref["a"] - a_true)[inner]) <= 1.05 * x ** 2 / 14 * omega ** 2
    assert ref["v"].shape == (len(t), 2)


def test_even_window_is_rounded_up_and_reported():
    t = np.arange(0.0, 4.0, DT)
    p = np.sin(t) + 0.1 * t ** 3
    even, odd = sg_references(p, DT, window=150), sg_references(p, DT, window=151)
    assert even["window_used"] == odd["window_used"] == 151 == centred_window(150)
    for key in ("p", "v", "a"):
        np.testing.assert_array_equal(even[key], odd[key])


def test_why_even_windows_are_not_passed_to_scipy():
    # scipy 1.17 accepts window 150 silently but evaluates the fit half a sample off-centre.
    ramp = np.arange(1000.0)
    from scipy.signal import savgol_filter

    assert savgol_filter(ramp, 150, 2)[500] - ramp[500] == pytest.approx(0.5, abs=1e-6)
    assert sg_references(ramp, 1.0, window=150)["p"][500] == pytest.approx(ramp[500], abs=1e-6)


@pytest.mark.parametrize("kwargs, message", [
    ({"window": 301}, "longer than the series"),
    ({"window": 300}, "longer than the series"),      # 300 -> 301 > 300 samples
    ({"window": 5, "order": 5}, "order"),
    ({"window": 4, "order": 7}, "order"),
    ({"window": 0}, "positive"),
    ({"window": 2.5}, "integer"),
])
def test_bad_window_or_order(kwargs, message):
    with pytest.raises(ValueError, match=message):
        sg_references(np.zeros(300), DT, **kwargs)


def test_nan_and_bad_dt_rejected():
    p = np.zeros(300)
    p[10] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        sg_references(p, DT)
    with pytest.raises(ValueError, match="dt"):
        sg_references(np.zeros(300), 0.0)


def test_references_returns_state_matrix_of_a_flight():
    t = np.arange(0.0, 6.0, DT)
    p = np.column_stack([0.5 * t ** 2, np.zeros_like(t), np.ones_like(t)])
    quat = np.tile([0.0, 0.0, 0.0, 1.0], (len(t), 1))
    acc = np.tile([0.0, 0.0, 1.0], (len(t), 1))
    flight = build_flight("analytic", t_mocap=t, p=p, quat=quat, t_acc=t, acc_body_g=acc, cut=False)
    x = references(flight)
    assert x.shape == (len(flight.t), 9)
    np.testing.assert_allclose(x[:, 0], 0.5 * flight.t ** 2, atol=1e-9)   # p
    np.testing.assert_allclose(x[:, 3], flight.t, atol=1e-8)               # v = ṗ
    np.testing.assert_allclose(x[:, 6], 1.0, atol=1e-6)                    # a = p̈
    np.testing.assert_allclose(x[:, 8], 0.0, atol=1e-9)
