"""The Crazyflie firmware's log variables ("group.name") that the readers turn into Flight channels.

uSD-card logs, cfclient CSV logs and crazyswarm2's LogDataGeneric messages all carry the firmware's own
variable names, so this one table serves every reader of them.
"""
from __future__ import annotations

from .. import units

ACC = ("acc.x", "acc.y", "acc.z")                                                   # g, body frame

# Optional Flight channels: (channel, variables, converter to the channel's unit, ingest.units). The first
# source present wins.
OPTIONAL_SOURCES = (
    ("p_onboard", ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z"), units.identity),
    ("p_onboard", ("stateEstimateZ.x", "stateEstimateZ.y", "stateEstimateZ.z"), units.millimetres),  # int16 mm
    ("v_onboard", ("stateEstimate.vx", "stateEstimate.vy", "stateEstimate.vz"), units.identity),
    ("v_onboard", ("stateEstimateZ.vx", "stateEstimateZ.vy", "stateEstimateZ.vz"), units.millimetres),
    ("gyro", ("gyro.x", "gyro.y", "gyro.z"), units.degrees_per_second),
    ("setpoint", ("ctrltarget.x", "ctrltarget.y", "ctrltarget.z"), units.identity),
    ("setpoint", ("ctrltargetZ.x", "ctrltargetZ.y", "ctrltargetZ.z"), units.millimetres),
    ("motors", ("motor.m1", "motor.m2", "motor.m3", "motor.m4"), units.pwm_16bit),
    ("motors", ("pwm.m1_pwm", "pwm.m2_pwm", "pwm.m3_pwm", "pwm.m4_pwm"), units.pwm_16bit),
    ("vbat", ("pm.vbat",), units.identity),
    ("vbat", ("pm.vbatMV",), units.millivolts),
    ("rotor_speed", ("rpm.m1", "rpm.m2", "rpm.m3", "rpm.m4"), units.rpm),
    ("thrust_cmd", ("controller.cmd_thrust",), units.identity),
    ("thrust_si", ("ctrlLee.thrustSI",), units.identity),
    ("quat_onboard", ("stateEstimate.qx", "stateEstimate.qy", "stateEstimate.qz", "stateEstimate.qw"), units.identity),
    ("rpy_onboard", ("ctrlLee.rpyx", "ctrlLee.rpyy", "ctrlLee.rpyz"), units.identity),              # rad
    ("acc_onboard", ("stateEstimate.ax", "stateEstimate.ay", "stateEstimate.az"), units.standard_gravities),
    ("torque_cmd", ("ctrlLee.torquex", "ctrlLee.torquey", "ctrlLee.torquez"), units.identity),      # N m
)
