"""Clock offset between two recordings of one flight, found by cross-correlating what both measured.

A Vicon export counts time from its first frame; a cfclient log stamps rows in milliseconds since the
Crazyflie booted.  The two clocks share nothing, so the offset is estimated from the data:

    t_ref = t_other + offset_s

`estimate_clock_offset` works on any pair of scalar signals.  For mocap + accelerometer,
`align_mocap_and_accelerometer` compares the specific-force vector in the body frame, where the mocap has an
attitude:

    mocap:          R(q)ᵀ (p̈ + g ẑ)   (p̈ = Savitzky–Golay second derivative, q the mocap attitude)
    accelerometer:  acc · g            (body frame, in g from the log)

summing the three axes' cross-correlations.  Why the body frame:
  * Position and attitude share the mocap's clock, so R(q)ᵀ(p̈ + g ẑ) needs no offset.  Rotating the
    accelerometer into the world instead needs the attitude at the accelerometer's stamps, i.e. the offset
    being sought: at a trial offset the rotated thrust points where the mocap says at that offset, so the
    correlation confirms whatever offset it was given.  Rotated at every trial lag instead, the world-frame sum
    of products equals the body-frame one, lag by lag (a rotation keeps dot products).
  * What times the clocks is what changes in the body: the thrust's size (the body z axis) and the body x and
    y components, which for a quadrotor are the rotor drag (−k Rᵀv/m, ~0.2 m/s² at 1 m/s) turning with the
    velocity, plus any IMU tilt.  On a constant-speed circle the thrust's size barely changes and the
    magnitude alone cannot time it; the drag turning with the vehicle can (tests/ingest/test_clock_vector.py).
  * It assumes the mocap object's axes are the IMU's: their mean specific force (gravity's direction in the
    body) must agree within MAX_FRAME_TILT_DEG, or the magnitude stands in (``note`` says why).  The magnitude is
    also the fallback without an attitude: frame-free, it needs no convention at all.
  * Occlusion gaps longer than OCCLUSION_STEPS frames are left out of the vector (bridged linearly they have no
    p̈ and an interpolated attitude).
  * Motion with a constant body-frame specific force (a hover) carries no timing information; a periodic
    one (a circle flown for ever) times the clocks only to within a period: the score and the runner-up
    say so, and the caller must not trust the offset then.

The offset's uncertainty (``uncertainty_s``) is that of a block bootstrap (`clock_correlation.bootstrap_spread`:
2-s blocks of the paired samples drawn with replacement, the peak found again in each draw; half the central
68 % of the draws), which follows the spread of the offset's error over noise draws on simulated circles;
`ClockAlignment.pins_one_sample` says whether it is within one mocap sample (1 sigma).

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

Accuracy: the offset's error grows with the accelerometer's and the mocap's noise, and the score falls with
it, so a low score marks an offset to be trusted less (tests/ingest/formats/test_ingest_vicon_cfclient.py checks
both on a simulated figure-eight).  Magnitude and vector alike are limited by how fast the body-frame specific
force changes: brisk manoeuvres and take-offs give sharper correlation peaks than slow, level motion.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike

from .align import resample, resample_quaternions, uniform_grid
from .clock_correlation import Channel, bootstrap_spread, normalised_correlation, overlap, parabolic_vertex, runner_up
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
# The vector's body x and y are small differences (rotor drag, ~0.2 m/s² at 1 m/s) of large terms (g tilted,
# the manoeuvre): an order-2 derivative loses ~1 % of a 0.3-Hz manoeuvre, which leaks into x and y 90° out of
# phase with the drag and biases the offset.  Order 4 over 0.51 s is flat to 0.01 % there and no noisier.
VECTOR_SG_WINDOW_S = 0.51
VECTOR_SG_ORDER = 4
# The mocap object's axes and the IMU's must agree for the vector: the mean specific force (gravity's
# direction in the body, as each sees it) may differ by a few degrees of mounting tilt, not by this.
MAX_FRAME_TILT_DEG = 20.0
# A mocap gap of a few frames is bridged well by interpolation; one longer than this many frames (as
# `align.build_flight` counts gaps) is left out of the vector, with half the derivative's window either side.
OCCLUSION_STEPS = 5
# A candidate lag must overlap the shorter signal by this fraction: tiny overlaps can correlate perfectly
# by chance and would otherwise win.
MIN_OVERLAP_FRACTION = 0.5
# Shorter signals cannot be aligned meaningfully (a few manoeuvre periods are needed).
MIN_SIGNAL_S = 2.0
# The side-lobe search ignores the main lobe: the contiguous lags around the peak above half its height.
MAIN_LOBE_FRACTION = 0.5
# Mocap attitudes further than this from unit norm are not quaternions (a position-only stream writes zeros).
UNIT_QUATERNION_TOLERANCE = 0.1


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
        rms of the band-limited reference signal (all channels), in its units.
    start_offset_s : float
        The offset that aligns the two starts (the centre of the search), s.
    sensor_delay_s : float
        The group delay of the other stream's own low-pass, added to the correlation peak to give the
        clocks' offset (0 when no filter is declared), s.
    uncertainty_s : float
        1-sigma spread of the offset over a block bootstrap of the paired samples
        (`ingest.clock_correlation.bootstrap_spread`), s; NaN for signals too short to draw blocks from.
    signal : str
        What was correlated: "specific-force vector" or "specific-force magnitude" (mocap and accelerometer),
        "signal" (`align_signals` on two scalar signals).
    note : str
        Why the magnitude stood in for the vector, when it did ("" otherwise).
    """

    offset_s: float
    score: float
    runner_up: float
    excitation: float
    start_offset_s: float
    sensor_delay_s: float = 0.0
    uncertainty_s: float = float("nan")
    signal: str = "signal"
    note: str = ""

    def as_meta(self) -> dict:
        """The fields as a dict of floats, the signal as text (for ``Flight.meta``)."""
        return {name: value if isinstance(value, str) else float(value) for name, value in vars(self).items()}

    def pins_one_sample(self, sample_s: float) -> bool:
        """Whether the offset is known to within one sample of ``sample_s`` s: its 1-sigma uncertainty is at
        most one sample (NaN: not known)."""
        return bool(self.uncertainty_s <= sample_s)


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
    channel = Channel(_band_limited(x, rate_hz), _band_limited(y, rate_hz))
    return _align_channels([channel], grid_ref[0] - grid_other[0], max_lag_s, rate_hz, "signal")


