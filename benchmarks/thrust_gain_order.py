"""The per-flight thrust gain of the Crazyflie prior (`models.crazyflie.thrust_gain`) on the NanoBench flights, in flying
order: does it behave like motor heating (falling over flights flown back to back, recovering after a break)?

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/thrust_gain_order.py [--out benchmarks/results/crazyflie_thrust_gain]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from learnest.estimators.prepared import system_for
from learnest.ingest import read_flights
from learnest.models.inputs import flight_thrust_gain, system_inputs
from learnest.workflows.flights import log_start_ns

DATA = Path("../shared/data/nanobench")
BREAK_MIN = 5.0          # a gap this long since the previous log ended: the motors have cooled (τ_th 45-75 s)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/crazyflie_thrust_gain"))
    args = parser.parse_args(argv)
    flights = read_flights(sorted(args.data.glob("B*.csv")))
    if not flights:
        sys.exit(f"no NanoBench flights under {args.data}")
    rows = []
    for flight in flights:
        system = system_for(flight, "crazyflie")
        start_s = log_start_ns(flight) / 1e9
        rows.append({"flight": flight.name, "start_s": start_s, "end_s": start_s + flight.duration_s,
                     "gain": flight_thrust_gain(flight, system, system_inputs(flight, system)),
                     "vbat": float(np.nanmean(flight.channels["vbat"])), "ok": flight.quality["ok"]})
    rows.sort(key=lambda r: r["start_s"])
    lines = ["# Thrust gain per flight, in flying order (NanoBench, CF_01)", "",
             "Command: `python benchmarks/thrust_gain_order.py`. Gain: the mocap's body-z specific force over the "
             "identified thrust map's (`models/crazyflie/thrust_gain.py`).", "",
             "| flight | start (min) | gap since previous log (min) | gain | change vs previous | mean vbat (V) | note |",
             "|---|---|---|---|---|---|---|"]
    back_to_back, after_break = [], []
    for previous, row in zip([None] + rows[:-1], rows):
        gap = (row["start_s"] - previous["end_s"]) / 60.0 if previous else float("nan")
        change = row["gain"] - previous["gain"] if previous else float("nan")
        note = "" if row["ok"] else "fails the quality checks (not scored)"
        if previous and row["ok"] and previous["ok"]:
            (after_break if gap >= BREAK_MIN else back_to_back).append(change)
        lines.append(f"| {row['flight']} | {(row['start_s'] - rows[0]['start_s']) / 60:.1f} | {gap:.1f} | "
                     f"{row['gain']:.4f} | {change:+.4f} | {row['vbat']:.3f} | {note} |")
    lines += ["", f"Change of the gain from the previous flight (both passing the quality checks): flown within "
                  f"{BREAK_MIN:.0f} min of it, median {np.median(back_to_back):+.4f} ({sum(c < 0 for c in back_to_back)} "
                  f"of {len(back_to_back)} fall); after a break of {BREAK_MIN:.0f} min or more, median "
                  f"{np.median(after_break):+.4f} ({sum(c > 0 for c in after_break)} of {len(after_break)} rise).",
              f"Correlation of the gain with the mean battery voltage: "
              f"{np.corrcoef([r['vbat'] for r in rows], [r['gain'] for r in rows])[0, 1]:+.2f} (the map already "
              "carries the voltage).", ""]
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "gain_by_flying_order.md").write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
