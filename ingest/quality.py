"""Is a canonical Flight fit to train or evaluate an estimator?  `assess` answers with reasons.

Every check looks at the canonical arrays only (plus `meta["gaps"]`), so it works for any adapter.  The
flight is normally already cut to its flying part (ingest.flight_span.find_flight), so take-off and
touchdown transients are not judged here.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike
from scipy.ndimage import median_filter

from .baseline import sg_references
from .frames import GRAVITY
from .limits import MAX_ACCELERATION_G, MAX_ROOM_M

if TYPE_CHECKING:
    from .flight import Flight

# -- thresholds (each with why) -------------------------------------------------------------------------
# Shorter than this, the 1.5 s reference filter and any estimator warm-up leave too little to evaluate.
MIN_FLYING_S = 5.0
# The grid must be uniform; 1 % of dt is far above float rounding yet far below a dropped sample.
GRID_JITTER_FRACTION = 0.01

# Over a flight that begins and ends in hover the mean vertical acceleration is ~0, so the mean specific
# force |f| is at least 1 g (Jensen); allow 10 % for accelerometer scale error.
MIN_MEAN_ACC_G = 0.9
# A Crazyflie's thrust-to-weight ratio is ~2; a mean |f| above 1.5 g means an average bank > 48° for the
# whole flight, which no tracking flight does.
MAX_MEAN_ACC_G = 1.5
# An accelerometer in m/s² read as g gives mean |f| ≈ 9.8 g (96 m/s²); this band around 9.8 names that.
MS2_AS_G_BAND = (6.5, 14.0)
# The smallest full-scale range of Crazyflie IMUs (MPU-9250 ±2 g, BMI088 ±3 g) is 2 g: an extreme at or
# above it that repeats exactly is a rail, because sensor noise never repeats a value at random.
RAIL_MIN_G = 2.0
RAIL_MIN_REPEATS = 3
# Beyond ±16 g (a common full-scale setting) a reading is clipped or garbage for a 30 g quadrotor.
HARD_RAIL_G = 16.0
# Spikes: a sample that leaves the median of its ±3 neighbours by more than 3 g.  Onboard-filtered
# Crazyflie acceleration moves < 0.05 g between neighbours in flight (NanoBench: max 0.034 g), and the
# thrust cannot jump by g's for a single 10 ms sample; touchdown impacts are outside the flying window.
SPIKE_G = 3.0
SPIKE_NEIGHBOURHOOD = 7

# Accelerometer/mocap gaps: the longest stretch without a measured sample while airborne.  Radio
# dropouts in NanoBench last <= 0.17 s; beyond 0.5 s the vehicle moves ~0.5 m at 1 m/s with nothing but
# interpolation in between, and a lost link (stream stops in mid-air) shows up as seconds.
MAX_GAP_S = 0.5
# Resampled samples lying on the straight line through their neighbours to this relative precision are
# interpolation (float64 rounding ~1e-15); real sensor noise is many orders of magnitude larger.
COLLINEAR_RTOL = 1e-9
# More than a quarter of the samples inside gaps means the nominal rate is largely interpolation.
MAX_GAP_FRACTION = 0.25
# Vicon/OptiTrack report sub-millimetre noise at µm resolution, so a flying vehicle never repeats its
# position exactly; 0.1 s of identical positions is a frozen or held mocap stream.
FROZEN_MOCAP_S = 0.1
# A pose rounded to a coarse step (1 mm: crazyswarm2's extpos as uSD locSrv) repeats while a hovering vehicle
# moves less than the step.  A stretch (constant or interpolated) across which the position changes by at most
# RESOLUTION_STEPS steps is explained by the rounding: neither frozen nor a gap.  A held pose while the vehicle
# moved on ends with a jump of many steps.
RESOLUTION_STEPS = 2.0

# Unit mix-up for positions: a motion-capture room is < 20 m across.

# Mocap vs accelerometer: correlation of the SG second derivative of p with the equally smoothed a_meas
# (per-axis means removed, axes pooled).  Clean NanoBench flights: 0.94-0.99.  Swapped axes, a wrong
# sign, a wrong rotation or a time offset of a large part of a manoeuvre drive it towards 0 or below.
MIN_ACC_CORRELATION = 0.5
# Over a flight that starts and ends in hover the mean true acceleration is Δv/T ≈ 0 (NanoBench: a_meas
# minus p̈ averages <= 0.51 m/s², a ~3° IMU/marker tilt offset).  A mean offset above 1 m/s² (≈ 6° of
# attitude error) means the rotation is wrong (quaternion order/convention, body axes) or g not removed.
MAX_MEAN_ACC_OFFSET_MS2 = 1.0
# Below this reference acceleration (rms after removing the mean, m/s²) the flight is a hover and the
# correlation is only noise.
MIN_EXCITATION_MS2 = 0.2
SMOOTHING_WINDOW = 150   # as the SG references (paper Sec. VI)


def assess(flight: Flight) -> dict:
    """{"ok": bool, "issues": [reason, ...]} for a canonical Flight.

    Checks time stamps, finiteness and position units first, then physical plausibility; if either stage
    finds a problem, its issues are returned alone.  Otherwise: duration, accelerometer level, saturation,
    spikes, gaps, frozen mocap, and the agreement of a_meas with the mocap's second derivative.
    """
    # broken time or impossible numbers make the statistics below meaningless (and overflow): stop there
    for stage in ((_check_time, _check_finite, _check_position_units), (_check_plausible,)):
        issues = [issue for check in stage for issue in check(flight)]
        if issues:
            return {"ok": False, "issues": issues}
    for check in (_check_duration, _check_acc_level,
                  _check_saturation, _check_spikes, _check_gaps, _check_frozen_mocap, _check_acc_vs_mocap):
        issues.extend(check(flight))
    return {"ok": not issues, "issues": issues}


# -- time and size --------------------------------------------------------------------------------------
def _check_time(flight) -> list[str]:
    dt = np.diff(np.asarray(flight.t, dtype=float))
    if dt.size == 0:
        return ["fewer than 2 samples"]
    if not np.all(dt > 0):
        return [f"time is not strictly increasing ({int(np.sum(~(dt > 0)))} step(s) <= 0)"]
    step = float(np.median(dt))
    if np.max(np.abs(dt - step)) > GRID_JITTER_FRACTION * step:
        return [f"time grid is not uniform (steps from {dt.min():.4g} to {dt.max():.4g} s)"]
    return []


def _check_finite(flight) -> list[str]:
    bad = {name: int(np.sum(~np.isfinite(arr))) for name, arr in
           (("p", flight.p), ("a_meas", flight.a_meas), ("quat", flight.quat))}
    bad = {name: count for name, count in bad.items() if count}
    return [f"non-finite values: {bad}"] if bad else []


def _check_plausible(flight) -> list[str]:
    """Per sample, not only on the median: one row in seven at |p| = 1e308 m must not pass as a flight."""
    issues = []
    outside = np.abs(flight.p) > MAX_ROOM_M
    if np.any(outside):
        rows = int(np.sum(np.any(outside, axis=1)))
        issues.append(f"physically impossible positions: {rows} sample(s) beyond {MAX_ROOM_M:g} m "
                      f"(largest |p| component {np.nanmax(np.abs(flight.p)):.3g} m)")
    too_fast = np.abs(flight.a_meas) > MAX_ACCELERATION_G * GRAVITY
    if np.any(too_fast):
        rows = int(np.sum(np.any(too_fast, axis=1)))
        issues.append(f"physically impossible accelerations: {rows} sample(s) beyond {MAX_ACCELERATION_G:g} g")
    return issues


def _check_duration(flight) -> list[str]:
    duration = flight.duration_s
    if duration < MIN_FLYING_S:
        return [f"flying part too short: {duration:.2f} s < {MIN_FLYING_S:g} s"]
    return []


# -- units ----------------------------------------------------------------------------------------------
def _check_position_units(flight) -> list[str]:
    median_p = _nanmedian(np.linalg.norm(flight.p, axis=1))
    if median_p > MAX_ROOM_M:
        return [f"positions look like millimetres: median |p| = {median_p:.4g} m (room < {MAX_ROOM_M:g} m)"]
    return []


def _check_acc_level(flight) -> list[str]:
    mean_g = _nanmean(np.linalg.norm(_acc_body(flight), axis=1)) / GRAVITY
    if MS2_AS_G_BAND[0] <= mean_g <= MS2_AS_G_BAND[1]:
        return [f"accelerometer looks like m/s² read as g: mean |acc_body| = {mean_g * GRAVITY:.1f} m/s² "
                f"({mean_g:.2f} g, expected ≈ 1 g)"]
    if not MIN_MEAN_ACC_G <= mean_g <= MAX_MEAN_ACC_G:
        return [f"implausible accelerometer: mean |acc_body| = {mean_g:.3f} g over the flight, a flying "
                f"quadrotor averages ≈ 1 g (allowed {MIN_MEAN_ACC_G:g}-{MAX_MEAN_ACC_G:g} g)"]
    return []


# -- accelerometer defects ------------------------------------------------------------------------------
def _check_saturation(flight) -> list[str]:
    acc_g = _acc_body(flight) / GRAVITY
    issues = []
    for axis, values in zip("xyz", acc_g.T):
        values = values[np.isfinite(values)]
        if values.size == 0:
            continue
        extreme = float(np.max(np.abs(values)))
        repeats = int(np.sum(np.abs(values) == extreme))
        if extreme >= HARD_RAIL_G or (extreme >= RAIL_MIN_G and repeats >= RAIL_MIN_REPEATS):
            issues.append(f"accelerometer saturation on {axis}: |acc| reaches {extreme:.2f} g "
                          f"({repeats} sample(s) exactly at that value)")
    return issues


def _check_spikes(flight) -> list[str]:
    acc = _acc_body(flight)
    if len(acc) < SPIKE_NEIGHBOURHOOD:
        return []
    neighbours = median_filter(acc, size=(SPIKE_NEIGHBOURHOOD, 1), mode="nearest")
    deviation = np.max(np.abs(acc - neighbours), axis=1) / GRAVITY
    spikes = np.flatnonzero(deviation > SPIKE_G)
    if spikes.size:
        return [f"{spikes.size} accelerometer spike(s) > {SPIKE_G:g} g above their neighbours "
                f"(largest {np.nanmax(deviation):.1f} g at t = {flight.t[spikes[0]]:.2f} s)"]
    return []


# -- gaps, occlusions, frozen mocap ---------------------------------------------------------------------
def _check_gaps(flight) -> list[str]:
    gaps = flight.meta.get("gaps", {}) or {}
    issues = []
    resolution = mocap_resolution(flight)
    for stream, values, step in (("mocap", flight.p, resolution), ("acc", _acc_body(flight), 0.0)):
        # The adapter may know of gaps the grid cannot show (a stream which ends in mid-air ends the grid).
        reported = gaps.get(f"{stream}_longest_gap_airborne_s") or 0.0
        longest = max(interpolated_stretch_s(values, flight.dt, step), reported)
        if longest > MAX_GAP_S:
            issues.append(f"{stream} stream missing for {longest:.2f} s in flight (longest gap; allowed "
                          f"{MAX_GAP_S:g} s) — link lost or occluded")
        in_gaps = gaps.get(f"{stream}_samples_in_gaps", 0)   # counted by build_flight on the rows kept
        fraction = in_gaps / max(len(flight.t), 1)
        if fraction > MAX_GAP_FRACTION:
            issues.append(f"{stream}: {in_gaps} samples ({fraction:.0%}) fall into gaps "
                          f"(allowed {MAX_GAP_FRACTION:.0%})")
    return issues


def interpolated_stretch_s(values: ArrayLike, dt: float, resolution: float = 0.0) -> float:
    """Longest stretch (s) over which a resampled stream is a straight line: build_flight interpolates
    linearly across missing samples, while measured data is never collinear to 1e-9 (sensor noise).
    A held (constant) stream counts too: it is a line of slope zero.

    ``resolution`` (the step the values are rounded to, 0 for none; see `mocap_resolution`): a stretch
    across which the values change by at most RESOLUTION_STEPS steps is the rounding, not a gap.
    """
    values = np.asarray(values, dtype=float)
    if len(values) < 3 or not np.isfinite(dt):
        return 0.0
    midpoint = 0.5 * (values[:-2] + values[2:])
    tolerance = COLLINEAR_RTOL * np.maximum(1.0, np.abs(values[1:-1]))
    on_line = np.all(np.abs(values[1:-1] - midpoint) <= tolerance, axis=1)
    longest_run = 0
    for start, stop in _runs(on_line):   # samples start+1 .. stop lie on the line from start to stop+1
        change = np.max(np.abs(values[stop + 1] - values[start]))
        if resolution > 0 and change <= RESOLUTION_STEPS * resolution * (1 + 1e-6):
            continue
        longest_run = max(longest_run, stop - start)
    return float((longest_run + 1) * dt) if longest_run else 0.0


def mocap_resolution(flight: Flight) -> float:
    """The step (m) the flight's mocap positions are rounded to: ``meta["mocap_resolution_m"]`` as
    `ingest.align.build_flight` measured it on the samples, else 0 (Vicon-grade)."""
    return float(flight.meta.get("mocap_resolution_m") or 0.0)


def _check_frozen_mocap(flight) -> list[str]:
    min_run = max(2, int(round(FROZEN_MOCAP_S / flight.dt))) if len(flight.t) > 1 else 2
    same_as_previous = np.r_[False, np.all(np.diff(flight.p, axis=0) == 0, axis=1)]
    acc = _acc_body(flight)
    resolution = mocap_resolution(flight)
    issues = []
    for start, stop in _runs(same_as_previous):
        start -= 1  # the first sample of the frozen value
        if stop - start < min_run:
            continue
        # rounded to a coarse step, a slowly moving vehicle repeats its position: the rounding, unless the
        # position jumps by more than a step or two when it moves again (the vehicle went on while held)
        after = flight.p[min(stop, len(flight.p) - 1)]
        if resolution > 0 and np.max(np.abs(after - flight.p[start])) <= RESOLUTION_STEPS * resolution * (1 + 1e-6):
            continue
        # The accelerometer still reports a changing airframe: the mocap froze, not the vehicle.
        if np.ptp(acc[start:stop], axis=0).max() > 0:
            issues.append(f"mocap position frozen for {(stop - start) * flight.dt:.2f} s from t = "
                          f"{flight.t[start]:.2f} s while the accelerometer kept changing (held/occluded)")
    return issues


def _runs(mask: np.ndarray):
    """(start, stop) of each run of True values."""
    edges = np.diff(np.r_[0, mask.astype(int), 0])
    return zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1))


# -- mocap vs accelerometer -----------------------------------------------------------------------------
def acc_mocap_correlation(flight: Flight, window: int = SMOOTHING_WINDOW) -> float | None:
    """Pearson correlation of SG-smoothed a_meas with the SG second derivative of p, axes pooled after
    removing each axis' mean (a constant bias is a calibration matter, not misalignment).  None when the
    flight is too short for the window or too calm to tell."""
    from scipy.signal import savgol_filter  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    if not np.all(np.isfinite(flight.a_meas)):
        return None   # reported by the finiteness check
    try:
        reference = sg_references(flight.p, flight.dt, window=window)
    except ValueError:
        return None
    a_ref = reference["a"]
    a_meas = savgol_filter(flight.a_meas, reference["window_used"], 2, axis=0, mode="interp")
    a_ref, a_meas = a_ref - a_ref.mean(axis=0), a_meas - a_meas.mean(axis=0)
    if not (np.sqrt(np.mean(a_ref ** 2) * 3) >= MIN_EXCITATION_MS2 and np.all(np.isfinite(a_meas))):
        return None
    return float(np.sum(a_ref * a_meas) / np.sqrt(np.sum(a_ref ** 2) * np.sum(a_meas ** 2)))


def _check_acc_vs_mocap(flight) -> list[str]:
    issues = []
    offset = _mean_acc_offset(flight)
    if offset is not None and offset > MAX_MEAN_ACC_OFFSET_MS2:
        issues.append(f"mocap and accelerometer disagree: mean a_meas is {offset:.2f} m/s² away from the "
                      f"mean of p̈ (allowed {MAX_MEAN_ACC_OFFSET_MS2:g}) — wrong attitude convention/axes "
                      f"or gravity")
    correlation = acc_mocap_correlation(flight)
    if correlation is not None and correlation < MIN_ACC_CORRELATION:
        issues.append(f"mocap and accelerometer disagree: correlation of a_meas with p̈ (SG) is "
                      f"{correlation:.2f} < {MIN_ACC_CORRELATION:g} — misaligned in time, wrong "
                      f"axes/rotation or wrong data")
    return issues


def _mean_acc_offset(flight) -> float | None:
    """|mean a_meas - mean p̈| (m/s²), p̈ from the flight's first to last mocap velocity."""
    if len(flight.t) < 3 or not (flight.dt > 0 and flight.duration_s > 0):
        return None
    v = np.gradient(flight.p, flight.dt, axis=0)
    mean_reference = (v[-1] - v[0]) / flight.duration_s
    return float(np.linalg.norm(np.nanmean(flight.a_meas, axis=0) - mean_reference))


# -- helpers --------------------------------------------------------------------------------------------
def _acc_body(flight) -> np.ndarray:
    """Body-frame specific force (m/s²); every adapter provides it, else rebuild it from a_meas."""
    acc = flight.channels.get("acc_body")
    if acc is None:  # |specific force| is rotation-invariant, so the world-frame version serves the checks
        acc = np.asarray(flight.a_meas) + np.array([0.0, 0.0, GRAVITY])
    return np.asarray(acc, dtype=float)


def _nanmean(values) -> float:
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return float(values.mean()) if values.size else float("nan")


def _nanmedian(values) -> float:
    values = np.asarray(values, dtype=float)
    values = values[np.isfinite(values)]
    return float(np.median(values)) if values.size else float("nan")
