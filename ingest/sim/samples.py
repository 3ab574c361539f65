"""The bundled sample logs: which simulated flight each file holds (SAMPLE_FLIGHTS), and `make_sample_logs`,
which writes them with their README (python -m learnest.ingest.sim.samples [DIR])."""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, NamedTuple

from .export import CFCLIENT_BOOT_S, CFCLIENT_CLOCK_OFFSET_S, CFCLIENT_RATE_HZ, USD_BOOT_S, VICON_START_S, write_flight
from .sensors import SensorModel
from .simulation import SimulatedFlight, simulate
from .trajectories import Circle, Figure8, RandomWaypoints, Trajectory

SAMPLE_CIRCLE = Circle(radius=0.5, speed=0.6, altitude=1.0, duration_s=6.5)
SAMPLE_BIAS_M_S2 = (0.15, -0.10, 0.20)


class SampleLog(NamedTuple):
    """How one sample log was made, and the note the README gives it."""
    fmt: str                          # write_flight's format
    trajectory: Trajectory
    simulate_options: dict[str, Any]  # simulate() keywords
    write_options: dict[str, Any]     # write_flight() keywords
    note: str


SAMPLE_FLIGHTS = {
    **{f"circle_rep{k}": SampleLog("nanobench", SAMPLE_CIRCLE, {"seed": k}, {}, "") for k in (1, 2, 3, 4)},
    "effects_circle_acc_bias": SampleLog("nanobench", SAMPLE_CIRCLE,
                                         {"seed": 5, "sensors": SensorModel(bias=SAMPLE_BIAS_M_S2)}, {},
                                         "constant accelerometer bias in m/s², IMU axes = body axes"),
    "pair_circle": SampleLog("vicon+cfclient", SAMPLE_CIRCLE, {"seed": 6}, {},
                             f"two clocks: t_vicon = Timestamp/1000 + ({CFCLIENT_CLOCK_OFFSET_S:.3f} s); cfclient at "
                             f"{CFCLIENT_RATE_HZ:g} Hz"),
    "usd_figure8_v2": SampleLog("usd", Figure8(size=0.6, period=6.0, altitude=1.0, duration_s=7.0), {"seed": 7}, {},
                                "locSrv sample-and-hold in the 500 Hz fixed-frequency stream (real firmware layout)"),
    "usd_circle_v1_pose_event": SampleLog("usd-v1", SAMPLE_CIRCLE, {"seed": 8}, {"usd_pose_stream": "event"},
                                          "version 1 (ms stamps); locSrv in its own event stream at the mocap frames"),
    "mcap_waypoints_ros2": SampleLog("mcap-ros2", RandomWaypoints(count=5, speed=0.5, seed=3),
                                     {"seed": 9, "yaw_rad": 0.3, "yaw_rate": 0.2}, {},
                                     "PoseStamped + sensor_msgs/Imu; yaw 0.3 rad + 0.2 rad/s along the path"),
    "mcap_figure8_json": SampleLog("mcap-json", Figure8(size=0.8, period=8.0, altitude=0.8, duration_s=7.0),
                                   {"seed": 10}, {}, "foxglove.PoseInFrame + learnest.Acceleration (g)"),
}


def sample_flight(name: str) -> SimulatedFlight:
    """The simulation behind one of the bundled sample logs (its truth included)."""
    sample = SAMPLE_FLIGHTS[name]
    return simulate(sample.trajectory, name=name, **sample.simulate_options)


def make_sample_logs(directory) -> list[Path]:
    """Write every SAMPLE_FLIGHTS log and a README.md into directory (flat: `learnest demo` reads the
    files of one folder); deterministic.  Returns the files written."""
    directory = Path(directory)
    written, rows = [], []
    for name, sample in SAMPLE_FLIGHTS.items():
        sim = sample_flight(name)
        files = write_flight(sim, sample.fmt, directory, name, **sample.write_options)
        written += files
        rows.append((files, sample.fmt, _trajectory_text(sample.trajectory), sim, sample.note))
    readme = directory / "README.md"
    readme.write_text(_readme(rows), encoding="utf-8")
    return written + [readme]


def _trajectory_text(trajectory: Trajectory) -> str:
    if isinstance(trajectory, Circle):
        return f"circle r {trajectory.radius:g} m, {trajectory.speed:g} m/s, z {trajectory.altitude:g} m"
    if isinstance(trajectory, Figure8):
        return f"figure-eight {trajectory.size:g} m, period {trajectory.period:g} s, z {trajectory.altitude:g} m"
    if isinstance(trajectory, RandomWaypoints):
        return f"{trajectory.count} random waypoints (seed {trajectory.seed}), {trajectory.speed:g} m/s"
    return type(trajectory).__name__


# The real flights copied next to the simulated ones (not written by `make_sample_logs`): NanoBench CSVs with
# their metadata sidecars; BSD-3-Clause asks for the licence and the citation beside them.
REAL_FLIGHTS = ("B2_circle_fast_rep1", "B2_circle_medium_rep1", "B3_figure8_medium_rep1", "B3_figure8_slow_rep1",
                "B6_linear_ramp_rep1")
