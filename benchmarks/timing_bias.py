"""Timing-bias study (the accelerometer's delay and the clocks' alignment): known accelerometer delays and clock
offsets, recovered stage by stage, to find where a time shift enters.

For each injected delay the simulator (rotor drag on, the accelerometer's 30 Hz first-order low-pass on)
flies one flight; its accelerometer delay is recovered by the diagnosis's own fit of the ``accel_delay``
effect alone (`workflows.diagnosis.accelerometer_problem` + `models.diagnosis.fit`):

  memory      the simulated arrays handed to ingest.align.build_flight directly (no file)
  <format>    written by ingest.sim.write_flight and read back by ingest.read_flights
  vicon+cfclient (given)  the pair read with the true clock offset given

The truth is the injected delay plus the low-pass's group delay (SensorModel.accelerometer_group_delay_s).
For vicon+cfclient the estimated clock offset's error is printed too (estimate minus the true offset).

    python benchmarks/timing_bias.py [--seeds 0 1 2] [--out benchmarks/results/timing_bias.md]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from learnest.ingest import read_flights
from learnest.ingest.align import build_flight
from learnest.ingest.formats.vicon_cfclient.reader import read_pair
from learnest.ingest.sim import RandomWaypoints, SensorModel, simulate, write_flight
from learnest.ingest.sim.export import CFCLIENT_CLOCK_OFFSET_S
from learnest.models.diagnosis import fit
from learnest.models.effects import LIBRARY
from learnest.workflows.diagnosis import accelerometer_problem

DELAYS_S = (0.0, 0.02, 0.04, 0.06)
FORMATS = ("nanobench", "usd-v1", "usd", "vicon+cfclient", "mcap-ros2")
LOWPASS_HZ = 30.0


def recovered_delay_s(flight) -> float:
    """The diagnosis's fit of accel_delay alone on one flight, s."""
    problem = accelerometer_problem([flight])
    return fit(problem, [LIBRARY["accel_delay"]]).values["delay_s"]


def in_memory_flight(sim):
    return build_flight("memory", t_mocap=sim.mocap.t, p=sim.mocap.p, quat=sim.mocap.quat, t_acc=sim.imu.t,
                        acc_body_g=sim.imu.acc_g)


def study(seeds, directory: Path) -> list[str]:
    rows = ["| seed | injected ms | truth ms | stage | recovered ms | error ms | clock offset error ms |",
            "|---|---|---|---|---|---|---|"]
    for seed in seeds:
        for delay in DELAYS_S:
            sensors = SensorModel(delay_s=delay, lowpass_hz=LOWPASS_HZ)
            truth = delay + sensors.accelerometer_group_delay_s()
            sim = simulate(RandomWaypoints(count=14, speed=0.8, seed=seed), sensors=sensors, seed=seed)
            results = [("memory", recovered_delay_s(in_memory_flight(sim)), "")]
            for fmt in FORMATS:
                files = write_flight(sim, fmt, directory, f"s{seed}_d{int(delay * 1000)}_{fmt.replace('+', '_')}")
                # the simulated IMU's first-order filter is not the Crazyflie firmware's, which the pair's reader
                # declares by default: none is declared, so the whole lag shows in the clock offset
                flight = read_pair(*files, accel_lowpass=None) if fmt == "vicon+cfclient" else read_flights(files)[0]
                offset = ""
                if fmt == "vicon+cfclient":
                    offset = f"{(flight.meta['clock_offset_s'] - CFCLIENT_CLOCK_OFFSET_S) * 1000:+.1f}"
                results.append((fmt, recovered_delay_s(flight), offset))
                if fmt == "vicon+cfclient":
                    given = read_pair(*files, clock_offset_s=CFCLIENT_CLOCK_OFFSET_S)
                    results.append((f"{fmt} (offset given)", recovered_delay_s(given), ""))
            for stage, value, offset in results:
                rows.append(f"| {seed} | {delay * 1000:g} | {truth * 1000:.2f} | {stage} | {value * 1000:.2f} | "
                            f"{(value - truth) * 1000:+.2f} | {offset} |")
            print("\n".join(rows[-len(results):]), flush=True)
    return rows


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        rows = study(args.seeds, Path(tmp))
    if args.out:
        command = "python benchmarks/timing_bias.py " + " ".join(sys.argv[1:] if argv is None else argv)
        args.out.write_text("\n".join([
            "# Timing bias: known accelerometer delays and clock offsets, recovered", "",
            f"Command: `{command.strip()}` ({time.perf_counter() - started:.0f} s wall).", "",
            *rows, ""]), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