def _align_channels(channels: list[Channel], start_offset: float, max_lag_s: float, rate_hz: float,
                    signal: str) -> ClockAlignment:
    """The correlation peak of band-limited channels on one grid (lag 0 pairs the first samples, which lie
    ``start_offset`` s apart), refined to a fraction of a sample, with its bootstrap uncertainty."""
    lags, ncc = normalised_correlation(channels)
    n_x, n_y = len(channels[0].x), len(channels[0].y)
    candidates = (np.abs(lags) <= max_lag_s * rate_hz) & (overlap(lags, n_x, n_y) >= MIN_OVERLAP_FRACTION
                                                          * min(n_x, n_y))
    if not candidates.any():
        raise ValueError("the signals cannot overlap by half the shorter one within the lag range")
    ncc = np.where(candidates, ncc, -np.inf)
    peak = int(np.argmax(ncc))
    offset = start_offset + (lags[peak] + parabolic_vertex(ncc, peak)) / rate_hz
    excitation = np.sqrt(np.mean(sum(c.x ** 2 for c in channels)))
    return ClockAlignment(offset_s=float(offset), score=float(ncc[peak]),
                          runner_up=runner_up(ncc, peak, MAIN_LOBE_FRACTION), excitation=float(excitation),
                          start_offset_s=float(start_offset),
                          uncertainty_s=bootstrap_spread(channels, int(lags[peak]), rate_hz), signal=signal)


