"""Unit converters for the Crazyflie log variables that become Flight channels (one per unit).

Each converter takes the values as logged and returns them in the unit of `ingest.flight.UNITS`;
the adapters' source tables name the converter, never a bare factor, so a unit is converted in one place.
"""
from __future__ import annotations

import numpy as np

PWM_FULL_SCALE = 65535.0


def identity(values):
    """Already in the channel's unit (m, m/s, V, N, ...)."""
    return np.asarray(values, dtype=float)


def millimetres(values):
    """mm -> m (and mm/s -> m/s): the compressed int16 `stateEstimateZ.*`, `ctrltargetZ.*`."""
    return np.asarray(values, dtype=float) * 1e-3


def standard_gravities(values):
    """g -> m/s² (`stateEstimate.ax/ay/az`, the onboard estimate's acceleration, logged in g)."""
    from .frames import GRAVITY

    return np.asarray(values, dtype=float) * GRAVITY


def degrees_per_second(values):
    """deg/s -> rad/s (`gyro.*`)."""
    return np.asarray(values, dtype=float) * (np.pi / 180.0)


def millivolts(values):
    """mV -> V (`pm.vbatMV`)."""
    return np.asarray(values, dtype=float) * 1e-3


def rpm(values):
    """Revolutions per minute -> rad/s (`rpm.m1..m4` of the rpm deck)."""
    return np.asarray(values, dtype=float) * (2.0 * np.pi / 60.0)


def pwm_16bit(values):
    """16-bit PWM (`motor.m*`, `pwm.m*_pwm`): kept in counts 0..65535.  A value outside that range is not
    a PWM the firmware can write (a corrupt record): it becomes NaN, and the adapters drop such rows."""
    values = np.array(values, dtype=float)
    with np.errstate(invalid="ignore"):
        values[(values < 0.0) | (values > PWM_FULL_SCALE)] = np.nan
    return values
