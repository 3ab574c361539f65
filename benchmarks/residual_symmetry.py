"""Does a residual trained on counter-clockwise circles score the same on clockwise ones?

Simulated Crazyflie flights with a 3-fold rotor drag (the prior's `k_xy` too small), 20 s each: five circling
counter-clockwise train one pooled KNODE; three other seeds are scored, each flown both ways (mirror images of each
other: same radius, speeds and climbs).  The score is the one-step prediction error (eq. 8) on each flight's
observer states; the gain is 100 (1 − KNODE / prior).  Three residuals, trained alike: the body frame
(`models.residual_frame`, the Crazyflie's), the state frame blind to the attitude (the pooled default before the
body frame), and the state frame reading the attitude.

    python benchmarks/residual_symmetry.py [--out benchmarks/results/residual_symmetry]
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from learnest.estimators.algorithm1 import Algorithm1
from learnest.estimators.prepared import system_for
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.knode import HybridModel
from learnest.models.presets import CRAZYFLIE_TRAINING
from learnest.workflows.flights import train_on_flights

DRAG_TRUTH = {**cf.IDENTIFIED, "k_xy": 3 * cf.IDENTIFIED["k_xy"]}
RESIDUALS = (("body frame", "body", True), ("state frame, attitude-blind", "state", True),
             ("state frame, reads the attitude", "state", False))


def flights(seeds, turn: int) -> list:
    return [simulate_crazyflie(SimulatedFlight(truth=DRAG_TRUTH, duration_s=20.0, turn=turn), seed=s) for s in seeds]


def one_step_error(model: HybridModel, flight) -> float:
    _, zeta, u, _ = Algorithm1().observe_flight(flight, "crazyflie")
    model = HybridModel(replace(model.system, dt=flight.dt), model.kind, model.residual)
    return float(np.mean(np.sum((model.step(zeta[:-1], u[:-1], flight.dt) - zeta[1:]) ** 2, axis=1)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/residual_symmetry"))
    args = parser.parse_args()
    started = time.perf_counter()
    train = flights(range(5), 1)
    counter, clockwise = flights(range(5, 8), 1), flights(range(5, 8), -1)
    prior = HybridModel(system_for(counter[0], "crazyflie"), "prior")
    rows = []
    for label, frame, blind in RESIDUALS:
        model = train_on_flights(train, replace(CRAZYFLIE_TRAINING, residual_frame=frame), system="crazyflie",
                                 blind_attitude=blind).model
        gains = {turn: [100 * (1 - one_step_error(model, f) / one_step_error(prior, f)) for f in scored]
                 for turn, scored in (("counter-clockwise", counter), ("clockwise", clockwise))}
        rows.append({"residual": label, **gains})
    result = {"command": "python benchmarks/residual_symmetry.py", "seconds": time.perf_counter() - started,
              "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "residual_symmetry.json").write_text(json.dumps(result, indent=1))
    lines = ["# Trained on counter-clockwise circles, scored both ways", "",
             "One-step prediction gain over the prior (%), three scored seeds, each flown both ways. "
             f"Command: `{result['command']}` ({result['seconds']:.0f} s).", "",
             "| residual | counter-clockwise | clockwise | largest difference (points) |", "|---|---|---|---|"]
    for row in rows:
        ccw, cw = row["counter-clockwise"], row["clockwise"]
        cells = [", ".join(f"{g:+.1f}" for g in gains) for gains in (ccw, cw)]
        lines.append(f"| {row['residual']} | {cells[0]} | {cells[1]} | {max(abs(a - b) for a, b in zip(ccw, cw)):.1f} |")
    (args.out / "residual_symmetry.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
