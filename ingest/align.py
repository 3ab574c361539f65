"""Shared normalisation: raw mocap + accelerometer streams -> a Flight on a uniform grid.

Every adapter parses its format into raw arrays with their own time stamps and calls `build_flight`;
resampling, rotation into the world frame, gravity removal and the take-off/landing cut happen here once.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from learnest.errors import InvalidInput

from .flight import Flight, IngestError
from .frames import GRAVITY, world_acceleration

# The flying part: from TAKEOFF_SETTLE_S after the vehicle first rises FLYING_HEIGHT_M above its resting
# height, to LANDING_SETTLE_S before it last comes down below that height.
FLYING_HEIGHT_M = 0.10
TAKEOFF_SETTLE_S = 1.0
LANDING_SETTLE_S = 1.0
# The resting height is that of the first HEAD_S; a log whose first HEAD_S lie FLYING_HEIGHT_M above its
# GROUND_PERCENTILE height (robust to a dropped low sample) started in the air (logging began after take-off).
HEAD_S = 0.5
GROUND_PERCENTILE = 1.0
# A vehicle at rest moves only by the mocap's noise (< 1 cm over 0.5 s); one climbing or sinking faster than
# this over the first HEAD_S is flying.
RESTING_SPEED_M_S = 0.1
# A vehicle on the floor holds its position to the mocap's noise (Vicon < 0.5 mm, a 1 mm-rounded pose one
# step); a hovering one drifts by centimetres.  Smoothed over HEAD_SMOOTHING samples, a first HEAD_S that
# spans more than HEAD_STILL_M on any axis is not on the floor.
HEAD_STILL_M = 0.005
HEAD_SMOOTHING = 5

# Anti-aliasing before a stream sampled faster than the grid is brought to it: a zero-phase Butterworth
# low-pass (order ANTI_ALIAS_ORDER, run forwards and backwards) with its cut-off at ANTI_ALIAS_CUTOFF of the
# grid rate, i.e. 40 Hz for the 100 Hz grid: the Nyquist frequency is 50 Hz, and motor vibration (~100-300 Hz
# on a Crazyflie) would otherwise fold into the 0-50 Hz band the estimators use.  Streams faster than
# ANTI_ALIAS_MIN_RATIO times the grid are filtered (a 100 Hz log on a 100 Hz grid is left as it is).
ANTI_ALIAS_CUTOFF = 0.4
ANTI_ALIAS_ORDER = 8
ANTI_ALIAS_MIN_RATIO = 1.5
# Channels of the same IMU that alias like the accelerometer.
ANTI_ALIAS_CHANNELS = ("gyro",)

# Position resolution (`position_resolution`): a step finer than 10 µm is Vicon-grade (no rounding to speak
# of); fewer than 20 position changes cannot tell a rounding step.
RESOLUTION_MIN_M = 1e-5
RESOLUTION_MIN_STEPS = 20


def uniform_grid(t_start: float, t_end: float, rate_hz: float) -> np.ndarray:
    """Times t_start + k / rate_hz (s) up to and including t_end (within 1e-9 samples)."""
    n = int(np.floor((t_end - t_start) * rate_hz + 1e-9)) + 1
    return t_start + np.arange(n) / rate_hz


def samples_per_second(t: np.ndarray | Sequence[float]) -> float | None:
    """A stream's sample rate (Hz) measured from its time stamps: one over the mean step between samples,
    leaving out the gaps (steps longer than GAP_STEPS median steps).

    The rate the logger ran at, not the count over the span: a 100 Hz stream that lost a quarter of its
    packets over the radio is a 100 Hz stream with gaps (`stream_timing` reports those), and a rate taken
    from a row count would change with every dropout.  The mean of the ordinary steps (not their median)
    serves a stream held on a faster clock too: 100 Hz mocap frames seen on a 250 Hz log come 8 and 12 ms
    apart.  None for fewer than 2 samples or no positive step.
    """
    steps = np.diff(np.asarray(t, dtype=float))
    steps = steps[np.isfinite(steps) & (steps > 0)]
    if not steps.size:
        return None
    ordinary = steps[steps <= GAP_STEPS * np.median(steps)]
    return float(1.0 / np.mean(ordinary))


# A step longer than GAP_STEPS median steps is a gap (a lost packet or more), not the logger's jitter (a
# stream held on a faster clock alternates steps of 2 and 3 ticks: 1.5 median steps at most).
GAP_STEPS = 1.6


def stream_timing(t: np.ndarray | Sequence[float]) -> dict | None:
    """How a stream was delivered, from its time stamps.

    Returns
    -------
    dict or None
        ``rate_hz`` (`samples_per_second`), ``samples``, ``span_s`` (s), ``delivered`` (samples over those a
        gap-free stream at ``rate_hz`` would hold over the span, 0-1), ``gaps`` (steps longer than GAP_STEPS
        median positive steps: repeated stamps, as a log that stamps several rows alike writes, are no step)
        and ``longest_gap_s`` (s); None for fewer than 2 samples.
    """
    t = np.asarray(t, dtype=float)
    rate = samples_per_second(t)
    if rate is None:
        return None
    steps = np.diff(t)
    span = float(t[-1] - t[0])
    expected = span * rate + 1
    return {"rate_hz": round(rate, 3), "samples": int(len(t)), "span_s": round(span, 3),
            "delivered": round(min(1.0, len(t) / expected), 4),
            "gaps": int(np.sum(steps > GAP_STEPS * np.median(steps[steps > 0]))) if np.any(steps > 0) else 0,
            "longest_gap_s": round(float(steps.max()), 4)}


def resample(t_src: ArrayLike, values: ArrayLike, t_grid: np.ndarray,
             max_gap_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of (N, k) values onto t_grid; returns (values, mask of grid points that fell
    into a gap longer than max_gap_s, where interpolation would invent data).

    ``t_src`` (N,) s, increasing; ``values`` (N,) or (N, k); returns (len(t_grid), k) values and a
    (len(t_grid),) bool mask.  Outside ``t_src`` the end values are held (``np.interp``).
    """
    t_src = np.asarray(t_src, dtype=float)
    values = np.asarray(values, dtype=float)
    values = values[:, None] if values.ndim == 1 else values
    out = np.column_stack([np.interp(t_grid, t_src, values[:, j]) for j in range(values.shape[1])])
    in_gap = np.zeros(len(t_grid), dtype=bool)
    if max_gap_s is not None and len(t_src) > 1:
        idx = np.clip(np.searchsorted(t_src, t_grid), 1, len(t_src) - 1)
        in_gap = (t_src[idx] - t_src[idx - 1]) > max_gap_s
    return out, in_gap


