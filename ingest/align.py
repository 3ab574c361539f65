"""Shared normalisation: raw mocap + accelerometer streams -> a Flight on a uniform grid.

Every adapter parses its format into raw arrays with their own time stamps and calls `build_flight`;
resampling, rotation into the world frame, gravity removal and the take-off/landing cut happen here once.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from .flight import Flight, IngestError
from .frames import GRAVITY, world_acceleration

# The flying part: from TAKEOFF_SETTLE_S after the vehicle first rises FLYING_HEIGHT_M above its resting
# height, to LANDING_SETTLE_S before it last comes down below that height.
FLYING_HEIGHT_M = 0.10
TAKEOFF_SETTLE_S = 1.0
LANDING_SETTLE_S = 1.0


def uniform_grid(t_start: float, t_end: float, rate_hz: float) -> np.ndarray:
    """Times t_start + k / rate_hz (s) up to and including t_end (within 1e-9 samples)."""
    n = int(np.floor((t_end - t_start) * rate_hz + 1e-9)) + 1
    return t_start + np.arange(n) / rate_hz


def samples_per_second(t: np.ndarray | Sequence[float]) -> float | None:
    """Samples per second over a stream's span (None for fewer than 2 samples or no span)."""
    return float((len(t) - 1) / (t[-1] - t[0])) if len(t) >= 2 and t[-1] > t[0] else None


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


def flying_window(t: np.ndarray, z: np.ndarray, rate_hz: float) -> tuple[int, int, str]:
    """Indices [start, stop) of the flying part and the rule that chose them.

    ``z`` (T,) is the height, m; the resting height is the median of its first 0.5 s.
    """
    rest = np.median(z[: max(1, int(0.5 * rate_hz))])
    airborne = np.flatnonzero(z > rest + FLYING_HEIGHT_M)
    if airborne.size == 0:
        return 0, len(t), "never rose above the resting height: whole recording kept"
    start = airborne[0] + int(TAKEOFF_SETTLE_S * rate_hz)
    stop = airborne[-1] + 1 - int(LANDING_SETTLE_S * rate_hz)
    if stop <= start:
        return airborne[0], airborne[-1] + 1, "airborne too briefly to trim: airborne part kept"
    rule = (f"kept {TAKEOFF_SETTLE_S:g} s after first rising {FLYING_HEIGHT_M:g} m above the resting height "
            f"to {LANDING_SETTLE_S:g} s before last coming down below it")
    return int(start), int(stop), rule


def build_flight(path: str | Path, *, t_mocap: ArrayLike, p: ArrayLike, quat: ArrayLike, t_acc: ArrayLike,
                 acc_body_g: ArrayLike, channels: dict | None = None, rate_hz: float = 100.0,
                 meta: dict | None = None, cut: bool = True) -> Flight:
    """Resample mocap (m, scalar-last quaternions) and accelerometer (g, body frame) onto one grid.

    `channels` maps name -> (t, values) for optional streams.  Times are seconds on one clock (the caller
    applies any clock offset first).  The grid covers the time where both streams exist.

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
        Metadata to start from (``rate_hz``, ``t0_source_s``, ``flying_window``, ``gaps`` are added).
    cut : bool
        Keep only the flying part (`flying_window`).

    Returns
    -------
    Flight
        With ``a_meas`` in m/s² (world, gravity removed) and the channel ``acc_body`` (m/s², body frame).

    Raises
    ------
    IngestError
        With fewer than 2 samples in a stream, streams that overlap for less than two grid steps, or a
        flying part of fewer than 2 samples.
    """
    t_mocap, t_acc = np.asarray(t_mocap, float), np.asarray(t_acc, float)
    if len(t_mocap) < 2 or len(t_acc) < 2:
        raise IngestError(path, f"too few samples (mocap {len(t_mocap)}, accelerometer {len(t_acc)})")
    t0, t1 = max(t_mocap[0], t_acc[0]), min(t_mocap[-1], t_acc[-1])
    if t1 - t0 < 2.0 / rate_hz:
        raise IngestError(path, "mocap and accelerometer streams do not overlap in time")
    grid = uniform_grid(t0, t1, rate_hz)
    p_grid, mocap_gap = resample(t_mocap, p, grid, max_gap_s=5.0 / rate_hz)
    q_grid = resample_quaternions(t_mocap, quat, grid)
    acc_grid, acc_gap = resample(t_acc, acc_body_g, grid, max_gap_s=5.0 / rate_hz)
    extra = {name: resample(ts, vals, grid)[0] for name, (ts, vals) in (channels or {}).items()}
    extra["acc_body"] = acc_grid * GRAVITY
    meta = dict(meta or {})
    meta["rate_hz"] = rate_hz
    meta["t0_source_s"] = float(t0)
    flight = Flight(grid - grid[0], p_grid, world_acceleration(acc_grid, q_grid), q_grid, extra, meta)
    start, stop = 0, len(grid)
    if cut:
        start, stop, rule = flying_window(flight.t, flight.p[:, 2], rate_hz)
        if stop - start < 2:  # e.g. one corrupt height sample is the only "airborne" one
            raise IngestError(path, f"the flying part has {stop - start} sample(s) ({rule}): no flight to keep")
        flight = flight.slice(start, stop)
        flight.meta["flying_window"] = {"start_s": float(grid[start] - grid[0]),
                                        "stop_s": float(grid[stop - 1] - grid[0]), "rule": rule}
    # counted on the rows kept: gaps while the vehicle sits on the ground are not the flight's
    flight.meta["gaps"] = {"mocap_samples_in_gaps": int(mocap_gap[start:stop].sum()),
                           "acc_samples_in_gaps": int(acc_gap[start:stop].sum())}
    return flight
