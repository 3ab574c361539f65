"""Savitzky–Golay reference states from mocap position (LEARNEST paper, Sec. VI).

The paper differentiates the motion-capture position with a Savitzky–Golay filter (window 150 samples
≈ 1.5 s at 100 Hz, polynomial order 2) to get reference velocity and acceleration, i.e. the quadrotor
state x = [p, ṗ, p̈].

Even windows.  scipy 1.17's `savgol_filter` accepts an even `window_length` in every mode without a
warning, but the least-squares fit is then evaluated half-way between two samples (`savgol_coeffs` uses
pos = window/2 - 0.5) while the result is stored on the sample grid: the interior output is shifted by
half a sample (5 ms at 100 Hz), and the polynomial-fitted edges of mode="interp" are not shifted, so the
series gets a jump where the two meet.  Rule applied here: an even window is rounded up to the next odd
length (150 -> 151) so the fit is centred on each sample; the length used is returned as `window_used`.
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from learnest.errors import InvalidInput

if TYPE_CHECKING:
    from .flight import Flight

PAPER_WINDOW = 150
PAPER_ORDER = 2


def centred_window(window: int) -> int:
    """The odd window actually used: even lengths are rounded up so the fit is centred on a sample."""
    window = int(window)
    return window + 1 if window % 2 == 0 else window


def _validated_series(p) -> np.ndarray:
    try:
        series = np.asarray(p, dtype=float)
    except (TypeError, ValueError):
        raise InvalidInput("positions must be numeric") from None
    if series.ndim not in (1, 2):
        raise InvalidInput(f"positions must be (T,) or (T, k), got shape {series.shape}")
    if not np.all(np.isfinite(series)):
        raise InvalidInput(f"positions contain {int(np.sum(~np.isfinite(series)))} NaN/inf value(s); "
                         "fill or cut the gaps before differentiating")
    return series


def _validated_window(window, order, n_samples: int) -> int:
    if int(window) != window or int(order) != order or window < 1 or order < 0:
        raise InvalidInput(f"window ({window}) must be a positive integer and order ({order}) a non-negative one")
    if order >= window:
        raise InvalidInput(f"polynomial order {order} must be smaller than the window ({window} samples)")
    used = centred_window(window)
    if used > n_samples:
        raise InvalidInput(f"window of {used} samples is longer than the series ({n_samples} samples)")
    return used


def sg_references(p: ArrayLike, dt: float, window: int = PAPER_WINDOW, order: int = PAPER_ORDER) -> dict:
    """Smoothed position, velocity and acceleration of a uniformly sampled position series.

    p: (T,) or (T, k) positions; dt: sample spacing in s.  Returns dict(p, v, a, window_used).
    Edges use scipy's mode="interp" (a polynomial fitted to the first/last window), so no padding is
    invented; derivatives are least-squares polynomial derivatives, scaled by dt.

    Raises
    ------
    InvalidInput
        For non-numeric or non-finite positions, a bad ``dt``, ``window`` or ``order``, or a window
        longer than the series.
    """
    from scipy.signal import savgol_filter  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    series = _validated_series(p)
    if not (np.isfinite(dt) and dt > 0):
        raise InvalidInput(f"dt must be a positive number of seconds, got {dt}")
    used = _validated_window(window, order, len(series))
    smooth = {name: savgol_filter(series, used, int(order), deriv=deriv, delta=dt, axis=0, mode="interp")
              for name, deriv in (("p", 0), ("v", 1), ("a", 2))}
    return {**smooth, "window_used": used}


def references(flight: Flight, window: int = PAPER_WINDOW, order: int = PAPER_ORDER) -> np.ndarray:
    """(T, 9) reference states [p (m), v (m/s), a (m/s²)] of a Flight, matching the quadrotor state
    x = [p, ṗ, p̈]; SG of ``flight.p`` with ``window`` samples (see `sg_references`)."""
    ref = sg_references(flight.p, flight.dt, window, order)
    return np.column_stack([ref["p"], ref["v"], ref["a"]])
