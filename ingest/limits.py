"""Plausibility limits shared by every reader and the quality checks (one place, one name each).

Values outside them are not a flight under motion capture, whatever format they came in.
"""
from __future__ import annotations

MAX_ROOM_M = 20.0                  # a motion-capture volume is smaller than this (|p| median, metres)
QUATERNION_NORM_TOLERANCE = 0.1    # a recorded attitude quaternion is within this of unit length
MAX_ACCELERATION_G = 30.0         # the Crazyflie's accelerometer reads at most ±24 g: beyond is not a measurement
MAX_DURATION_S = 3600.0            # a Crazyflie battery lasts minutes: a longer recording has corrupt time stamps
