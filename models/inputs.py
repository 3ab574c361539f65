"""The input sequence u (T, p) a system needs, taken from a Flight's channels; a clear error otherwise.

The kinematic quadrotor needs no inputs; the Crazyflie prior needs the mocap attitude (always in a
Flight), the four motor PWM and the battery voltage.  Which log variables carry each channel is listed
so the message tells a user what their logger should have recorded.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight

from . import crazyflie as cf
from .crazyflie.motor_heating import HISTORY_KEY, motor_power, with_motor_heating
from .crazyflie.thrust_axis import calibrated_attitude, heading_removed, thrust_axis_offset
from .crazyflie.thrust_gain import thrust_gain, with_thrust_gain
from .metadata import (
    ATTITUDE_CALIBRATED,  # noqa: F401  (re-exported: the inputs a model was trained on)
    ATTITUDE_CALIBRATED_FORMAT,
    THRUST_GAIN_CALIBRATED,  # noqa: F401
    THRUST_GAIN_FORMAT,
    format_meta,
    input_format,
)
from .systems import System

# channel -> what carries it in each supported format (for the error message)
CHANNEL_SOURCES = {
    "motors": "motor PWM: NanoBench motor_motor_m1..m4, uSD/cfclient motor.m1..m4 or pwm.m1_pwm..m4_pwm, "
              "MCAP/ROS 2 LogDataGeneric topics named in a crazyflies.yaml beside the recording",
    "vbat": "battery voltage: NanoBench pwr_pm_vbat, uSD/cfclient pm.vbat or pm.vbatMV, "
            "MCAP/ROS 2 LogDataGeneric topics named in a crazyflies.yaml beside the recording",
}
CHANNEL_SOURCES["rotor_speed"] = "rotor speed: uSD/cfclient/MCAP rpm.m1..m4 (rpm deck)"
CHANNEL_SOURCES["thrust_si"] = "collective thrust in N: uSD/MCAP ctrlLee.thrustSI (crazyswarm2's Lee controller)"
# system name -> the Flight channels its inputs come from, in input order after the attitude (PWM source)
NEEDED = {"crazyflie": ("motors", "vbat")}
# the Crazyflie prior's thrust source (`models.crazyflie.THRUST_SOURCES`) -> the Flight channels it needs,
# in the order a flight's own source is chosen when it carries several (PWM first: the battery matters)
SOURCE_CHANNELS = {"pwm": ("motors", "vbat"), "rpm": ("rotor_speed",), "thrust_n": ("thrust_si",)}


def flight_thrust_source(flight: Flight) -> str | None:
    """The thrust source a flight carries: "pwm" (motor PWM and battery voltage), else "rpm" (rotor speed),
    else "thrust_n" (the controller's thrust in N); None when it carries none."""
    for source, channels in SOURCE_CHANNELS.items():
        if all(name in flight.channels for name in channels):
            return source
    return None


def thrust_columns(flight: Flight, source: str) -> np.ndarray:
    """(T, 5): the four thrust columns and the battery voltage of the Crazyflie prior's inputs for
    ``source`` (`models.crazyflie.THRUST_SOURCES`): PWM, rotor speed (rad/s) or the collective thrust (N)
    over four; the voltage where the flight logs it, else V_ref (only the PWM source uses it)."""
    n = len(flight.t)
    vbat = (np.asarray(flight.channels["vbat"], float).reshape(n) if "vbat" in flight.channels
            else np.full(n, cf.V_REF))
    if source == "thrust_n":
        total = np.asarray(flight.channels["thrust_si"], float).reshape(n, -1).sum(axis=1)
        thrust = np.repeat(total[:, None] / 4.0, 4, axis=1)
    else:
        thrust = np.asarray(flight.channels["motors" if source == "pwm" else "rotor_speed"], float).reshape(n, 4)
    return np.column_stack([thrust, vbat])
# systems whose prior turns thrust into acceleration through the attitude: their attitude input is the
# mocap attitude rotated onto the flight's thrust axis, with the heading removed (`models.crazyflie.thrust_axis`)
THRUST_THROUGH_ATTITUDE = frozenset({"crazyflie"})
# A model trained on such inputs records which in its meta (`models.metadata`): the integer
# ``format_version`` and the sentence ``attitude_input``.  The battery voltage may also carry the flight's
# thrust gain (`models.crazyflie.thrust_gain`).  A model keeps being fed the inputs it was trained on: one of the
# calibrated formats, else it is scored with a warning to retrain.  (The motors' heating is a parameter of
# the prior, `kappa_th`: a model whose stored prior has none is fed no heating.)


class MissingInputs(InvalidInput):
    """A flight without the channels a system's inputs come from."""


def missing_inputs(flight: Flight, system_name: str, source: str = "pwm") -> list[str]:
    """Names of the Flight channels the named system's inputs need that ``flight`` lacks (empty if none);
    for the crazyflie prior, those of its thrust ``source``."""
    needed = SOURCE_CHANNELS[source] if system_name == "crazyflie" else NEEDED.get(system_name, ())
    return [name for name in needed if name not in flight.channels]


def driven_flights(flights: Sequence[Flight]) -> list[Flight]:
    """The flights that carry the Crazyflie prior's default inputs, motor PWM and battery voltage (nothing
    `missing_inputs` of "crazyflie"), in order."""
    return [f for f in flights if not missing_inputs(f, "crazyflie")]


def prior_for_flights(flights: Sequence[Flight], least: int | None = None) -> str:
    """The prior to train on ``flights`` when none is asked for: "crazyflie" where they carry its inputs
    (motor PWM and battery voltage: it knows the vehicle's thrust, which the kinematic prior leaves to the
    network), else "quadrotor".

    Parameters
    ----------
    flights : sequence of Flight
        The flights to train on.
    least : int, optional
        How many of them must carry the inputs (default: every one, so no flight is refused for lacking
        them).  ``learnest demo`` asks for two (it trains on one and scores the others that carry them).

    Returns
    -------
    str
        "crazyflie" or "quadrotor".
    """
    needed = len(flights) if least is None else least
    return "crazyflie" if flights and len(driven_flights(flights)) >= max(needed, 1) else "quadrotor"


def system_for_flight_thrust(system: System, flight: Flight) -> System:
    """``system`` with the Crazyflie prior of the thrust ``flight`` carries, where it lacks the system's own.

    The Crazyflie prior's default is motor PWM and battery voltage; a flight that carries rotor speed or the
    controller's thrust in N instead (`flight_thrust_source`) gets `models.crazyflie.prior_for` of that source,
    with the mass the flight declares (``meta["mass_kg"]``, e.g. crazyswarm2's info*.yaml; else Bitcraze's) and
    the rest of ``system``'s parameters.  Other systems, flights that carry the system's own source, and flights
    that carry none (`system_inputs` names what is missing) are returned as they are.
    """
    if system.name not in THRUST_THROUGH_ATTITUDE:
        return system
    carried = flight_thrust_source(flight)
    if carried is None or not missing_inputs(flight, system.name, cf.thrust_source_of(system.prior_params)):
        return system
    params = cf.prior_for(carried, flight.meta.get("mass_kg"), base=system.prior_params)
    return replace(system, prior_params=params)


def flight_thrust_axis(flight: Flight) -> np.ndarray:
    """(d_x, d_y), sines of the lean (≈ rad): the flight's thrust axis in its mocap body frame
    (`models.crazyflie.thrust_axis`).

    Raises
    ------
    InvalidInput
        Naming the flight, if the offset is implausibly large.
    """
    try:
        return thrust_axis_offset(flight.p, flight.quat, flight.dt)
    except ValueError as err:
        raise InvalidInput(f"{flight.name}: {err}") from None


def flight_thrust_gain(flight: Flight, system: System, u: np.ndarray) -> float:
    """The flight's thrust gain against ``system``'s thrust map (`models.crazyflie.thrust_gain`), from the prior's
    inputs ``u`` (T, 9) with the attitude already calibrated and the motors' heating applied.

    Raises
    ------
    InvalidInput
        Naming the flight, if the gain is implausible (the channels are not this vehicle's).
    """
    try:
        return thrust_gain(flight.p, u, flight.dt, system.prior_params)
    except ValueError as err:
        raise InvalidInput(f"{flight.name}: {err}") from None


def training_meta(system: System, thrust_gain: bool = True) -> dict:
    """What a model trained on `system_inputs` of this system records about them in its meta: evaluations
    feed it the same inputs (`calibrates_thrust_gain`; a model trained on the raw attitude is scored with a
    warning).  ``thrust_gain``: trained with the per-flight thrust gain."""
    if system.name not in THRUST_THROUGH_ATTITUDE:
        return {}
    return format_meta(THRUST_GAIN_FORMAT if thrust_gain else ATTITUDE_CALIBRATED_FORMAT)


def calibrates_thrust_gain(meta: dict | None, kind: str) -> bool:
    """Whether a model's inputs carry the per-flight thrust gain: prior-only models and models whose meta
    says they were trained on it; a KNODE trained before it (or by the diagnosis) keeps its own inputs."""
    return kind == "prior" or input_format(meta) >= THRUST_GAIN_FORMAT


def calibrates_attitude(meta: dict | None) -> bool:
    """Whether a model of a thrust-through-attitude prior was trained on the attitude evaluations make (onto the
    flight's thrust axis, heading removed): its input format (`models.metadata.input_format`) is at least
    `ATTITUDE_CALIBRATED_FORMAT`."""
    return input_format(meta) >= ATTITUDE_CALIBRATED_FORMAT


def thrust_calibration(flight: Flight, system: System, thrust_gain: bool = True) -> dict:
    """What the prior's thrust carries on this flight, for reports: ``heating_thrust_loss_pct``, the largest
    thrust loss to the motors' heating (%, `models.crazyflie.motor_heating`; only for a prior with
    ``kappa_th``), and, with ``thrust_gain``, the flight's gain against the heated map (`flight_thrust_gain`; 1
    for a prior whose voltage exponent cannot carry it)."""
    u = system_inputs(flight, system, motor_heating=False)
    out = {}
    if system.prior_params.get("kappa_th"):
        u, out["heating_thrust_loss_pct"] = with_motor_heating(u, flight.dt, system.prior_params,
                                                               flight.meta.get(HISTORY_KEY))
    if thrust_gain:
        out["thrust_gain"] = flight_thrust_gain(flight, system, u)
    return out


def system_inputs(flight: Flight, system: System, thrust_gain: bool = False,
                  motor_heating: bool = True) -> np.ndarray:
    """u (T, system.n_inputs) for this flight: empty for input-free systems, [quat, PWM x4, vbat] for crazyflie,
    whose attitude is calibrated onto the flight's thrust axis (`flight_thrust_axis`) and has its heading
    removed (`models.crazyflie.thrust_axis.heading_removed`: the prior depends on the body z axis only).  Its battery
    voltage is scaled so the prior's thrust carries the motors' heating (`models.crazyflie.motor_heating`, from the
    prior's ``kappa_th``, ``tau_th_s``; ``motor_heating=False`` leaves it to the caller, as `models.crazyflie.identify`
    does) and, with ``thrust_gain``, the flight's thrust gain (`flight_thrust_gain`); estimation asks for the
    gain, the diagnosis not (the gain would absorb the payload and thrust effects it looks for)."""
    if system.n_inputs == 0:
        return np.zeros((len(flight.t), 0))
    if system.name not in NEEDED:
        raise InvalidInput(f"no rule for the inputs of system {system.name!r} on a Flight")
    source = cf.thrust_source_of(system.prior_params)
    missing = missing_inputs(flight, system.name, source)
    if missing:
        what = "; ".join(CHANNEL_SOURCES[name] for name in missing)
        carried = flight_thrust_source(flight)
        other = (f" This flight carries thrust as {carried!r}: diagnose it with --system crazyflie, which picks "
                 f"the prior by what the flight carries." if carried and carried != source else "")
        raise MissingInputs(f"{flight.name}: the {system.name!r} prior needs inputs this flight does not carry "
                            f"({what}).{other} The kinematic prior (system 'quadrotor') works without them.")
    quat = flight.quat
    if system.name in THRUST_THROUGH_ATTITUDE:
        offset = flight_thrust_axis(flight)
        try:
            # the heading is no physics to such a prior, and a residual must not learn the training flight's
            quat = heading_removed(calibrated_attitude(quat, offset))
        except ValueError as err:
            raise InvalidInput(f"{flight.name}: {err}") from None
    u = np.column_stack([quat, thrust_columns(flight, source)])
    if u.shape[1] != system.n_inputs:
        raise MissingInputs(f"{flight.name}: expected {system.n_inputs} input columns for {system.name!r}, got "
                            f"{u.shape[1]} (channels {', '.join(SOURCE_CHANNELS[source])})")
    if system.name in THRUST_THROUGH_ATTITUDE:
        if motor_heating:
            u, _ = with_motor_heating(u, flight.dt, system.prior_params, flight.meta.get(HISTORY_KEY))
        if thrust_gain:
            u = with_thrust_gain(u, flight_thrust_gain(flight, system, u), system.prior_params["gamma"],
                                 cf.thrust_source_of(system.prior_params))
    return u


def slice_keeping_heat(flight: Flight, start: int, stop: int) -> Flight:
    """``flight.slice(start, stop)`` whose meta carries the motor power before ``start``
    (`models.crazyflie.motor_heating.HISTORY_KEY`, after any history ``flight`` itself carries), so the slice's motors
    start as warm as the flight's were there.  A flight without motor PWM and battery voltage is sliced plainly."""
    piece = flight.slice(start, stop)
    if "motors" not in flight.channels or "vbat" not in flight.channels:
        return piece
    logged = np.column_stack([flight.quat[:start], np.asarray(flight.channels["motors"], float)[:start],
                              np.asarray(flight.channels["vbat"], float).reshape(-1)[:start]])   # INPUT_NAMES order
    piece.meta[HISTORY_KEY] = list(flight.meta.get(HISTORY_KEY) or []) + motor_power(logged).tolist()
    return piece