def resample_quaternions(t_src: ArrayLike, quat: ArrayLike, t_grid: np.ndarray) -> np.ndarray:
    """Component-wise interpolation after making the sign continuous, then renormalised (fine at
    mocap rates, where consecutive attitudes differ by far less than the nlerp/slerp discrepancy).

    ``quat`` (N, 4) scalar-last -> (len(t_grid), 4) unit quaternions, scalar-last.
    """
    q = np.array(quat, dtype=float, copy=True)
    flips = np.cumsum(np.r_[0, np.sum(q[1:] * q[:-1], axis=1) < 0]) % 2 == 1
    q[flips] *= -1
    out, _ = resample(t_src, q, t_grid)
    return out / np.linalg.norm(out, axis=1, keepdims=True)


def flying_window(t: np.ndarray, p: np.ndarray, rate_hz: float) -> tuple[int, int, str]:
    """Indices [start, stop) of the flying part and the rule that chose them.

    ``p`` (T, 3) is the position, m (z up).  The ground is the median height of the first 0.5 s, unless the log
    started in the air (`started_in_air`): then it is the lowest height of the log, and nothing is cut
    at the start (there was no take-off to cut).  A log that ends in the air keeps its end too.

    Parameters
    ----------
    t : ndarray, shape (T,)
        Time, s.
    p : ndarray, shape (T, 3)
        Position, m, z up.
    rate_hz : float
        Grid rate, Hz.
    """
    head = max(1, int(HEAD_S * rate_hz))
    in_air, why = started_in_air(p, rate_hz)
    z = p[:, 2]
    ground = float(np.percentile(z, GROUND_PERCENTILE)) if in_air else float(np.median(z[:head]))
    airborne = np.flatnonzero(z > ground + FLYING_HEIGHT_M)
    if airborne.size == 0:
        return 0, len(t), (f"never {FLYING_HEIGHT_M:g} m above the height of its first {HEAD_S:g} s (a log that "
                           f"starts in the air and stays level, or no flight): whole recording kept")
    ends_in_air = bool(np.median(z[-head:]) > ground + FLYING_HEIGHT_M)
    start = 0 if in_air else airborne[0] + int(TAKEOFF_SETTLE_S * rate_hz)
    stop = len(t) if ends_in_air else airborne[-1] + 1 - int(LANDING_SETTLE_S * rate_hz)
    if stop <= start:
        return int(airborne[0]), int(airborne[-1]) + 1, "airborne too briefly to trim: airborne part kept"
    first = (f"from the start (the log starts in the air: {why})" if in_air else
             f"{TAKEOFF_SETTLE_S:g} s after first rising {FLYING_HEIGHT_M:g} m above the resting height")
    last = ("to the end (the log ends in the air)" if ends_in_air else
            f"to {LANDING_SETTLE_S:g} s before last coming down below it")
    return int(start), int(stop), f"kept {first} {last}"


