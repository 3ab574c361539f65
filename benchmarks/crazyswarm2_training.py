"""Another lab's Crazyflie: KNODEs trained on crazyswarm2 log182-183 and scored on log184, with the Crazyflie
prior driven by the thrust command in N the logs carry (``ctrlLee.thrustSI``, the declared 32 g, each flight's
thrust gain) and with the kinematic prior.  Every method's position RMSE in the mocap gaps (the headline) and
velocity RMSE against the fast reference.

Run from the repository root (needs ../shared/data, ~1 min):
    .venv/bin/python benchmarks/crazyswarm2_training.py > benchmarks/results/crazyswarm2_training.md
"""
from __future__ import annotations

import time
from pathlib import Path

import learnest as le

LOGS = [Path(__file__).resolve().parents[2] / "shared" / "data" / "crazyswarm2-tools" / f"log{n}"
        for n in (182, 183, 184)]
METHODS = ("ukf", "knode-ukf", "mhe", "knode-mhe", "onboard")
GAP_METHODS = METHODS[:4]      # the onboard estimate never loses the mocap: no gap score


def main() -> None:
    started = time.perf_counter()
    flights = le.read_flights([str(path) for path in LOGS])
    print("# crazyswarm2 log182-184: trained on two flights, scored on the third\n")
    print("| prior | thrust gains (training flights) | " + " | ".join(f"gap {m} (mm)" for m in GAP_METHODS)
          + " | gain in mean squared gap error, KNODE-UKF / KNODE-MHE (95 % interval) | "
          + " | ".join(f"fast {m} (m/s)" for m in METHODS) + " |")
    print("|---" * (3 + len(GAP_METHODS) + len(METHODS)) + "|")
    for system in ("crazyflie", "quadrotor"):
        model = le.KNODE(system=system).fit(flights[:2]).model_
        meta = model.meta
        gains = [f.get("thrust_gain") for f in meta["training_flights"] + meta["validation_flights"]]
        scored = le.evaluate(model, flights[2:], methods=METHODS)["flights"][0]["yardsticks"]
        gaps, fast = scored["mocap_gaps"], scored["fast_reference"]["velocity_rmse_m_s"]
        intervals = gaps["gain_interval_pct"]
        gain_cells = " / ".join(f"{gaps['gain_pct'][k]:+.1f} % [{intervals[k][0]:+.0f}, {intervals[k][1]:+.0f}]"
                                for k in ("knode-ukf_vs_ukf", "knode-mhe_vs_mhe"))
        print(f"| {system} | {', '.join('-' if g is None else f'{g:.3f}' for g in gains)} | "
              + " | ".join(f"{1e3 * gaps['rmse_m'][m]:.1f}" for m in GAP_METHODS)
              + f" | {gain_cells} | " + " | ".join(f"{fast[m]:.4f}" for m in METHODS) + " |")
    print(f"\n{time.perf_counter() - started:.0f} s.")


if __name__ == "__main__":
    main()
