"""What every estimator and check needs of one flight under one model, built once (`prepare`).

A flight model ("quadrotor" or "crazyflie") sees a flight through its own prior parameters (a diagnosis may
have extended them), with the measurement effects it carries corrected, and with inputs whose thrust carries
the flight's thrust gain where the model was trained on it.  The evaluation (`workflows.flights`),
its envelope and prediction checks, the yardsticks and the notebook's `ukf`/`mhe` all start from this one
`PreparedFlight`, so they cannot disagree about what the model saw.  What each estimator run of the flight
is given, it gets from here as one bundle (`PreparedFlight.params`, `PreparedFlight.prior_params`).

Each of the two models runs with its own noise (`models.noise`): the KNODE with the noise identified for it,
the prior-only filters with the noise identified for the prior on the same flights, or both with the system's
fixed noise when asked for ``noise="paper"`` (or when the model never had its noise identified).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.models.effects import correct_acc_body, world_from_body
from learnest.models.ensemble import spread_variance
from learnest.models.inputs import calibrates_thrust_gain, system_inputs
from learnest.models.knode import HybridModel
from learnest.models.noise import IDENTIFIED, NOISE_SOURCES, PAPER, NoiseModel
from learnest.models.systems import System, make_system

from .params import EstimatorParams

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


def model_params(model: HybridModel, x0: np.ndarray, dt: float | None = None) -> EstimatorParams:
    """The estimator bundle of ``model`` with the noise its system carries (Q, R, P0: the model's own noise once
    `prepare` applied it, else its system's fixed settings), from the first state ``x0`` (n,), on a grid of
    ``dt`` s (default the system's): the one place a model's noise is read for an estimator run."""
    system = model.system
    return EstimatorParams(model, system.dt if dt is None else dt, system.Q, system.R, system.P0, x0)


def initial_state(flight: Flight) -> np.ndarray:
    """First state estimate x0, shape (9,): p[0] (m), the mean velocity over the first (up to) 5 steps (m/s),
    a_meas[0] (m/s²)."""
    k = min(5, len(flight.t) - 1)
    velocity = (flight.p[k] - flight.p[0]) / (k * flight.dt)
    return np.concatenate([flight.p[0], velocity, flight.a_meas[0]])


def rough_states(flight: Flight) -> np.ndarray:
    """States (T, 9) read off the measurements alone: mocap position (m), its central difference (m/s), the
    measured acceleration (m/s²).  Where an ensemble's members are asked how much they disagree on a flight: no
    filter of either model decides where they are asked."""
    return np.hstack([flight.p, np.gradient(flight.p, flight.dt, axis=0), flight.a_meas])


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
        The model's system on the flight's grid with the model's prior parameters (`model_system`) and the
        noise ``model`` runs with (its Q, R, P0).
    model : HybridModel
        The model with its system's dt set to the flight's and its noise applied.
    prior : HybridModel
        The prior-only model of ``system``, its system carrying the prior's own noise (Q, R, P0).
    u : ndarray, shape (T, p)
        Inputs (`models.inputs.system_inputs`), the thrust scaled by the flight's gain when ``thrust_gain``.
    y : ndarray, shape (T, m)
        Measurements of ``measured``: [p (m), a_meas (m/s²)].
    x0 : ndarray, shape (n,)
        First state estimate (`initial_state` of ``measured``).
    thrust_gain : bool
        Whether ``u`` carries the flight's thrust gain.
    noise : dict
        Which noise each model runs with, ``{"prior": "identified" | "paper", "knode": ...}``.
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
    noise: dict

    @property
    def dt(self) -> float:
        """Sample period of the flight, s."""
        return self.flight.dt

    @property
    def params(self) -> EstimatorParams:
        """What every estimator run of ``model`` on this flight is given (`model_params`): the model, dt, its
        own noise and ``x0``."""
        return model_params(self.model, self.x0, self.dt)

    @property
    def prior_params(self) -> EstimatorParams:
        """The same of ``prior``, with the prior's own noise: the prior-only rows of an evaluation."""
        return model_params(self.prior, self.x0, self.dt)


def noise_models(model: HybridModel, system: System, noise: str = IDENTIFIED) -> tuple[NoiseModel, NoiseModel]:
    """(the model's, its prior's) noise under the choice ``noise``: identified where the model carries it,
    else the system's fixed noise (`models.noise.NoiseModel.paper`).

    Raises
    ------
    InvalidInput
        If ``noise`` is not ``"identified"`` or ``"paper"``.
    """
    if noise not in NOISE_SOURCES:
        raise InvalidInput(f"noise must be one of {', '.join(NOISE_SOURCES)}, not {noise!r}")
    paper = NoiseModel.paper(system)
    if noise == PAPER:
        return paper, paper
    own = model.noise or paper
    prior = model.prior_noise or (own if model.kind == "prior" else paper)
    return own, prior


def prepare(model: HybridModel, flight: Flight, thrust_gain: bool | None = None,
            noise: str = IDENTIFIED) -> PreparedFlight:
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
    noise : {"identified", "paper"}
        Each model with its own identified noise (`noise_models`), or both with the system's fixed noise.

    Returns
    -------
    PreparedFlight

    Raises
    ------
    InvalidInput
        If the model's system does not model a flight or ``noise`` is unknown; `models.inputs.MissingInputs`
        when the prior needs inputs the flight lacks.
    """
    system = model_system(model, flight)
    own, prior_noise = noise_models(model, system, noise)
    measured = flight
    if model.meta.get("measurement_effects"):
        measured = corrected_flight(flight, model.meta["measurement_effects"])
    if thrust_gain is None:
        thrust_gain = calibrates_thrust_gain(model.meta, model.kind)
    u = system_inputs(flight, system, thrust_gain=thrust_gain)
    if model.residual is not None and model.residual.members:   # the ensemble's doubt on this flight
        own = own.with_model_spread(spread_variance(model.residual, rough_states(measured), u, flight.dt))
    own_system = own.apply(system)
    return PreparedFlight(flight, measured, own_system,
                          HybridModel(own.apply(replace(model.system, dt=flight.dt)), model.kind, model.residual,
                                      model.meta, model.noise, model.prior_noise),
                          HybridModel(prior_noise.apply(system), "prior", noise=prior_noise), u,
                          measured.measurements(), initial_state(measured), bool(thrust_gain),
                          {"prior": prior_noise.source, "knode": own.source})
