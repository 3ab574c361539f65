"""The input sequence u (T, p) a system needs, taken from a Flight's channels; a clear error otherwise.

The kinematic quadrotor needs no inputs; the Crazyflie prior needs the mocap attitude (always in a
Flight), the four motor PWM and the battery voltage.  Which log variables carry each channel is listed
so the message tells a user what their logger should have recorded.
"""
from __future__ import annotations

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight

from .systems import System
from .thrust_axis import calibrated_attitude, heading_removed, thrust_axis_offset

# channel -> what carries it in each supported format (for the error message)
CHANNEL_SOURCES = {
    "motors": "motor PWM: NanoBench motor_motor_m1..m4, uSD/cfclient motor.m1..m4 or pwm.m1_pwm..m4_pwm, "
              "MCAP/ROS 2 LogDataGeneric topics named in a crazyflies.yaml beside the recording",
    "vbat": "battery voltage: NanoBench pwr_pm_vbat, uSD/cfclient pm.vbat or pm.vbatMV, "
            "MCAP/ROS 2 LogDataGeneric topics named in a crazyflies.yaml beside the recording",
}
# system name -> the Flight channels its inputs come from, in input order after the attitude
NEEDED = {"crazyflie": ("motors", "vbat")}
# systems whose prior turns thrust into acceleration through the attitude: their attitude input is the
# mocap attitude rotated onto the flight's thrust axis, with the heading removed (`models.thrust_axis`)
THRUST_THROUGH_ATTITUDE = frozenset({"crazyflie"})
# what a model trained on such inputs records in meta["attitude_input"]
ATTITUDE_CALIBRATED = "mocap attitude calibrated onto the thrust axis, heading removed"


class MissingInputs(InvalidInput):
    """A flight without the channels a system's inputs come from."""


def missing_inputs(flight: Flight, system_name: str) -> list[str]:
    """Names of the Flight channels the named system's inputs need that ``flight`` lacks (empty if none)."""
    return [name for name in NEEDED.get(system_name, ()) if name not in flight.channels]


def flight_thrust_axis(flight: Flight) -> np.ndarray:
    """(d_x, d_y), sines of the lean (≈ rad): the flight's thrust axis in its mocap body frame
    (`models.thrust_axis`).

    Raises
    ------
    InvalidInput
        Naming the flight, if the offset is implausibly large.
    """
    try:
        return thrust_axis_offset(flight.p, flight.quat, flight.dt)
    except ValueError as err:
        raise InvalidInput(f"{flight.name}: {err}") from None


def training_meta(system: System) -> dict:
    """What a model trained on `system_inputs` of this system records about them in its meta: evaluations
    compare it (a model trained on the raw attitude is scored with a warning)."""
    return {"attitude_input": ATTITUDE_CALIBRATED} if system.name in THRUST_THROUGH_ATTITUDE else {}


def system_inputs(flight: Flight, system: System) -> np.ndarray:
    """u (T, system.n_inputs) for this flight: empty for input-free systems, [quat, PWM x4, vbat] for crazyflie,
    whose attitude is calibrated onto the flight's thrust axis (`flight_thrust_axis`) and has its heading
    removed (`models.thrust_axis.heading_removed`: the prior depends on the body z axis only)."""
    if system.n_inputs == 0:
        return np.zeros((len(flight.t), 0))
    if system.name not in NEEDED:
        raise ValueError(f"no rule for the inputs of system {system.name!r} on a Flight")
    missing = missing_inputs(flight, system.name)
    if missing:
        what = "; ".join(CHANNEL_SOURCES[name] for name in missing)
        raise MissingInputs(f"{flight.name}: the {system.name!r} prior needs inputs this flight does not carry "
                            f"({what}). The kinematic prior (system 'quadrotor') works without them.")
    quat = flight.quat
    if system.name in THRUST_THROUGH_ATTITUDE:
        offset = flight_thrust_axis(flight)
        try:
            # the heading is no physics to such a prior, and a residual must not learn the training flight's
            quat = heading_removed(calibrated_attitude(quat, offset))
        except ValueError as err:
            raise InvalidInput(f"{flight.name}: {err}") from None
    columns = [quat] + [np.asarray(flight.channels[name], float).reshape(len(flight.t), -1)
                               for name in NEEDED[system.name]]
    u = np.column_stack(columns)
    if u.shape[1] != system.n_inputs:
        raise MissingInputs(f"{flight.name}: expected {system.n_inputs} input columns for {system.name!r}, got "
                            f"{u.shape[1]} (channels {', '.join(NEEDED[system.name])})")
    return u