def _uniform(t, values, rate_hz: float, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(uniform grid (G,) s, values (G,) or (G, k) on it) from samples (N,) or (N, k) at times (N,) s."""
    t, values = np.asarray(t, dtype=float), np.asarray(values, dtype=float)
    if t.ndim != 1 or values.shape[:1] != t.shape or values.ndim > 2:
        raise ValueError(f"{name}: times {t.shape} and values {values.shape} must have one row per time")
    finite = np.isfinite(t) & np.all(np.isfinite(values.reshape(len(t), -1)), axis=1)
    t, values = t[finite], values[finite]
    if len(t) < 2 or not np.all(np.diff(t) > 0):
        raise ValueError(f"{name}: needs at least 2 finite samples with increasing times")
    if t[-1] - t[0] < MIN_SIGNAL_S:
        raise ValueError(f"{name}: {t[-1] - t[0]:.2f} s is too short to align clocks (needs {MIN_SIGNAL_S:g} s)")
    grid = uniform_grid(t[0], t[-1], rate_hz)
    return grid, (np.interp(grid, t, values) if values.ndim == 1 else resample(t, values, grid)[0])


def _band_limited(signal: np.ndarray, rate_hz: float) -> np.ndarray:
    """Zero-phase low-pass and mean removal (the same for both signals: no relative delay)."""
    from scipy.signal import butter, sosfiltfilt  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    cutoff = min(BAND_HZ, 0.4 * rate_hz)
    sos = butter(BAND_ORDER, cutoff, fs=rate_hz, output="sos")
    filtered = sosfiltfilt(sos, signal - signal.mean())
    return filtered - filtered.mean()


# -- mocap vs accelerometer -----------------------------------------------------------------------------
def mocap_specific_force(t: ArrayLike, p: ArrayLike, rate_hz: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """(uniform times (G,) s, |p̈ + g ẑ| (G,) m/s²) from mocap positions (N, 3) m, world z-up, at frame times
    ``t`` (N,) s."""
    grid, acc = _mocap_acceleration(t, p, rate_hz)
    return grid, np.linalg.norm(acc + [0.0, 0.0, GRAVITY], axis=1)


def mocap_body_specific_force(t: ArrayLike, p: ArrayLike, quat: ArrayLike,
                              rate_hz: float = 100.0) -> tuple[np.ndarray, np.ndarray]:
    """(uniform times (G,) s, R(q)ᵀ (p̈ + g ẑ) (G, 3) m/s²): the specific force an accelerometer fixed to the
    mocap object reads, from positions (N, 3) m and attitudes (N, 4) scalar-last at frame times ``t`` (N,) s.

    Position and attitude share the mocap's clock, so this needs no clock offset (module docstring)."""
    from .frames import quat_to_matrix

    grid, acc = _mocap_acceleration(t, p, rate_hz, VECTOR_SG_WINDOW_S, VECTOR_SG_ORDER)
    rotation = quat_to_matrix(resample_quaternions(t, quat, grid))
    return grid, np.einsum("tji,tj->ti", rotation, acc + [0.0, 0.0, GRAVITY])


def _mocap_acceleration(t: ArrayLike, p: ArrayLike, rate_hz: float, window_s: float = SG_WINDOW_S,
                        order: int = SG_ORDER) -> tuple[np.ndarray, np.ndarray]:
    """(uniform times (G,) s, Savitzky–Golay p̈ (G, 3) m/s², world).  Occlusion gaps are bridged linearly
    (p̈ = 0 inside, a short bump at the edges): harmless while gaps are a small part of the flight."""
    from scipy.signal import savgol_filter  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    t, p = np.asarray(t, dtype=float), np.asarray(p, dtype=float)
    grid = uniform_grid(t[0], t[-1], rate_hz)
    window = _odd_window(window_s * rate_hz, len(grid), order)
    p_grid = resample(t, p, grid)[0]
    return grid, savgol_filter(p_grid, window, order, deriv=2, delta=1.0 / rate_hz, axis=0, mode="interp")


def accelerometer_specific_force(acc_g: ArrayLike) -> np.ndarray:
    """|acc| in m/s², shape (M,), from body-frame accelerometer samples in g, shape (M, 3)."""
    return np.linalg.norm(np.asarray(acc_g, dtype=float), axis=1) * GRAVITY


def _odd_window(samples: float, n: int, order: int = SG_ORDER) -> int:
    window = max(order + 1, int(round(samples)))
    window += 1 - window % 2
    if window > n:
        raise ValueError(f"mocap: {n} samples are too few for the {window}-sample differentiation window")
    return window


def align_mocap_and_accelerometer(t_mocap: np.ndarray | Sequence[float], p: ArrayLike, t_acc: ArrayLike,
                                  acc_g: ArrayLike, max_lag_s: float = DEFAULT_MAX_LAG_S,
                                  rate_hz: float = 100.0, accel_lowpass: SensorLowPass | None = None,
                                  quat: ArrayLike | None = None) -> ClockAlignment:
    """Offset with t_mocap = t_acc + offset_s, from the specific-force vector where the mocap has an attitude,
    else from its magnitude (module docstring).

    Parameters
    ----------
    t_mocap : array_like, shape (N,)
        Mocap frame times, s (the mocap's clock).
    p : array_like, shape (N, 3)
        Mocap positions, m, world z-up.
    t_acc : array_like, shape (M,)
        Accelerometer stamps, s (its own clock).
    acc_g : array_like, shape (M, 3)
        Body-frame specific force, g.
    max_lag_s : float
        Search half-width around the start-aligned offset, s.
    rate_hz : float
        Correlation grid rate, Hz.
    accel_lowpass : SensorLowPass, optional
        The accelerometer's own filter, whose group delay is added to the peak (``sensor_delay_s``); None for
        an unfiltered accelerometer.
    quat : array_like, shape (N, 4), optional
        Mocap attitudes, scalar-last.  None, or not finite unit quaternions: the magnitude alone.

    Raises
    ------
    ValueError
        As `align_signals`, or for fewer than 2 mocap frames.
    """
    if len(t_mocap) < 2:
        raise ValueError("mocap: needs at least 2 frames")
    alignment, note = None, "the mocap has no attitude"
    if _attitude_usable(quat, len(t_mocap)):
        alignment, note = _align_vector(t_mocap, p, quat, t_acc, acc_g, max_lag_s, rate_hz)
    if alignment is None:
        grid, mocap_norm = mocap_specific_force(t_mocap, p, rate_hz)
        alignment = align_signals(grid, mocap_norm, t_acc, accelerometer_specific_force(acc_g),
                                  max_lag_s=max_lag_s, rate_hz=rate_hz, names=("mocap", "accelerometer"))
        alignment = replace(alignment, signal="specific-force magnitude", note=note)
    if accel_lowpass is None:
        return alignment
    # the logged value at t_acc is the body's specific force one group delay earlier: the peak pairs mocap
    # time T with accelerometer stamp T - offset + delay, so the clocks' offset is the peak's + delay
    delay = accel_lowpass.group_delay_s()
    return replace(alignment, offset_s=alignment.offset_s + delay, sensor_delay_s=delay)


def _attitude_usable(quat: ArrayLike | None, frames: int) -> bool:
    """Whether ``quat`` is one finite unit quaternion (scalar-last) per mocap frame."""
    if quat is None:
        return False
    quat = np.asarray(quat, dtype=float)
    return (quat.shape == (frames, 4) and bool(np.all(np.isfinite(quat)))
            and bool(np.all(np.abs(np.linalg.norm(quat, axis=1) - 1.0) < UNIT_QUATERNION_TOLERANCE)))


def _align_vector(t_mocap, p, quat, t_acc, acc_g, max_lag_s: float,
                  rate_hz: float) -> tuple[ClockAlignment | None, str]:
    """`align_mocap_and_accelerometer` on the body-frame specific-force vector, the three axes' correlations
    summed: (the alignment, "") or (None, why the axes cannot be compared)."""
    grid_ref, mocap = mocap_body_specific_force(t_mocap, p, quat, rate_hz)
    grid_other, acc = _uniform(t_acc, np.asarray(acc_g, dtype=float) * GRAVITY, rate_hz, "accelerometer")
    tilt = _angle_deg(np.mean(mocap, axis=0), np.mean(acc, axis=0))
    if not tilt <= MAX_FRAME_TILT_DEG:
        return None, (f"the mocap object's axes and the accelerometer's disagree by {tilt:.0f}° "
                      f"(> {MAX_FRAME_TILT_DEG:g}°) on gravity's direction")
    _uniform(grid_ref, mocap[:, 2], rate_hz, "mocap")        # long enough to align, as the magnitude requires
    seen = _seen(t_mocap, grid_ref, VECTOR_SG_WINDOW_S / 2)
    channels = [Channel(_band_limited(mocap[:, j], rate_hz) * seen, _band_limited(acc[:, j], rate_hz))
                for j in range(3)]
    return _align_channels(channels, grid_ref[0] - grid_other[0], max_lag_s, rate_hz, "specific-force vector"), ""


def _seen(t_mocap: ArrayLike, grid: np.ndarray, margin_s: float) -> np.ndarray:
    """(G,) 1.0 where the mocap saw the vehicle, 0.0 within ``margin_s`` of an occlusion gap (a step longer than
    OCCLUSION_STEPS median steps): bridged linearly, a gap has no p̈ and the attitude turns by interpolation,
    so the vector there would be compared with nothing the vehicle did."""
    t_mocap = np.asarray(t_mocap, dtype=float)
    steps = np.diff(t_mocap)
    seen = np.ones(len(grid))
    for gap in np.flatnonzero(steps > OCCLUSION_STEPS * np.median(steps)):
        seen[(grid > t_mocap[gap] - margin_s) & (grid < t_mocap[gap + 1] + margin_s)] = 0.0
    return seen


def _angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """Angle between two 3-vectors, degrees (NaN for a zero vector)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        cosine = np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v))
    return float(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))))
