"""Leave one trajectory family out on the real NanoBench flights: does a KNODE learn the vehicle or the flight?

Four families of one Crazyflie (circles, figure-eights, helices, low linear ramps; `../shared/data/nanobench`
and `../shared/data/nanobench-more`).  For each family held out, KNODEs are trained on the other three and
scored on every flight of the held-out family:

- training: one flight (the paper's protocol; a medium-speed repetition of another family) or pooled (every
  flight of the other three families, one in five whole flights held out for validation), the pooled residual
  scaled by the scale chosen with each of the three training families held out in turn
  (`estimators.group_training`; ``--scale full`` keeps the whole residual);
- prior: the paper's kinematic chain (``quadrotor``) or the Crazyflie driven by its motors and battery;
- estimators: UKF, KNODE-UKF, MHE, KNODE-MHE, and the vehicle's own onboard EKF (``onboard``, fast reference
  only);
- yardsticks: mocap gaps (position RMSE inside 0.5-s windows where the mocap was hidden, one every 2.5 s),
  the fast reference (velocity RMSE against a 0.05-s derivative of the raw mocap) and the paper's SG MSE.

Per family and configuration: the median gain of each KNODE over its prior on every yardstick, how many
flights it is better on, and how many are worse beyond their 95 % interval (paired block bootstrap over the
gaps).

Run from the repository root (needs ../shared/data; ~30 min on 2 cores):
    .venv/bin/python benchmarks/family_holdout.py [--families circle,figure8,helix,ramp]
        [--trainings pooled,one] [--systems crazyflie,quadrotor] [--attitude blind|seen] [--battery blind|seen]
        [--scale chosen|full] [--frame system|body|state] [--noise paper|identified]
        [--out benchmarks/results/family_holdout]
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from learnest.estimators.group_training import train_with_scale_choice
from learnest.ingest import read_flights
from learnest.models.presets import CRAZYFLIE_TRAINING
from learnest.workflows.flights import evaluate_flights, train_on_flights

DATA = (Path("../shared/data/nanobench"), Path("../shared/data/nanobench-more"))
FAMILIES = {"circle": "B2_circle", "figure8": "B3_figure8", "helix": "B5_helix", "ramp": "B6_linear_ramp"}
# the one-flight model of each held-out family: a medium-speed repetition of another family
ONE_FLIGHT = {"circle": "B3_figure8_medium_rep2", "figure8": "B2_circle_medium_rep2",
              "helix": "B2_circle_medium_rep2", "ramp": "B2_circle_medium_rep2"}
METHODS = ("ukf", "knode-ukf", "mhe", "knode-mhe", "onboard")
PAIRS = ("knode-ukf_vs_ukf", "knode-mhe_vs_mhe")


def family_of(name: str) -> str | None:
    return next((fam for fam, prefix in FAMILIES.items() if name.startswith(prefix)), None)


def per_flight(report: dict) -> list[dict]:
    """The scored flights' numbers on the three yardsticks (gains in %: 100 (1 - knode / prior))."""
    rows = []
    for entry in report["flights"]:
        if entry["excluded"]:
            continue
        sticks = entry.get("yardsticks") or {}
        gaps = sticks.get("mocap_gaps") or {}
        fast = (sticks.get("fast_reference") or {}).get("velocity_rmse_m_s") or {}
        sg = (sticks.get("paper_sg") or {}).get("mse") or entry["mse"]
        row = {"flight": entry["flight"], "gap_rmse_m": gaps.get("rmse_m") or {}, "fast_rmse_m_s": fast,
               "sg_mse": sg, "gap_gain_pct": gaps.get("gain_pct") or {},
               "gap_interval_pct": gaps.get("gain_interval_pct") or {}, "gaps": gaps.get("gaps"),
               "gap_note": gaps.get("skipped")}
        for pair in PAIRS:
            knode, base = pair.split("_vs_")
            for stick, values in (("fast", fast), ("sg", sg)):
                if knode in values and base in values and values[base] > 0:
                    row.setdefault(f"{stick}_gain_pct", {})[pair] = 100.0 * (1.0 - values[knode] / values[base])
        rows.append(row)
    return rows


def summary(rows: list[dict]) -> dict:
    out = {}
    for pair in PAIRS:
        gap = [r["gap_gain_pct"][pair] for r in rows if pair in r["gap_gain_pct"]]
        beyond = sum(1 for r in rows if (r["gap_interval_pct"].get(pair) or [0, 0])[1] < 0)
        out[pair] = {
            "gap_median_gain_pct": float(np.median(gap)) if gap else None,
            "gap_flights_better": sum(1 for g in gap if g > 0), "gap_flights": len(gap),
            "gap_worse_beyond_interval": beyond,
            "fast_median_gain_pct": _median(rows, "fast_gain_pct", pair),
            "sg_median_gain_pct": _median(rows, "sg_gain_pct", pair)}
    for method in METHODS:
        gap = [r["gap_rmse_m"][method] for r in rows if method in r["gap_rmse_m"]]
        fast = [r["fast_rmse_m_s"][method] for r in rows if method in r["fast_rmse_m_s"]]
        out[method] = {"gap_median_rmse_m": float(np.median(gap)) if gap else None,
                       "fast_median_rmse_m_s": float(np.median(fast)) if fast else None}
    return out


