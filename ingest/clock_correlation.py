"""The correlation behind the clock alignment (`ingest.clock`): several channels summed, the peak to a fraction
of a sample, and how tightly the data pin that peak (a block bootstrap).

A channel pairs a reference signal x (N,) with the other stream's y (M,), both band-limited, mean removed and
on one uniform grid (one axis of a vector, or a scalar).  The normalised correlation at lag m (x[n + m] against
y[n]) is

    sum over channels of the lag-m products  /  sqrt(energy of all x and of all y over the overlap at m).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The block bootstrap: blocks much longer than the band-limited signals' correlation time (~0.3 s below 3 Hz),
# lags searched within ±BOOTSTRAP_HALF_WIDTH_S of the peak, BOOTSTRAP_DRAWS draws with a fixed seed (the same
# log gives the same uncertainty).
BOOTSTRAP_BLOCK_S = 2.0
BOOTSTRAP_BLOCKS = 8
MIN_BLOCK_S = 0.5
BOOTSTRAP_HALF_WIDTH_S = 0.25
BOOTSTRAP_DRAWS = 200
MIN_BOOTSTRAP_BLOCKS = 4


@dataclass
class Channel:
    """One pair of signals to correlate.

    Attributes
    ----------
    x : ndarray, shape (N,)
        The reference stream's signal.
    y : ndarray, shape (M,)
        The other stream's signal of the same quantity, in the same units.
    """
    x: np.ndarray
    y: np.ndarray


def normalised_correlation(channels: list[Channel]) -> tuple[np.ndarray, np.ndarray]:
    """(lags (N + M - 1,), correlation in [-1, 1] at each lag) of the channels summed.

    Normalising by the overlap (not the whole signals) keeps a lag with a short but perfect overlap comparable
    with the full one; the caller bounds the overlap from below.
    """
    from scipy.signal import correlate  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    n_x, n_y = len(channels[0].x), len(channels[0].y)
    lags = np.arange(-(n_y - 1), n_x)
    raw = sum(correlate(c.x, c.y, mode="full", method="fft") for c in channels)
    cx = np.r_[0.0, np.cumsum(sum(c.x ** 2 for c in channels))]
    cy = np.r_[0.0, np.cumsum(sum(c.y ** 2 for c in channels))]
    x_start, x_stop = np.maximum(lags, 0), np.minimum(n_y + lags, n_x)
    y_start, y_stop = np.maximum(-lags, 0), np.minimum(n_y, n_x - lags)
    energy = (cx[x_stop] - cx[x_start]) * (cy[y_stop] - cy[y_start])
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = np.where(energy > 0, raw / np.sqrt(energy), 0.0)
    return lags, np.clip(ncc, -1.0, 1.0)


def overlap(lags: np.ndarray, n_x: int, n_y: int) -> np.ndarray:
    """Samples shared by x (N,) and y (M,) at each lag."""
    return np.minimum(n_y, n_x - lags) - np.maximum(0, -lags)


def parabolic_vertex(values: np.ndarray, peak: int) -> float:
    """Sub-sample position of the peak (in samples, within ±0.5) from the parabola through 3 points."""
    if peak == 0 or peak == len(values) - 1 or not np.all(np.isfinite(values[peak - 1:peak + 2])):
        return 0.0
    left, centre, right = values[peak - 1:peak + 2]
    curvature = left - 2 * centre + right
    return float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5)) if curvature < 0 else 0.0


def runner_up(ncc: np.ndarray, peak: int, main_lobe_fraction: float) -> float:
    """Best correlation outside the main lobe (the contiguous lags around the peak above ``main_lobe_fraction``
    of it): close to the peak when the motion repeats (a periodic trajectory matches itself one period later),
    so the peak cannot be told from its neighbours."""
    threshold = main_lobe_fraction * ncc[peak]
    below = ~(ncc > threshold)
    left = peak - int(np.argmax(below[peak::-1])) if below[:peak + 1].any() else -1
    right = peak + int(np.argmax(below[peak:])) if below[peak:].any() else len(ncc)
    outside = np.r_[ncc[:max(left, 0)], ncc[right:]]
    outside = outside[np.isfinite(outside)]
    return float(outside.max()) if outside.size else float("nan")


def bootstrap_spread(channels: list[Channel], lag: int, rate_hz: float, seed: int = 0) -> float:
    """1-sigma spread (s) of the correlation peak's lag over a block bootstrap of the paired samples.

    At the lags within ±BOOTSTRAP_HALF_WIDTH_S of ``lag`` (samples, x[n + lag] against y[n]), the products and
    energies are summed per block of the other stream (BOOTSTRAP_BLOCK_S, shorter for a recording of fewer than
    BOOTSTRAP_BLOCKS such blocks, never under MIN_BLOCK_S); each draw sums blocks drawn with replacement and finds
    its peak as the estimate does (the parabola's vertex).  Blocks keep the noise's and the motion's
    correlation in time.  The spread is half the central 68 % of the draws: the few draws that miss every
    manoeuvre (a take-off and a landing may time a whole flight) scatter across the width and would inflate a
    standard deviation.  A flight the motion cannot time spreads across the width (~0.1 s and more); NaN with
    fewer than MIN_BOOTSTRAP_BLOCKS blocks.
    """
    half = int(round(BOOTSTRAP_HALF_WIDTH_S * rate_hz))
    n_x, n_y = len(channels[0].x), len(channels[0].y)
    longest = min(int(round(BOOTSTRAP_BLOCK_S * rate_hz)), n_y // BOOTSTRAP_BLOCKS)
    block = max(int(round(MIN_BLOCK_S * rate_hz)), longest)
    starts = np.arange(0, n_y, block)
    if len(starts) < MIN_BOOTSTRAP_BLOCKS:
        return float("nan")
    shifts = np.arange(lag - half, lag + half + 1)
    products, energy_x, energy_y = (np.zeros((len(starts), len(shifts))) for _ in range(3))
    n = np.arange(n_y)
    for j, shift in enumerate(shifts):
        valid = (n + shift >= 0) & (n + shift < n_x)
        index = np.clip(n + shift, 0, n_x - 1)
        for c in channels:     # per block: the lag's products and both energies over the pairs that exist
            products[:, j] += np.add.reduceat(np.where(valid, c.x[index] * c.y, 0.0), starts)
            energy_x[:, j] += np.add.reduceat(np.where(valid, c.x[index] ** 2, 0.0), starts)
            energy_y[:, j] += np.add.reduceat(np.where(valid, c.y ** 2, 0.0), starts)
    draws = np.random.default_rng(seed).integers(0, len(starts), (BOOTSTRAP_DRAWS, len(starts)))
    with np.errstate(invalid="ignore", divide="ignore"):
        ncc = products[draws].sum(axis=1) / np.sqrt(energy_x[draws].sum(axis=1) * energy_y[draws].sum(axis=1))
    ncc = np.where(np.isfinite(ncc), ncc, -np.inf)
    peaks = np.argmax(ncc, axis=1)
    found = [shifts[p] + parabolic_vertex(row, p) for row, p in zip(ncc, peaks)]
    return float(np.diff(np.percentile(found, [15.87, 84.13]))[0] / 2.0 / rate_hz)


