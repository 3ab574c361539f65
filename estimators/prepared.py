"""What every estimator and check needs of one flight under one model, built once (`prepare`).

A flight model ("quadrotor" or "crazyflie") sees a flight through its own prior parameters (a diagnosis may
have extended them), with the measurement effects it carries corrected, and with inputs whose thrust carries
the flight's thrust gain where the model was trained on it.  The evaluation (`service.experiments.flights`),
its envelope and prediction checks, the yardsticks and the notebook's `ukf`/`mhe` all start from this one
`PreparedFlight`, so they cannot disagree about what the model saw.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.models.effects import correct_acc_body, world_from_body
from learnest.models.inputs import calibrates_thrust_gain, system_inputs
from learnest.models.knode import HybridModel
from learnest.models.systems import System, make_system

# Systems a model of a real flight may use: the paper's kinematic chain, or the Crazyflie prior driven by
# the motors and the battery (needs those channels in the flight).
FLIGHT_SYSTEMS = ("quadrotor", "crazyflie")


def system_for(flight: Flight, name: str = "quadrotor") -> System:
    """The named flight system on this flight's grid; noise settings are the system's defaults.

    Raises
    ------
    InvalidInput
        If ``name`` is not one of `FLIGHT_SYSTEMS`.
    """
    if name not in FLIGHT_SYSTEMS:
        raise InvalidInput(f"system {name!r} does not model a flight; choose one of {', '.join(FLIGHT_SYSTEMS)}")
    return make_system(name, dt=flight.dt, n_samples=len(flight.t))


def model_system(model: HybridModel, flight: Flight) -> System:
    """``model``'s system on this flight's grid with the model's own prior parameters: a diagnosis may have
    extended them, and a model trained before the motors' heating has none (`models.crazyflie.motor_heating`)."""
    return replace(system_for(flight, model.system.name), prior_params=dict(model.system.prior_params))


def initial_state(flight: Flight) -> np.ndarray:
    """First state estimate x0, shape (9,): p[0] (m), the mean velocity over the first (up to) 5 steps (m/s),
    a_meas[0] (m/s²)."""
    k = min(5, len(flight.t) - 1)
    velocity = (flight.p[k] - flight.p[0]) / (k * flight.dt)
    return np.concatenate([flight.p[0], velocity, flight.a_meas[0]])


def corrected_flight(flight: Flight, values: dict) -> Flight:
    """The flight with accelerometer effects (bias, scale, delay, misalignment) removed: the measurement
    model a diagnosis repaired, applied to the data."""
    acc_body = correct_acc_body(flight.channels["acc_body"], flight.t, values)
    return Flight(flight.t, flight.p, world_from_body(acc_body, flight.quat), flight.quat,
                  {**flight.channels, "acc_body": acc_body}, dict(flight.meta))


@dataclass(frozen=True, eq=False)
class PreparedFlight:
    """One flight as one model sees it (`prepare`).

    Attributes
    ----------
    flight : Flight
        The flight as read; its mocap position makes the references.
    measured : Flight
        The flight with the model's measurement effects corrected (``flight`` itself when it carries none).
    system : System
        The model's system on the flight's grid with the model's prior parameters (`model_system`); its Q, R,
        P0 are the estimators' noise settings.
    model : HybridModel
        The model with its system's dt set to the flight's.
    prior : HybridModel
        The prior-only model of ``system``.
    u : ndarray, shape (T, p)
        Inputs (`models.inputs.system_inputs`), the thrust scaled by the flight's gain when ``thrust_gain``.
    y : ndarray, shape (T, m)
        Measurements of ``measured``: [p (m), a_meas (m/s²)].
    x0 : ndarray, shape (n,)
        First state estimate (`initial_state` of ``measured``).
    thrust_gain : bool
        Whether ``u`` carries the flight's thrust gain.
    """

    flight: Flight
    measured: Flight
    system: System
    model: HybridModel
    prior: HybridModel
    u: np.ndarray
    y: np.ndarray
    x0: np.ndarray
    thrust_gain: bool

    @property
    def dt(self) -> float:
        """Sample period of the flight, s."""
        return self.flight.dt


def prepare(model: HybridModel, flight: Flight, thrust_gain: bool | None = None) -> PreparedFlight:
    """Build, once, what every estimator and check of ``model`` on ``flight`` needs.

    Parameters
    ----------
    model : HybridModel
        A flight model (system in `FLIGHT_SYSTEMS`), prior-only or KNODE.
    flight : Flight
        The flight.
    thrust_gain : bool, optional
        Whether the prior's thrust is scaled by the flight's thrust gain (`models.inputs.system_inputs`);
        None decides by the model (`models.inputs.calibrates_thrust_gain`); the diagnosis passes False.

    Returns
    -------
    PreparedFlight

    Raises
    ------
    InvalidInput
        If the model's system does not model a flight; `models.inputs.MissingInputs` when the prior needs
        inputs the flight lacks.
    """
    system = model_system(model, flight)
    measured = flight
    if model.meta.get("measurement_effects"):
        measured = corrected_flight(flight, model.meta["measurement_effects"])
    if thrust_gain is None:
        thrust_gain = calibrates_thrust_gain(model.meta, model.kind)
    u = system_inputs(flight, system, thrust_gain=thrust_gain)
    return PreparedFlight(flight, measured, system,
                          HybridModel(replace(model.system, dt=flight.dt), model.kind, model.residual, model.meta),
                          HybridModel(system, "prior"), u, measured.measurements(), initial_state(measured),
                          bool(thrust_gain))