def _median(rows, key, pair):
    values = [r[key][pair] for r in rows if pair in r.get(key, {})]
    return float(np.median(values)) if values else None


def _fmt(value, spec="+.1f", unit=" %"):
    return "–" if value is None else f"{value:{spec}}{unit}"


def markdown(result: dict) -> str:
    lines = ["# Leave one family out: one-flight vs pooled training, kinematic vs Crazyflie prior (real NanoBench)",
             "", f"Command: `{result['command']}` ({result['seconds']:.0f} s wall on 2 shared cores)", "",
             "Gains are 100 (1 − KNODE / prior) per flight, median over the held-out family; *worse beyond* counts "
             "flights whose 95 % interval of the gap gain lies below 0.", "",
             "## The KNODE against its prior, per held-out family", "",
             "| held out | training | prior | flights | gap gain UKF / MHE | better on (gap) UKF / MHE "
             "| worse beyond UKF / MHE | fast-ref gain UKF / MHE | paper SG gain UKF / MHE |",
             "|---|---|---|---|---|---|---|---|---|"]
    for run in result["runs"]:
        s = run["summary"]
        u, m = s["knode-ukf_vs_ukf"], s["knode-mhe_vs_mhe"]
        lines.append(f"| {run['family']} | {run['training']} | {run['system']} | {len(run['flights'])} | "
                     f"{_fmt(u['gap_median_gain_pct'])} / {_fmt(m['gap_median_gain_pct'])} | "
                     f"{u['gap_flights_better']}/{u['gap_flights']} / {m['gap_flights_better']}/{m['gap_flights']} | "
                     f"{u['gap_worse_beyond_interval']} / {m['gap_worse_beyond_interval']} | "
                     f"{_fmt(u['fast_median_gain_pct'])} / {_fmt(m['fast_median_gain_pct'])} | "
                     f"{_fmt(u['sg_median_gain_pct'])} / {_fmt(m['sg_median_gain_pct'])} |")
    lines += ["", "## Every method on the yardsticks that need no smoothed truth (median over the family)", "",
              "| held out | training | prior | " + " | ".join(f"gap {m} (m)" for m in METHODS if m != "onboard")
              + " | " + " | ".join(f"fast {m} (m/s)" for m in METHODS) + " |",
              "|---" * (3 + 2 * len(METHODS) - 1) + "|"]
    for run in result["runs"]:
        s = run["summary"]
        lines.append(f"| {run['family']} | {run['training']} | {run['system']} | "
                     + " | ".join(_fmt(s[m]["gap_median_rmse_m"], ".4f", "") for m in METHODS if m != "onboard")
                     + " | " + " | ".join(_fmt(s[m]["fast_median_rmse_m_s"], ".4f", "") for m in METHODS) + " |")
    lines += ["", "## Training", "", "| held out | training | prior | flights trained / validated | learned | "
              "best epoch | residual scale | seconds |", "|---|---|---|---|---|---|---|---|"]
    for run in result["runs"]:
        t = run["train"]
        scale = t.get("residual_scale")
        lines.append(f"| {run['family']} | {run['training']} | {run['system']} | {t['trained']} / {t['validated']} | "
                     f"{t['learned']} | {t['best_epoch']} | {'1 (full)' if scale is None else scale} | "
                     f"{t['seconds']:.1f} |")
    lines += ["", "## How each pooled residual scale was chosen (training families held out in turn; KNODE-UKF gap "
              "gain median %, flights worse beyond their interval)", ""]
    for run in result["runs"]:
        choice = run["train"].get("residual_scale_choice")
        if not choice:
            continue
        lines += [f"- {run['family']} held out, {run['system']}: chosen {choice['chosen']}; " + "; ".join(
            f"scale {s}: " + ", ".join(f"{r['group']} {_fmt(r['median_gain_pct'])} ({r['worse_beyond']} worse)"
                                     for r in rows) for s, rows in choice["scales"].items())]
    lines += ["", "## Per flight (gap gain, % — interval)", ""]
    for run in result["runs"]:
        lines += [f"### {run['family']} held out — {run['training']}, {run['system']}", "",
                  "| flight | gaps | KNODE-UKF vs UKF | KNODE-MHE vs MHE | gap RMSE ukf / knode-ukf (m) |",
                  "|---|---|---|---|---|"]
        for r in run["flights"]:
            cells = []
            for pair in PAIRS:
                g, iv = r["gap_gain_pct"].get(pair), r["gap_interval_pct"].get(pair)
                cells.append(_fmt(g) + (f" [{iv[0]:+.1f}, {iv[1]:+.1f}]" if iv else ""))
            rm = r["gap_rmse_m"]
            lines.append(f"| {r['flight']} | {r['gaps'] if r['gaps'] is not None else (r['gap_note'] or '–')} | "
                         f"{cells[0]} | {cells[1]} | {_fmt(rm.get('ukf'), '.4f', '')} / "
                         f"{_fmt(rm.get('knode-ukf'), '.4f', '')} |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--families", default=",".join(FAMILIES))
    parser.add_argument("--trainings", default="pooled,one")
    parser.add_argument("--systems", default="crazyflie,quadrotor")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--attitude", choices=("blind", "seen"), default="blind",
                        help="pooled residual blind to the attitude (the default of train_on_flights) or seeing it")
    parser.add_argument("--battery", choices=("blind", "seen"), default="blind",
                        help="with --attitude blind: the pooled residual blind to the battery voltage too")
    parser.add_argument("--scale", choices=("chosen", "full"), default="chosen",
                        help="pooled residual scaled by the scale chosen on held-out training families "
                             "(estimators.group_training), or the full residual")
    parser.add_argument("--frame", choices=("system", "body", "state"), default="system",
                        help="what the residual reads and where it acts (models.residual_frame); system: the "
                             "prior's own (body for the Crazyflie, state for the quadrotor)")
    parser.add_argument("--noise", choices=("paper", "identified"), default="paper",
                        help="the filters' noise: the system's fixed (paper) noise, or each model's and its prior's "
                             "identified on the training flights")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/family_holdout"))
    args = parser.parse_args(argv)
    config = replace(CRAZYFLIE_TRAINING, residual_frame="" if args.frame == "system" else args.frame)
    started = time.perf_counter()
    paths = sorted(p for folder in DATA for p in folder.glob("B*.csv"))
    if not paths:
        sys.exit("no NanoBench flights under ../shared/data")
    flights = [f for f in read_flights(paths) if family_of(f.name)]
    by_name = {f.name: f for f in flights}
    usable = [f for f in flights if f.quality["ok"]]
    methods = [m for m in args.methods.split(",") if m]
    command = ("python benchmarks/family_holdout.py " + " ".join(argv if argv is not None else sys.argv[1:])).strip()
    args.out.mkdir(parents=True, exist_ok=True)
    runs = []
    for training in args.trainings.split(","):
        for system in args.systems.split(","):
            for family in args.families.split(","):
                test = [f for f in flights if family_of(f.name) == family]
                train = ([f for f in usable if family_of(f.name) != family] if training == "pooled"
                         else [by_name[ONE_FLIGHT[family]]])
                t0 = time.perf_counter()
                blind = {"blind_attitude": args.attitude == "blind", "blind_battery": args.battery == "blind"}
                if training == "pooled" and args.scale == "chosen":   # the scale chosen on training families only
                    groups: dict = {}
                    for f in train:
                        groups.setdefault(family_of(f.name), []).append(f)
                    trained = train_with_scale_choice(groups, system=system, config=config, noise=args.noise, **blind)
                else:
                    trained = train_on_flights(train, config, system=system, group_by="none", noise=args.noise, **blind)
                meta = trained.model.meta
                report = evaluate_flights(trained.model, test, methods, noise=args.noise)
                rows = per_flight(report)
                runs.append({"family": family, "training": training, "system": system, "flights": rows,
                             "summary": summary(rows), "headline": report.get("headline"),
                             "excluded": [(e["flight"], e["reason"]) for e in report["flights"] if e["excluded"]],
                             "train": {"trained": len(meta.get("training_flights") or [1]),
                                       "validated": len(meta.get("validation_flights") or []),
                                       "learned": meta.get("learned"), "best_epoch": meta.get("best_epoch"),
                                       "seconds": trained.seconds, "residual_scale": meta.get("residual_scale"),
                                       "residual_scale_choice": meta.get("residual_scale_choice")},
                             "seconds": time.perf_counter() - t0})
                print(f"{family} held out, {training}, {system}: {runs[-1]['summary']['knode-ukf_vs_ukf']} "
                      f"({runs[-1]['seconds']:.0f} s)", file=sys.stderr, flush=True)
                partial = {"command": command, "runs": runs, "seconds": time.perf_counter() - started}
                (args.out / "family_holdout.json").write_text(json.dumps(partial, indent=1, default=float))
    result = {"command": command, "runs": runs, "seconds": time.perf_counter() - started}
    (args.out / "family_holdout.json").write_text(json.dumps(result, indent=1, default=float))
    (args.out / "family_holdout.md").write_text(markdown(result))
    print(markdown(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
