"""`simulate`: fly a trajectory with take-off and landing in closed loop and sample the sensors, keeping
the truth (a SimulatedFlight)."""
from __future__ import annotations

from dataclasses import dataclass

from .sensors import Imu, Mocap, SensorModel, sample_imu, sample_mocap
from .trajectories import Phases, Reference, Timing, Trajectory, reference
from .vehicle import States, Vehicle, fly


@dataclass
class SimulatedFlight:
    """A simulated flight with its truth and everything it was made from.

    Attributes
    ----------
    truth : States
        True states at every 1 kHz simulation step.
    reference : Reference
        The reference the controller tracked.
    mocap, imu : Mocap, Imu
        The sampled sensors.
    phases : Phases
        Times (s) where the flight's phases begin.
    trajectory, vehicle, sensors : Trajectory, Vehicle, SensorModel
        What the flight was simulated with.
    seed : int
        Noise seed.
    name : str
        Name of the flight.
    """
    truth: States          # every 1 kHz step
    reference: Reference
    mocap: Mocap
    imu: Imu
    phases: Phases
    trajectory: Trajectory
    vehicle: Vehicle
    sensors: SensorModel
    seed: int
    name: str = "simulated"


def simulate(trajectory: Trajectory, *, vehicle: Vehicle | None = None, sensors: SensorModel | None = None,
             timing: Timing | None = None, yaw_rad: float = 0.0, yaw_rate: float = 0.0, seed: int = 0,
             name: str = "simulated") -> SimulatedFlight:
    """Fly `trajectory` (with take-off and landing) in closed loop and sample the sensors."""
    vehicle, sensors, timing = vehicle or Vehicle(), sensors or SensorModel(), timing or Timing()
    ref, phases = reference(trajectory, timing, yaw_rad, yaw_rate)
    truth = fly(ref, phases, vehicle)
    return SimulatedFlight(truth, ref, sample_mocap(truth, sensors, seed), sample_imu(truth, ref, sensors, seed),
                           phases, trajectory, vehicle, sensors, seed, name)
