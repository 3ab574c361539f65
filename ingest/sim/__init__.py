"""A closed-loop Crazyflie simulator that writes every supported log format, with the truth kept.

Model (world frame z-up, SI units, quaternions scalar-last as in ingest.flight):
  translation   m p̈ = T R e3 − m g e3 − k_drag v        (linear rotor drag, isotropic)
  control       a_cmd = a_ref + Kp (p_ref − p) + Kd (v_ref − v);  F = m (a_cmd + g e3);
                desired body z along F, desired yaw from the reference;  T = F · (R e3), clamped to
                [0, max_thrust] (the thrust acts along the *current* body z, as in Lee/Mellinger)
  attitude      first-order lag towards the desired attitude (time constant τ, yaw included): every
                step rotates the body by the fraction 1 − exp(−dt/τ) of the rotation that is left
  integration   1 kHz, control held over each step (the firmware's loop rate).  Translation by
                semi-implicit Euler (v += a dt, then p += v dt): the recorded a_k is then *exactly* the
                central second difference of the recorded positions, so the truth is self-consistent to
                machine precision; the attitude step is the exact solution of the lag for a target held
                over the step, and the body rate is that step's rotation / dt (integrating the true gyro
                reproduces the true attitudes exactly).
  ground        the vehicle rests (v = a = 0, motors off) level before take-off, and after the landing
                reference reaches the ground where and as it touched down (within mm of z = 0).

Flight timeline (Timing): sit on the ground, take off vertically (minimum-jerk) to the trajectory's start,
hover, fly the trajectory (its speed ramps up and down smoothly), hover, land vertically, sit.  So the
take-off/landing cut of ingest.align applies as on real logs.

Sensors (SensorModel, all parameters known):
  mocap          100 Hz: position + white noise (0.5 mm), attitude · exp(white rotation noise)
  accelerometer  500 Hz, body specific force f = R^T (p̈ + g e3) in g, then in this order:
                 misalignment (IMU frame = body rotated by roll, then pitch:  f_imu = R_mis^T f),
                 scale and bias (IMU axes, bias in m/s²), first-order low-pass (`lowpass_hz`, run at
                 1 kHz), delay (the sample stamped t holds the value of t − delay_s), white noise (g)
  gyro           same stamps, misalignment and delay as the accelerometer; white noise (rad/s)

`write_flight` writes a SimulatedFlight as nanobench, usd, usd-v1, vicon+cfclient, mcap-ros2 or mcap-json;
`write_canonical_flight` writes any Flight (e.g. one flown by `models.crazyflie.simulate_crazyflie`) with the inputs it
carries (motor PWM, battery voltage, gyro, setpoint) as nanobench, usd, usd-v1, vicon+cfclient or mcap-ros2
(crazyswarm2 LogDataGeneric topics /cf1/<channel> and the <stem>_crazyflies.yaml that names their values),
and as cfclient (the CSV carrying the pose), mcap-json, rosbag-db3, rosbag-mcap or rosbag-ros1
(ALL_CANONICAL_FORMATS; MOTOR_FORMATS carry the motor PWM);
`sim_times` maps a Flight read back from those files onto simulation time; `make_sample_logs` writes the
bundled sample_logs/ (python -m learnest.ingest.sim.samples [DIR]).

Modules: `trajectories` (paths, timing and the reference over the whole flight), `vehicle` (the vehicle,
its closed loop and the true states), `sensors` (the sensor model and the sampled mocap and IMU records),
`simulation` (`simulate`: one SimulatedFlight), `export` (`write_flight`, `sim_times`), `samples` (the
bundled sample logs: `sample_flight`, `make_sample_logs`).  The names below are the simulator's public surface.
"""
from .export import (
    ALL_CANONICAL_FORMATS,
    CANONICAL_FORMATS,
    FORMATS,
    MOTOR_FORMATS,
    sim_times,
    write_canonical_flight,
    write_flight,
)
from .sensors import SensorModel
from .simulation import SimulatedFlight, simulate
from .trajectories import Circle, Figure8, RandomWaypoints, Timing, Trajectory
from .vehicle import Vehicle

__all__ = ["ALL_CANONICAL_FORMATS", "MOTOR_FORMATS",
           "CANONICAL_FORMATS", "FORMATS", "Circle", "Figure8", "RandomWaypoints", "SensorModel", "SimulatedFlight",
           "Timing", "Trajectory", "Vehicle", "sim_times", "simulate", "write_canonical_flight", "write_flight"]
