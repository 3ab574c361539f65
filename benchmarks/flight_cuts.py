"""Where each real flight is cut (the stretch `learnest ingest --cut auto` keeps), and how the cut moved.

Reads every shared real flight (../shared/data: the 17 NanoBench circles and figure-eights, the nanobench-more
helices and ramps, the three crazyswarm2-tools uSD logs) with the automatic cut and records, per flight, the
recording's length, the kept [start, stop] (s from the recording's start), the quality verdict, the measured
sensor rates and the rule the cut printed.

Run (before.json was written by the same script on the code before the cut used the motors and the
accelerometer, and before rates were measured from the time stamps):
  .venv/bin/python benchmarks/flight_cuts.py --out benchmarks/results/flight_cuts/after.json
  .venv/bin/python benchmarks/flight_cuts.py --compare benchmarks/results/flight_cuts/before.json \
      benchmarks/results/flight_cuts/after.json --reasons benchmarks/results/flight_cuts/reasons.json \
      --md benchmarks/results/flight_cuts/table.md
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

PREAMBLE = """# Where each shared real flight is cut: before and after the cut used motors and accelerometer

`learnest ingest --cut auto` on every real flight in ../shared/data (17 NanoBench circles and figure-eights,
15 nanobench-more helices and ramps, 3 crazyswarm2-tools uSD logs).  Kept: seconds from the recording's start.
Before: the height rule alone (floor = the first 0.5 s), rates from row counts over the span.  After:
`ingest.flight_span` (motor PWM / thrust command: motors off is not flying; accelerometer at rest; height above
the floor seen at rest), rates from the time stamps.  Made by `benchmarks/flight_cuts.py` (see its docstring).
"""
DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FAMILIES = {"nanobench": "*.csv", "nanobench-more": "*.csv", "crazyswarm2-tools": "log*"}


def measure() -> list[dict]:
    from learnest.ingest import IngestError, read_flights

    rows = []
    for family, pattern in FAMILIES.items():
        for path in sorted((DATA / family).glob(pattern)):
            row = {"family": family, "file": path.name}
            try:
                flight = read_flights([path])[0]
            except IngestError as err:
                row["error"] = str(err)
                rows.append(row)
                continue
            kept = flight.meta["flying_window"]
            rates = (flight.meta.get("profile") or {}).get("rates_hz") or {}
            row.update({"recording_s": round(kept["recording_s"], 2), "start_s": round(kept["start_s"], 2),
                        "stop_s": round(kept["stop_s"], 2), "rule": kept["rule"],
                        "ok": flight.quality["ok"], "issues": flight.quality["issues"],
                        "acc_hz": rates.get("acc"), "mocap_hz": rates.get("mocap")})
            rows.append(row)
            print(f"{family}/{path.name}: {row['start_s']}-{row['stop_s']} of {row['recording_s']} s", file=sys.stderr)
    return rows


def compare(before: list[dict], after: list[dict], reasons: dict) -> str:
    old = {(r["family"], r["file"]): r for r in before}
    lines = ["| flight | recording (s) | before: kept (s) | after: kept (s) | Δstart, Δstop (s) | quality before → after "
             "| rates before → after (acc/mocap Hz) | why it changed |", "|---|---|---|---|---|---|---|---|"]
    for row in after:
        key = (row["family"], row["file"])
        prev = old.get(key, {})
        if "error" in row or "error" in prev:
            lines.append(f"| {key[0]}/{key[1]} | | {prev.get('error', '')} | {row.get('error', '')} | | | | |")
            continue
        d_start, d_stop = row["start_s"] - prev["start_s"], row["stop_s"] - prev["stop_s"]
        moved = abs(d_start) > 0.005 or abs(d_stop) > 0.005
        quality = lambda r: "ok" if r["ok"] else "bad: " + "; ".join(r["issues"])[:90]
        rates = lambda r: f"{r['acc_hz']}/{r['mocap_hz']}"
        why = []
        if moved:
            why.append(reasons.get(key[1], reasons.get("small move", "")))
        if rates(prev) != rates(row):
            why.append(reasons.get("rates", ""))
        why = " ".join(w for w in why if w) or "unchanged"
        lines.append(f"| {key[0]}/{key[1]} | {row['recording_s']} | {prev['start_s']}–{prev['stop_s']} | "
                     f"{row['start_s']}–{row['stop_s']} | {d_start:+.2f}, {d_stop:+.2f} | {quality(prev)} → "
                     f"{quality(row)} | {rates(prev)} → {rates(row)} | {why} |")
    return "\n".join(lines)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--out")
    parser.add_argument("--compare", nargs=2)
    parser.add_argument("--reasons", help="JSON {file: why its cut changed}")
    parser.add_argument("--md")
    args = parser.parse_args()
    if args.compare:
        before, after = (json.loads(Path(p).read_text()) for p in args.compare)
        reasons = json.loads(Path(args.reasons).read_text()) if args.reasons else {}
        table = compare(before, after, reasons)
        text = "\n".join([PREAMBLE, table, "", *(f"{note}\n" for note in reasons.get("_notes", []))])
        Path(args.md).write_text(text) if args.md else print(text)
        return
    rows = measure()
    text = json.dumps(rows, indent=1)
    Path(args.out).write_text(text + "\n") if args.out else print(text)


if __name__ == "__main__":
    main()
