"""Signal filters shared by the Crazyflie identification, thrust-axis and thrust-gain code.

Kept apart from `models.crazyflie.identify` so the modules that only need a low-pass (`thrust_axis`, `thrust_gain`) do
not import the identification, which imports them through `models.inputs`.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

LOWPASS_HZ = 5.0   # Hz: the identification's low-pass of the accelerometer and of its predictions


def lowpass(x: np.ndarray, dt: float, cutoff_hz: float = LOWPASS_HZ) -> np.ndarray:
    """Zero-phase 2nd-order Butterworth low-pass along axis 0."""
    from scipy.signal import sosfiltfilt  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    return sosfiltfilt(_butter_sos(cutoff_hz, 1.0 / dt), x, axis=0)


@lru_cache(maxsize=16)
def _butter_sos(cutoff_hz: float, rate_hz: float) -> np.ndarray:
    from scipy.signal import butter  # scipy.signal imports scipy.stats (~1.5 s): loaded on first use

    # designed once per rate: effect selection low-passes thousands of predictions
    return butter(2, cutoff_hz, fs=rate_hz, output="sos")
