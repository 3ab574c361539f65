"""Algorithm 1's data of real flights: each flight's prior, inputs and thrust gain, the checks that a training set
is one vehicle, which flights are held out whole, and what the model records of them (`estimators.algorithm1`
trains on it)."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.flight import Flight
from learnest.ingest.profile import MASS_TOLERANCE, RATE_TOLERANCE, flight_profile
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.thrust_gain import with_thrust_gain
from learnest.models.inputs import THRUST_THROUGH_ATTITUDE, flight_thrust_gain, system_for_flight_thrust, system_inputs
from learnest.models.systems import System

from .prepared import system_for

# Thrust gains (`models.crazyflie.thrust_gain`, against the prior's map with the battery voltage and the motors' heating
# already in it) of one vehicle's flights lie within a few percent of each other: the map explains the battery and
# the warm motors (CF_01's NanoBench flights, benchmarks/results/crazyflie_thrust_gain/).  A training set whose
# gains spread more than twice that (max/min above 1 + GAIN_SPREAD) is not one thrust map: another vehicle,
# motors or payload, which one residual cannot learn as one vehicle.
GAIN_SPREAD = 0.12
# A thrust command in N without the battery voltage (crazyswarm2's ctrlLee.thrustSI) leaves the battery in the
# gain: from a full to a flat LiPo (4.2 -> 3.4 V) the thrust made at one command falls by up to ~20 % (thrust ∝ V
# at one duty), so such flights may spread up to that much more.
GAIN_SPREAD_WITHOUT_BATTERY = 0.3
# By default one flight in VALIDATION_EVERY is held out whole (at least one when there are two or more).
VALIDATION_EVERY = 5


def default_validation(n_flights: int) -> list[int]:
    """Indices of the flights held out by default: round(n / `VALIDATION_EVERY`) of n (at least one when
    n >= 2, none for one flight), spread evenly through the given order and ending with the last, so a
    folder listed family by family has its held-out flights in several families."""
    if n_flights < 2:
        return []
    held = max(1, round(n_flights / VALIDATION_EVERY))
    return sorted({(k + 1) * n_flights // held - 1 for k in range(held)})


def check_one_vehicle(flights: Sequence[Flight], systems: Sequence[System], gains: Sequence[float | None]) -> None:
    """Refuse a training set whose flights are not one vehicle: different prior parameters, different declared
    vehicles or masses (`ingest.profile`), or thrust gains that spread more than `GAIN_SPREAD` (a different
    thrust map).  One residual is one vehicle's; the message names the flights on each side so the user can
    split the set.

    Raises
    ------
    InvalidInput
        Naming the disagreeing flights and what differs.
    """
    first = flights[0]
    for flight, system in zip(flights[1:], systems[1:]):
        if system.name != systems[0].name or system.prior_params != systems[0].prior_params:
            differing = sorted(k for k in {*system.prior_params, *systems[0].prior_params}
                               if system.prior_params.get(k) != systems[0].prior_params.get(k))
            raise InvalidInput(f"{flight.name} and {first.name} have different prior parameters "
                               f"({', '.join(differing) or system.name}): one model is trained on one vehicle; "
                               "train a model per vehicle")

    def groups(key) -> dict:
        by: dict = {}
        for flight in flights:
            value = key(flight)
            if value is not None:
                by.setdefault(value, []).append(flight.name)
        return by

    vehicles = groups(lambda f: (str(f.meta["vehicle"]) if f.meta.get("vehicle") else None))
    if len(vehicles) > 1:
        listed = "; ".join(f"{v}: {', '.join(names)}" for v, names in vehicles.items())
        raise InvalidInput(f"the training flights come from different vehicles ({listed}): one model is trained on "
                           "one vehicle; train a model per vehicle")
    masses = groups(lambda f: f.meta.get("mass_kg"))
    if masses and max(masses) > (1 + MASS_TOLERANCE) * min(masses):
        listed = "; ".join(f"{1000 * m:.1f} g: {', '.join(names)}" for m, names in sorted(masses.items()))
        raise InvalidInput(f"the training flights declare different masses ({listed}): another vehicle or payload; "
                           "train a model per vehicle")
    known = [(g, f.name) for g, f in zip(gains, flights) if g is not None]
    if known:
        low, high = min(known), max(known)
        with_battery = cf.thrust_source_of(systems[0].prior_params) == "pwm"
        spread = GAIN_SPREAD if with_battery else GAIN_SPREAD_WITHOUT_BATTERY
        if high[0] > (1 + spread) * low[0]:
            accounted = "battery and motor heating accounted for" if with_battery else "the battery not logged"
            raise InvalidInput(f"the training flights disagree on the thrust map: thrust gain {high[0]:.3f} on "
                               f"{high[1]} against {low[0]:.3f} on {low[1]} ({accounted}; one vehicle's flights "
                               f"lie within {100 * spread:.0f} %): another vehicle, motors or payload; train a model "
                               "per vehicle")


def flight_inputs(flight: Flight, system: str, prior_params: dict | None = None,
                  thrust_gain: bool = True) -> tuple[System, np.ndarray, float | None]:
    """Algorithm 1's inputs of one flight with the named prior: the one place a training derives its system and
    inputs from a flight.

    Parameters
    ----------
    flight : Flight
        The flight.
    system : {"quadrotor", "crazyflie"}
        The prior (`estimators.prepared.FLIGHT_SYSTEMS`).
    prior_params : dict, optional
        The prior's parameters (a diagnosis's, which already chose the thrust source); default the system's, the
        Crazyflie prior's for the thrust the flight carries (`models.inputs.system_for_flight_thrust`).
    thrust_gain : bool
        Whether the thrust carries the flight's thrust gain (the default: training); a diagnosis trains without
        it, since the gain would absorb the payload and thrust effects it looks for.

    Returns
    -------
    (System, ndarray of shape (T, p), float or None)
        The prior on the flight's grid; u = `models.inputs.system_inputs` (quaternion, thrust and battery
        columns in their log units, width 0 for the kinematic quadrotor); the flight's thrust gain for a prior
        with a thrust map and ``thrust_gain``, else None (split out for `check_one_vehicle` and the model's
        lineage).

    Raises
    ------
    InvalidInput
        If ``system`` does not model a flight; `models.inputs.MissingInputs` when the prior needs inputs the
        flight lacks.
    """
    base = system_for(flight, system)
    prior = replace(base, prior_params=dict(prior_params)) if prior_params is not None else \
        system_for_flight_thrust(base, flight)
    gain = None
    if not thrust_gain:
        u = system_inputs(flight, prior)
    elif prior.name in THRUST_THROUGH_ATTITUDE:
        u = system_inputs(flight, prior)
        gain = flight_thrust_gain(flight, prior, u)
        u = with_thrust_gain(u, gain, prior.prior_params["gamma"], cf.thrust_source_of(prior.prior_params))
    else:
        u = system_inputs(flight, prior, thrust_gain=True)
    return prior, u, gain


def pooled_profile(flights: Sequence[Flight]) -> dict:
    """The vehicle and sensor profile (`ingest.profile.flight_profile`) a model trained on ``flights`` records:
    the first flight's, with each sensor rate the median of the flights' when they all lie within
    `ingest.profile.RATE_TOLERANCE` of it, else None (the model saw several rates: none is "another" one),
    and the controller None when the flights name different ones.  An evaluation warns against it as against
    one flight's profile."""
    profiles = [flight_profile(f) for f in flights]
    merged = {**profiles[0], "rates_hz": dict(profiles[0]["rates_hz"])}
    for stream in merged["rates_hz"]:
        rates = [p["rates_hz"].get(stream) for p in profiles]
        if any(r is None for r in rates):
            merged["rates_hz"][stream] = None
            continue
        median = float(np.median(rates))
        merged["rates_hz"][stream] = round(median, 1) if all(abs(r - median) <= RATE_TOLERANCE * median
                                                             for r in rates) else None
    if len({p.get("controller") for p in profiles}) > 1:
        merged["controller"] = None
    return merged


def flight_lineage(flight: Flight, gain: float | None) -> dict:
    """What a model records of one flight it saw: {"name", "sha256" (its source files'), "samples", "dt" (s),
    "thrust_gain" where the prior has one}."""
    return {"name": flight.name, "sha256": [s["sha256"] for s in flight.meta.get("sources", [])],
            "samples": len(flight.t), "dt": flight.dt, **({"thrust_gain": round(gain, 5)} if gain else {})}