REAL_FLIGHTS_README = """# Sample logs

## Real flights (NanoBench)

| file(s) | format | trajectory | flight |
|---|---|---|---|
{rows}

Five unmodified flights of a Crazyflie 2.1 (CF_01) under Vicon at 100 Hz with its onboard IMU, motors, battery,
setpoints and onboard estimates, from the public NanoBench dataset (repository syediu/nanobench-iros2026,
commit 0ae7d689): two circles, two figure-eights and a low linear ramp. `learnest demo sample_logs` reads the
folder in name order, so it trains on the fast circle and scores the four other real flights, each with the
95 % interval of the KNODE's gain. All pass the quality checks; the onboard streams came over the radio and
have the dataset's 20-ms gaps (the flight page shades longer ones).

License: BSD-3-Clause, `LICENSE-nanobench.txt` (the dataset's LICENSE, unchanged). Cite:
S. I. Ullah and J. Baca, "NanoBench: A Multi-Task Benchmark Dataset for Nano-Quadrotor System
Identification, Control, and State Estimation", arXiv:2603.09908, 2026.

""".format(rows="\n".join([
    "| `B2_circle_fast_rep1.csv` + `B2_circle_fast_rep1_metadata.yaml` | nanobench | circle r 1 m, 1 m/s, z 1 m "
    "| 26.8 s recorded, 18.2 s kept after the take-off/landing cut |",
    "| `B2_circle_medium_rep1.csv` + `B2_circle_medium_rep1_metadata.yaml` | nanobench | circle r 1 m, 0.75 m/s, "
    "z 1 m | 28 s recorded, 18.2 s kept |",
    "| `B3_figure8_medium_rep1.csv` + `B3_figure8_medium_rep1_metadata.yaml` | nanobench | figure-eight 1 m, "
    "0.7 m/s, z 1 m | 24.8 s recorded, 15.3 s kept |",
    "| `B3_figure8_slow_rep1.csv` + `B3_figure8_slow_rep1_metadata.yaml` | nanobench | figure-eight 1 m, "
    "0.5 m/s, z 1 m | 26 s recorded, 17.5 s kept |",
    "| `B6_linear_ramp_rep1.csv` + `B6_linear_ramp_rep1_metadata.yaml` | nanobench | linear ramp 1 m at 0.25, "
    "0.5 and 1 m/s, z 1 m | 32 s recorded, 17.7 s kept |"]))


def _readme(rows) -> str:
    nominal = SensorModel()
    lines = [
        REAL_FLIGHTS_README + "## Simulated flights",
        "",
        "Written by `python -m learnest.ingest.sim.samples sample_logs` (`make_sample_logs` in",
        "`learnest.ingest.sim.samples`): a closed-loop Crazyflie simulation (32 g, linear rotor drag 0.007 kg/s,",
        "PD + feed-forward position control, 30 ms attitude lag, 1 kHz) flying each trajectory with take-off and",
        "landing. Deterministic: the same code writes the same bytes. The truth behind a file:",
        "`learnest.ingest.sim.samples.sample_flight(stem)` (the pair: `sample_flight('pair_circle')`).",
        "",
        f"Sensors of every file: mocap {nominal.mocap_rate_hz:g} Hz with "
        f"{nominal.mocap_position_noise_m * 1e3:g} mm position and {nominal.mocap_attitude_noise_rad:g} rad "
        f"attitude noise; IMU {nominal.imu_rate_hz:g} Hz, accelerometer noise {nominal.acc_noise_g:g} g, "
        f"gyro noise {nominal.gyro_noise_rad_s:g} rad/s; no bias, scale error, delay, misalignment or low-pass.",
        "The sensors column lists every setting of a file that differs from these; there are no other effects.",
        "",
        "| file(s) | format | trajectory | flight | sensors | note |",
        "|---|---|---|---|---|---|",
    ]
    for files, fmt, trajectory, sim, note in rows:
        names = " + ".join(f"`{path.name}`" for path in files)
        flight = (f"{sim.phases.end:.1f} s (trajectory {sim.phases.fly:.1f}-{sim.phases.fly_end:.1f} s), "
                  f"seed {sim.seed}")
        changes = ", ".join(f"{name}={value}" for name, value in sim.sensors.changes().items()) or "nominal"
        lines.append(f"| {names} | {fmt} | {trajectory} | {flight} | {changes} | {note} |")
    lines += [
        "",
        "Train on one circle (`circle_rep1.csv`), evaluate on the other circles and on the other formats.",
        "Clocks: NanoBench `t` = 1.7e9 s + simulation time; uSD stamps = simulation time + "
        f"{USD_BOOT_S} s (boot); MCAP stamps start at 1.7e9 s; the Vicon export starts {VICON_START_S} s "
        f"after the cfclient log, whose Timestamp is ms since a boot {CFCLIENT_BOOT_S} s before the log "
        "(the reader estimates that offset from the data).",
        "",
    ]
    return "\n".join(lines)


if __name__ == "__main__":
    target = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[2] / "sample_logs"
    for path in make_sample_logs(target):
        print(f"{path}  {path.stat().st_size / 1024:.0f} kB")