def started_in_air(p: np.ndarray, rate_hz: float) -> tuple[bool, str]:
    """(whether the log starts with the vehicle in the air, why).

    In the air at the start: the first 0.5 s lie FLYING_HEIGHT_M above the log's lowest height (it comes
    down later), or the vehicle moves sideways faster than a resting one can (mocap noise; a take-off that
    begins within the first 0.5 s climbs, it does not slide), or it is not still (HEAD_STILL_M): it wanders
    sideways, or it sinks (a vehicle on the floor cannot; a climb is a take-off, not a sign of flight).
    ``p`` (T, 3) m, z up.  A log that starts hovering at its lowest height and holds still at first cannot be
    told from one on a shelf: the user's cut (`parse_cut`) decides then.
    """
    head = max(2, int(HEAD_S * rate_hz))
    z = p[:, 2]
    start_height, lowest = float(np.median(z[:head])), float(np.percentile(z, GROUND_PERCENTILE))
    if start_height > lowest + FLYING_HEIGHT_M:
        return True, f"{start_height - lowest:.2f} m above its lowest height"
    if len(p) >= head:
        tenth = max(1, head // 5)
        moved = np.linalg.norm(np.median(p[head - tenth:head, :2], axis=0) - np.median(p[:tenth, :2], axis=0))
        speed = float(moved) * rate_hz / (head - tenth)
        if speed > RESTING_SPEED_M_S:
            return True, f"moving sideways at {speed:.2f} m/s in the first {HEAD_S:g} s"
        from scipy.ndimage import uniform_filter1d

        smooth = uniform_filter1d(p[:head], min(HEAD_SMOOTHING, head), axis=0, mode="nearest")
        sink = float(np.max(np.maximum.accumulate(smooth[:, 2]) - smooth[:, 2]))   # largest fall after a height
        span = max(float(np.max(np.ptp(smooth[:, :2], axis=0))), sink)
        if span > HEAD_STILL_M:
            return True, f"moving by {1000 * span:.0f} mm in the first {HEAD_S:g} s (a vehicle on the floor is still)"
    return False, ""


def parse_cut(value: str | bool | tuple | None) -> bool | tuple[float | None, float | None]:
    """A user's take-off/landing cut: "auto" (default, `ingest.flight_span.find_flight`), "none" (the
    whole recording) or "START:STOP" in seconds from the recording's start (either side may be empty: "2.5:"
    keeps from 2.5 s).

    Returns
    -------
    True, False or (start_s, stop_s)
        What `build_flight`'s ``cut`` takes.

    Raises
    ------
    InvalidInput
        A value of another form, a negative or non-finite time, or start >= stop.
    """
    if value is None or value is True or value is False:
        return True if value is None else value
    if isinstance(value, tuple):
        start, stop = value
    else:
        text = str(value).strip().lower()
        if text in ("", "auto"):
            return True
        if text in ("none", "all", "off"):
            return False
        if text.count(":") != 1:
            raise InvalidInput(f"cut {value!r}: give auto, none or START:STOP in seconds (e.g. 2.5:14)")
        try:
            start, stop = (float(part) if part.strip() else None for part in text.split(":"))
        except ValueError:
            raise InvalidInput(f"cut {value!r}: START and STOP must be seconds (e.g. 2.5:14)") from None
    for side in (start, stop):
        if side is not None and not (math.isfinite(side) and side >= 0):
            raise InvalidInput(f"cut {value!r}: times must be finite and >= 0 s")
    if start is not None and stop is not None and start >= stop:
        raise InvalidInput(f"cut {value!r}: START must come before STOP")
    return (start, stop)


def cut_text(cut: bool | tuple) -> str:
    """The cut as `parse_cut` reads it back ("auto", "none", "2.5:14")."""
    if cut is True:
        return "auto"
    if cut is False:
        return "none"
    return ":".join("" if side is None else f"{side:g}" for side in cut)


def _window(flight: Flight, rate_hz: float, cut: bool | tuple) -> tuple[int, int, str]:
    if cut is True:
        from .flight_span import find_flight

        span = find_flight(flight.t, flight.p, rate_hz, flight.channels, flying_height_m=FLYING_HEIGHT_M,
                           takeoff_settle_s=TAKEOFF_SETTLE_S, landing_settle_s=LANDING_SETTLE_S,
                           height_rule=flying_window)
        return span.start, span.stop, span.rule
    if cut is False:
        return 0, len(flight.t), "whole recording kept (no cut asked)"
    start_s, stop_s = cut
    start = 0 if start_s is None else int(np.searchsorted(flight.t, start_s - 1e-9))
    stop = len(flight.t) if stop_s is None else int(np.searchsorted(flight.t, stop_s + 1e-9))
    return start, stop, f"kept {cut_text(cut)} s as asked"


def position_resolution(p: ArrayLike) -> float:
    """The step (m) positions are rounded to, told from the data: 0.001 for a pose sent to the vehicle as
    int16 millimetres (crazyswarm2's extpos, uSD ``locSrv``), 0.0 for a stream finer than RESOLUTION_MIN_M
    (Vicon/OptiTrack exports, µm) or one whose steps are not multiples of one step (noise).

    ``p`` (N, 3) as sampled (not resampled: interpolation hides the rounding).
    """
    steps = np.abs(np.diff(np.asarray(p, dtype=float), axis=0)).ravel()
    steps = steps[np.isfinite(steps) & (steps > 1e-9)]
    if steps.size < RESOLUTION_MIN_STEPS:
        return 0.0
    quantum = float(np.percentile(steps, 5))
    if quantum < RESOLUTION_MIN_M:
        return 0.0
    ratio = steps / quantum
    on_multiples = np.mean(np.abs(ratio - np.round(ratio)) < 0.1)
    return float(f"{quantum:.3g}") if on_multiples >= 0.9 else 0.0   # 3 digits: float32 logs hold 0.000999987


def anti_alias(t_src: ArrayLike, values: ArrayLike, rate_hz: float) -> tuple[np.ndarray, np.ndarray, bool]:
    """A stream sampled faster than ``rate_hz``, low-passed (zero phase) so that the grid does not alias it.

    A stream faster than ANTI_ALIAS_MIN_RATIO × ``rate_hz`` is interpolated onto a uniform grid at its own
    median rate, filtered forwards and backwards by a Butterworth low-pass at ANTI_ALIAS_CUTOFF × ``rate_hz``
    (no delay: the timing the estimators and the clock alignment rely on is kept) and returned on that grid;
    a slower stream is returned as it is.

    Parameters
    ----------
    t_src : array_like, shape (N,)
        Stamps, s, increasing.
    values : array_like, shape (N,) or (N, k)
        The samples.
    rate_hz : float
        The rate the stream will be resampled to, Hz.

    Returns
    -------
    (t, values, filtered)
        Stamps (M,) s, values (M, k), and whether the stream was filtered.
    """
    t_src = np.asarray(t_src, dtype=float)
    values = np.asarray(values, dtype=float)
    values = values[:, None] if values.ndim == 1 else values
    steps = np.diff(t_src)
    if len(t_src) < 4 or not np.all(np.isfinite(values)):
        return t_src, values, False
    source_hz = 1.0 / float(np.median(steps))
    if not source_hz > ANTI_ALIAS_MIN_RATIO * rate_hz:
        return t_src, values, False
    from scipy.signal import butter, sosfiltfilt  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    uniform = uniform_grid(t_src[0], t_src[-1], source_hz)
    on_grid, _ = resample(t_src, values, uniform)
    sos = butter(ANTI_ALIAS_ORDER, ANTI_ALIAS_CUTOFF * rate_hz, fs=source_hz, output="sos")
    if len(uniform) <= 3 * (2 * len(sos) + 1):   # too short for filtfilt's padding: leave it
        return t_src, values, False
    return uniform, sosfiltfilt(sos, on_grid, axis=0), True


def build_flight(path: str | Path, *, t_mocap: ArrayLike, p: ArrayLike, quat: ArrayLike, t_acc: ArrayLike,
                 acc_body_g: ArrayLike, channels: dict | None = None, rate_hz: float = 100.0,
                 meta: dict | None = None, cut: bool | tuple = True, mocap_alive_t: ArrayLike | None = None
                 ) -> Flight:
    """Resample mocap (m, scalar-last quaternions) and accelerometer (g, body frame) onto one grid.

    `channels` maps name -> (t, values) for optional streams.  Times are seconds on one clock (the caller
    applies any clock offset first).  The grid covers the time where both streams exist.  The accelerometer
    and the gyro, when sampled faster than the grid, are low-passed first (`anti_alias`).

    Parameters
    ----------
    path : str or Path
        The source file, named in errors.
    t_mocap : array_like, shape (N,)
        Mocap time stamps, s.
    p : array_like, shape (N, 3)
        Mocap position, m, world z-up.
    quat : array_like, shape (N, 4)
        Mocap attitude, scalar-last [qx, qy, qz, qw].
    t_acc : array_like, shape (M,)
        Accelerometer time stamps, s, same clock.
    acc_body_g : array_like, shape (M, 3)
        Body-frame specific force, g.
    channels : dict, optional
        name -> (t (K,) s, values (K,) or (K, k)), resampled without gap detection.
    rate_hz : float
        Grid rate, Hz.
    meta : dict, optional
        Metadata to start from (``rate_hz``, ``t0_source_s``, ``flying_window``, ``gaps``,
        ``mocap_resolution_m`` (`position_resolution`), ``timing`` (`stream_timing` of the mocap and the
        accelerometer, unless the adapter gave it) and ``anti_alias`` are added).
    mocap_alive_t : array_like, optional
        Stamps at which the mocap stream was alive, for telling gaps (default ``t_mocap``): a log that
        repeats the last pose between frames (uSD fixed-frequency stream) drops the repeats from ``t_mocap``,
        but a repeat of a pose rounded to 1 mm is often a new frame at the same place, not a gap.
    cut : bool or (start_s, stop_s)
        True: keep only the flying part (`ingest.flight_span.find_flight`: motors, accelerometer, height);
        False: the whole recording; (start_s, stop_s):
        that stretch, s from the start of the grid (None for either end), as `parse_cut` gives.

    Returns
    -------
    Flight
        With ``a_meas`` in m/s² (world, gravity removed) and the channel ``acc_body`` (m/s², body frame);
        ``meta["flying_window"]`` = {"start_s", "stop_s", "recording_s", "rule", "cut"}: the stretch kept,
        s on the recording's grid.

    Raises
    ------
    IngestError
        With fewer than 2 samples in a stream, streams that overlap for less than two grid steps, or a
        flying part (or asked-for cut) of fewer than 2 samples.
    """
    t_mocap, t_acc = np.asarray(t_mocap, float), np.asarray(t_acc, float)
    if len(t_mocap) < 2 or len(t_acc) < 2:
        raise IngestError(path, f"too few samples (mocap {len(t_mocap)}, accelerometer {len(t_acc)})")
    t0, t1 = max(t_mocap[0], t_acc[0]), min(t_mocap[-1], t_acc[-1])
    if t1 - t0 < 2.0 / rate_hz:
        raise IngestError(path, "mocap and accelerometer streams do not overlap in time")
    grid = uniform_grid(t0, t1, rate_hz)
    p_grid, q_grid, mocap_gap, alive_t = _mocap_on_grid(t_mocap, p, quat, grid, rate_hz, mocap_alive_t)
    # gaps are told from the stamps as recorded, the values from the low-passed stream
    _, acc_gap = resample(t_acc, acc_body_g, grid, max_gap_s=5.0 / rate_hz)
    t_filtered, acc_filtered, filtered = anti_alias(t_acc, acc_body_g, rate_hz)
    acc_grid, _ = resample(t_filtered, acc_filtered, grid)
    extra, low_passed = _resample_channels(channels, grid, rate_hz, ["acc"] if filtered else [])
    extra["acc_body"] = acc_grid * GRAVITY
    meta = _grid_meta(meta, rate_hz, t0, p, alive_t, t_acc, low_passed)
    flight = Flight(grid - grid[0], p_grid, world_acceleration(acc_grid, q_grid), q_grid, extra, meta)
    start, stop, rule = _window(flight, rate_hz, parse_cut(cut))
    if stop - start < 2:  # e.g. one corrupt height sample is the only "airborne" one
        raise IngestError(path, f"the flying part has {stop - start} sample(s) ({rule}): no flight to keep")
    flight = flight.slice(start, stop)
    _record_window(flight, grid, start, stop, rule, cut, mocap_gap, acc_gap)
    return flight


def _mocap_on_grid(t_mocap: np.ndarray, p: ArrayLike, quat: ArrayLike, grid: np.ndarray, rate_hz: float,
                   mocap_alive_t: ArrayLike | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`build_flight`'s mocap on the grid: (position (G, 3) m, quaternions (G, 4), mask of grid points in a
    mocap gap longer than 5 grid steps, the stamps the stream was alive at), the gaps told from
    ``mocap_alive_t`` when given (a repeated pose is not a lost frame)."""
    alive_t = t_mocap if mocap_alive_t is None else np.asarray(mocap_alive_t, dtype=float)
    p_grid, _ = resample(t_mocap, p, grid)
    mocap_gap = resample(alive_t, np.zeros(len(alive_t)), grid, max_gap_s=5.0 / rate_hz)[1]
    return p_grid, resample_quaternions(t_mocap, quat, grid), mocap_gap, alive_t


def _resample_channels(channels: dict | None, grid: np.ndarray, rate_hz: float, low_passed: list[str]):
    """`build_flight`'s optional streams on the grid, those in `ANTI_ALIAS_CHANNELS` low-passed first when
    sampled faster: ``({name: values on the grid}, low_passed + the names of those filtered)``."""
    extra = {}
    for name, (ts, vals) in (channels or {}).items():
        if name in ANTI_ALIAS_CHANNELS:
            ts, vals, channel_filtered = anti_alias(ts, vals, rate_hz)
            low_passed += [name] if channel_filtered else []
        extra[name] = resample(ts, vals, grid)[0]
    return extra, low_passed


def _grid_meta(meta: dict | None, rate_hz: float, t0: float, p: ArrayLike, t_mocap_alive: np.ndarray,
               t_acc: np.ndarray, low_passed: list[str]) -> dict:
    """`build_flight`'s metadata: ``meta`` with the grid's rate and start, the mocap's resolution, the
    streams' timing (unless the adapter gave it) and the anti-alias filter applied, if any."""
    meta = dict(meta or {})
    meta["rate_hz"] = rate_hz
    meta["t0_source_s"] = float(t0)
    meta["mocap_resolution_m"] = position_resolution(p)
    meta.setdefault("timing", {"mocap": stream_timing(t_mocap_alive), "acc": stream_timing(t_acc)})
    if low_passed:
        meta["anti_alias"] = {"streams": low_passed, "cutoff_hz": ANTI_ALIAS_CUTOFF * rate_hz,
                              "filter": f"Butterworth order {ANTI_ALIAS_ORDER}, zero phase (forwards-backwards)"}
    return meta


def _record_window(flight: Flight, grid: np.ndarray, start: int, stop: int, rule: str, cut, mocap_gap: np.ndarray,
                   acc_gap: np.ndarray) -> None:
    """Write the stretch kept (s on the recording's grid, the rule, the cut asked for) and the samples in
    gaps into ``flight.meta``."""
    flight.meta["flying_window"] = {"start_s": float(grid[start] - grid[0]),
                                    "stop_s": float(grid[stop - 1] - grid[0]),
                                    "recording_s": float(grid[-1] - grid[0]), "rule": rule,
                                    "cut": cut_text(parse_cut(cut))}
    # counted on the rows kept: gaps while the vehicle sits on the ground are not the flight's
    flight.meta["gaps"] = {"mocap_samples_in_gaps": int(mocap_gap[start:stop].sum()),
                           "acc_samples_in_gaps": int(acc_gap[start:stop].sum())}
