"""Clock offset between two recordings of one flight, found by cross-correlating what both measured.

A Vicon export counts time from its first frame; a cfclient log stamps rows in milliseconds since the
Crazyflie booted.  The two clocks share nothing, so the offset is estimated from the data:

    t_ref = t_other + offset_s

`estimate_clock_offset` works on any pair of scalar signals.  For mocap + accelerometer,
`align_mocap_and_accelerometer` compares the magnitude of the specific force:

    mocap:          |p̈ + g ẑ|      (p̈ = Savitzky–Golay second derivative of the mocap position)
    accelerometer:  |acc| · g      (body frame, in g from the log)

Why this quantity:
  * It needs no attitude.  Rotating the accelerometer into the world (or the mocap acceleration into the
    body) uses the mocap attitude *at the accelerometer's time stamps* — i.e. the offset being estimated.
  * It is frame-free: a norm is unchanged by the IMU's mounting rotation, the mocap object's axis
    definition (its yaw is set when the object is created in Vicon, often unrelated to the IMU axes) and
    quaternion/axis conventions, none of which the two files tell us.
  * It is what an ideal accelerometer measures in magnitude, gravity included, so both sides agree up to
    sensor scale and bias — which the normalised correlation (mean removed) ignores.
  * Cost: a norm discards direction.  Motion at constant |a + g ẑ| (a hover, a level circle at constant
    speed) carries no timing information; the score then stays low and the caller must not trust the
    offset.  Take-off and landing, which every recording normally contains, excite it strongly.

Both signals pass through the same zero-phase low-pass, so any filter phase is common to both and cannot
bias the offset; the band keeps the manoeuvre and drops double-differentiated mocap noise (it grows with
frequency squared) and propeller vibration.  The Savitzky–Golay derivative is a symmetric window: no lag.

The accelerometer's own low-pass is another matter: it runs on the vehicle before the value is logged, so
the logged specific force lags the body's by the filter's group delay, and the correlation peak finds the
clocks' offset less that delay.  The Crazyflie firmware filters the accelerometer with a 2-pole Butterworth
at 30 Hz on its 1 kHz samples (`CRAZYFLIE_ACCEL_LOWPASS`), a delay of √2/(2π·30 Hz) ≈ 7.5 ms below the
manoeuvres' few Hz.  `align_mocap_and_accelerometer` adds the declared filter's low-frequency group delay
(`SensorLowPass.group_delay_s`, flat to 0.1 ms across the correlation's band) back to the peak, so the
offset is the clocks' and the filter's delay stays what it is, a property of the sensor.

Accuracy (simulated 8 s figure-eight with take-off and landing,
tests/ingest/formats/test_ingest_vicon_cfclient.py): ~1-3 ms with 0.01 g accelerometer and 0.1 mm mocap noise
(score 0.99); ~10-15 ms at 0.05 g / 0.5 mm (score 0.9);
~20-35 ms at 0.1 g / 1 mm (score 0.75).  It is limited by how fast |specific force| changes: brisk
manoeuvres and take-offs give sharper correlation peaks than slow, level motion.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from .align import resample, uniform_grid
from .frames import GRAVITY

DEFAULT_MAX_LAG_S = 30.0
# Tracking manoeuvres of a quadrotor live below a few Hz; above this, mocap p̈ is mostly differentiated
# noise (at 0.5 mm) and the accelerometer shows propeller vibration.  (2-5 Hz performed alike on the tests.)
BAND_HZ = 3.0
BAND_ORDER = 4
# SG second derivative over 0.31 s: short enough not to blur a take-off (~0.5 s), long enough to tame
# the noise of double differentiation before the common low-pass.
SG_WINDOW_S = 0.31
SG_ORDER = 2
# A candidate lag must overlap the shorter signal by this fraction: tiny overlaps can correlate perfectly
# by chance and would otherwise win.
MIN_OVERLAP_FRACTION = 0.5
# Shorter signals cannot be aligned meaningfully (a few manoeuvre periods are needed).
MIN_SIGNAL_S = 2.0
# The side-lobe search ignores the main lobe: the contiguous lags around the peak above half its height.
MAIN_LOBE_FRACTION = 0.5


@dataclass(frozen=True)
class SensorLowPass:
    """A sensor's own Butterworth low-pass, run on the vehicle before its values are logged.

    Attributes
    ----------
    order : int
        Number of poles.
    cutoff_hz : float
        −3 dB frequency, Hz.
    rate_hz : float
        Rate the filter runs at on the vehicle, Hz (the sensor's sampling rate, not the log's).
    """

    order: int
    cutoff_hz: float
    rate_hz: float

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """(b, a) of the discrete filter (bilinear, pre-warped at the cut-off: the firmware's ``lpf2p``)."""
        from scipy.signal import butter  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

        b, a = butter(self.order, self.cutoff_hz, fs=self.rate_hz)
        return np.asarray(b, dtype=float), np.asarray(a, dtype=float)

    def group_delay_s(self, frequency_hz: float = 1.0) -> float:
        """Group delay −dφ/dω at ``frequency_hz`` (default 1 Hz, where a flight's manoeuvres live), s.

        A 2-pole Butterworth at 30 Hz run at 1 kHz: 7.49 ms at 1 Hz, 7.55 ms at 3 Hz (√2/(2π·30 Hz) = 7.50 ms
        for the analogue filter)."""
        from scipy.signal import group_delay  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

        _, samples = group_delay(self.coefficients(), w=[frequency_hz], fs=self.rate_hz)
        return float(samples[0]) / self.rate_hz


# The Crazyflie firmware's accelerometer filter (sensors task: lpf2p, ACCEL_LPF_CUTOFF_FREQ 30 Hz, 1 kHz):
# what the acc.x/y/z log variables of a cfclient or uSD log have been through.
CRAZYFLIE_ACCEL_LOWPASS = SensorLowPass(order=2, cutoff_hz=30.0, rate_hz=1000.0)


@dataclass
class ClockAlignment:
    """The result of `align_signals`, with the diagnostics a caller needs to trust it.

    Attributes
    ----------
    offset_s : float
        t_ref = t_other + offset_s, s.
    score : float
        Normalised correlation at the peak, in [-1, 1].
    runner_up : float
        Highest normalised correlation outside the peak's main lobe (periodic motion gives a high one).
    excitation : float
        rms of the band-limited reference signal, in its units.
    start_offset_s : float
        The offset that aligns the two starts (the centre of the search), s.
    sensor_delay_s : float
        The group delay of the other stream's own low-pass, added to the correlation peak to give the
        clocks' offset (0 when no filter is declared), s.
    """

    offset_s: float          # t_ref = t_other + offset_s
    score: float             # normalised correlation at the peak, in [-1, 1]
    runner_up: float         # highest normalised correlation outside the peak's main lobe (periodic motion)
    excitation: float        # rms of the band-limited reference signal, in its units
    start_offset_s: float    # the offset that aligns the two starts: the centre of the search
    sensor_delay_s: float = 0.0   # the other stream's low-pass group delay, added to the peak

    def as_meta(self) -> dict:
        """The fields as a dict of floats (for ``Flight.meta``)."""
        return {name: float(value) for name, value in vars(self).items()}


# -- the generic estimator ------------------------------------------------------------------------------
def estimate_clock_offset(t_ref: ArrayLike, a_ref: ArrayLike, t_other: ArrayLike, a_other: ArrayLike,
                          max_lag_s: float = DEFAULT_MAX_LAG_S,
                          rate_hz: float = 100.0) -> tuple[float, float]:
    """(offset_s, score) with t_ref = t_other + offset_s, for two scalar signals of one quantity.

    The starts are aligned first (t_ref[0] <-> t_other[0]) and the offset is searched within ±max_lag_s
    of that.  Score: normalised correlation at the peak (1 = identical shape); see `ClockAlignment`.
    Raises ValueError for signals too short or too flat to correlate.
    """
    alignment = align_signals(t_ref, a_ref, t_other, a_other, max_lag_s=max_lag_s, rate_hz=rate_hz)
    return alignment.offset_s, alignment.score


def align_signals(t_ref: ArrayLike, a_ref: ArrayLike, t_other: ArrayLike, a_other: ArrayLike,
                  max_lag_s: float = DEFAULT_MAX_LAG_S,
                  rate_hz: float = 100.0, names: tuple[str, str] = ("reference", "other")) -> ClockAlignment:
    """As `estimate_clock_offset`, with the diagnostics.  Signals need not be uniformly sampled; errors
    about one signal start with its name.

    Parameters
    ----------
    t_ref, a_ref : array_like, shape (N,)
        Reference times (s) and signal.
    t_other, a_other : array_like, shape (M,)
        The other stream's times (s, its own clock) and the same quantity.
    max_lag_s : float
        Search half-width around the start-aligned offset, s.
    rate_hz : float
        Rate both signals are resampled to before correlating, Hz.
    names : tuple of str
        Names of the two signals in error messages.

    Raises
    ------
    ValueError
        For signals too short or too flat to correlate, or that cannot overlap enough within the lag range.
    """
    grid_ref, x = _uniform(t_ref, a_ref, rate_hz, names[0])
    grid_other, y = _uniform(t_other, a_other, rate_hz, names[1])
    x, y = _band_limited(x, rate_hz), _band_limited(y, rate_hz)
    lags, ncc = _normalised_correlation(x, y)
    start_offset = grid_ref[0] - grid_other[0]     # lag 0 pairs the first samples of both grids
    min_overlap = MIN_OVERLAP_FRACTION * min(len(x), len(y))
    candidates = (np.abs(lags) <= max_lag_s * rate_hz) & (_overlap(lags, len(x), len(y)) >= min_overlap)
    if not candidates.any():
        raise ValueError("the signals cannot overlap by half the shorter one within the lag range")
    ncc = np.where(candidates, ncc, -np.inf)
    peak = int(np.argmax(ncc))
    offset = start_offset + (lags[peak] + _parabolic_vertex(ncc, peak)) / rate_hz
    return ClockAlignment(offset_s=float(offset), score=float(ncc[peak]), runner_up=_runner_up(ncc, peak),
                          excitation=float(np.sqrt(np.mean(x ** 2))), start_offset_s=float(start_offset))


def _uniform(t, values, rate_hz: float, name: str) -> tuple[np.ndarray, np.ndarray]:
    t, values = np.asarray(t, dtype=float), np.asarray(values, dtype=float)
    if t.ndim != 1 or values.shape != t.shape:
        raise ValueError(f"{name}: times {t.shape} and values {values.shape} must be equal 1-D arrays")
    finite = np.isfinite(t) & np.isfinite(values)
    t, values = t[finite], values[finite]
    if len(t) < 2 or not np.all(np.diff(t) > 0):
        raise ValueError(f"{name}: needs at least 2 finite samples with increasing times")
    if t[-1] - t[0] < MIN_SIGNAL_S:
        raise ValueError(f"{name}: {t[-1] - t[0]:.2f} s is too short to align clocks (needs {MIN_SIGNAL_S:g} s)")
    grid = uniform_grid(t[0], t[-1], rate_hz)
    return grid, np.interp(grid, t, values)


def _band_limited(signal: np.ndarray, rate_hz: float) -> np.ndarray:
    """Zero-phase low-pass and mean removal (the same for both signals: no relative delay)."""
    from scipy.signal import butter, sosfiltfilt  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    cutoff = min(BAND_HZ, 0.4 * rate_hz)
    sos = butter(BAND_ORDER, cutoff, fs=rate_hz, output="sos")
    filtered = sosfiltfilt(sos, signal - signal.mean())
    return filtered - filtered.mean()


def _normalised_correlation(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lags m and sum_n x[n+m] y[n] / sqrt(energy of x and of y over their overlap at m).

    Normalising by the overlap (not the whole signals) keeps a lag with a short but perfect overlap
    comparable with the full one; the caller bounds the overlap from below.
    """
    from scipy.signal import correlate  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    lags = np.arange(-(len(y) - 1), len(x))
    raw = correlate(x, y, mode="full", method="fft")
    cx, cy = np.r_[0.0, np.cumsum(x ** 2)], np.r_[0.0, np.cumsum(y ** 2)]
    x_start, x_stop = np.maximum(lags, 0), np.minimum(len(y) + lags, len(x))
    y_start, y_stop = np.maximum(-lags, 0), np.minimum(len(y), len(x) - lags)
    energy = (cx[x_stop] - cx[x_start]) * (cy[y_stop] - cy[y_start])
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = np.where(energy > 0, raw / np.sqrt(energy), 0.0)
    return lags, np.clip(ncc, -1.0, 1.0)


def _overlap(lags: np.ndarray, n_x: int, n_y: int) -> np.ndarray:
    return np.minimum(n_y, n_x - lags) - np.maximum(0, -lags)


def _parabolic_vertex(values: np.ndarray, peak: int) -> float:
    """Sub-sample position of the peak (in samples, within ±0.5) from the parabola through 3 points."""
    if peak == 0 or peak == len(values) - 1 or not np.all(np.isfinite(values[peak - 1:peak + 2])):
        return 0.0
    left, centre, right = values[peak - 1:peak + 2]
    curvature = left - 2 * centre + right
    return float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5)) if curvature < 0 else 0.0


def _runner_up(ncc: np.ndarray, peak: int) -> float:
    """Best correlation outside the main lobe: close to the peak when the motion repeats (a periodic
    trajectory matches itself one period later), so the peak cannot be told from its neighbours."""
    threshold = MAIN_LOBE_FRACTION * ncc[peak]
    below = ~(ncc > threshold)
    left = peak - int(np.argmax(below[peak::-1])) if below[:peak + 1].any() else -1
    right = peak + int(np.argmax(below[peak:])) if below[peak:].any() else len(ncc)
    outside = np.r_[ncc[:max(left, 0)], ncc[right:]]
    outside = outside[np.isfinite(outside)]
    return float(outside.max()) if outside.size else float("nan")


# -- mocap vs accelerometer -----------------------------------------------------------------------------
def mocap_specific_force(t: ArrayLike, p: ArrayLike, rate_hz: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """(uniform times, |p̈ + g ẑ| in m/s²) from mocap positions (m, world z-up) at frame times `t`.

    Occlusion gaps are bridged linearly (p̈ = 0 inside, a short bump at the edges): harmless for the
    correlation as long as gaps are a small part of the flight.
    """
    from scipy.signal import savgol_filter  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    t, p = np.asarray(t, dtype=float), np.asarray(p, dtype=float)
    grid = uniform_grid(t[0], t[-1], rate_hz)
    window = _odd_window(SG_WINDOW_S * rate_hz, len(grid))
    p_grid = resample(t, p, grid)[0]
    acc = savgol_filter(p_grid, window, SG_ORDER, deriv=2, delta=1.0 / rate_hz, axis=0, mode="interp")
    return grid, np.linalg.norm(acc + [0.0, 0.0, GRAVITY], axis=1)


def accelerometer_specific_force(acc_g: ArrayLike) -> np.ndarray:
    """|acc| in m/s², shape (M,), from body-frame accelerometer samples in g, shape (M, 3)."""
    return np.linalg.norm(np.asarray(acc_g, dtype=float), axis=1) * GRAVITY


def _odd_window(samples: float, n: int) -> int:
    window = max(SG_ORDER + 1, int(round(samples)))
    window += 1 - window % 2
    if window > n:
        raise ValueError(f"mocap: {n} samples are too few for the {window}-sample differentiation window")
    return window


def align_mocap_and_accelerometer(t_mocap: np.ndarray | Sequence[float], p: ArrayLike, t_acc: ArrayLike,
                                  acc_g: ArrayLike, max_lag_s: float = DEFAULT_MAX_LAG_S,
                                  rate_hz: float = 100.0,
                                  accel_lowpass: SensorLowPass | None = None) -> ClockAlignment:
    """Offset with t_mocap = t_acc + offset_s, from the specific-force magnitude (module docstring).

    ``t_mocap`` (N,) s, ``p`` (N, 3) m, ``t_acc`` (M,) s, ``acc_g`` (M, 3) g.  ``accel_lowpass``: the
    accelerometer's own filter, whose group delay is added to the correlation peak (``sensor_delay_s``);
    None for an unfiltered accelerometer.  Raises ValueError as `align_signals` does, or for fewer than 2
    mocap frames.
    """
    if len(t_mocap) < 2:
        raise ValueError("mocap: needs at least 2 frames")
    grid, mocap_norm = mocap_specific_force(t_mocap, p, rate_hz)
    alignment = align_signals(grid, mocap_norm, t_acc, accelerometer_specific_force(acc_g),
                              max_lag_s=max_lag_s, rate_hz=rate_hz, names=("mocap", "accelerometer"))
    if accel_lowpass is None:
        return alignment
    # the logged value at t_acc is the body's specific force one group delay earlier: the peak pairs mocap
    # time T with accelerometer stamp T - offset + delay, so the clocks' offset is the peak's + delay
    delay = accel_lowpass.group_delay_s()
    return replace(alignment, offset_s=alignment.offset_s + delay, sensor_delay_s=delay)
