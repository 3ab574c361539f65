"""The Crazyflie diagnosis on real logs from two labs, with the thrust each log carries.

- crazyswarm2-tools log182-184 (uSD, the Lee controller's collective thrust ``ctrlLee.thrustSI`` in N, no PWM
  or battery; ``info*.yaml`` declares 32 g): the mass the data give against the declared one.
- NanoBench circles (motor PWM + battery): against the prior identified on NanoBench (nothing should be
  missing) and against the published prior (Förster's map, gamma 1, Bitcraze's 27 g), where the thrust gain
  and the battery exponent come with intervals.

Fitted on the first half of the flights, scored on the others (body-frame specific force from the inputs,
RMSE m/s², and the prior-only UKF's MSE with the repaired prior); every claimed parameter is checked against
its physical bounds.

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/crazyflie_diagnosis_real.py > benchmarks/results/crazyflie_diagnosis_real/results.md
(each report's JSON beside it)
"""
from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from learnest.ingest import read_flights
from learnest.models import crazyflie as cf
from learnest.workflows.diagnosis import diagnose_crazyflie, format_diagnosis

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
OUT = Path(__file__).parent / "results" / "crazyflie_diagnosis_real"
METHODS = ("ukf",)


def _cases():
    crazyswarm = [DATA / "crazyswarm2-tools" / f"log{n}" for n in (182, 183, 184)]
    circles = sorted((DATA / "nanobench").glob("B2_circle_*.csv"))
    public_pwm = {**cf.PUBLIC}
    return [("crazyswarm2 log182-184, thrust in N, declared 32 g", crazyswarm, None),
            ("NanoBench circles, PWM + battery, prior identified on NanoBench", circles, None),
            ("NanoBench circles, PWM + battery, published prior (Förster, gamma 1, 27 g)", circles, public_pwm)]


def _check(report) -> dict:
    """Claimed parameters at a bound or outside it, and claimed effects against the held-out flights."""
    at_bound, outside = [], []
    for e in report["effects"]:
        for name, ok in e["identified"].items():
            lo, hi = e["bounds"][name]
            if ok and e["at_bound"][name]:
                at_bound.append(f"{e['id']}.{name}")
            if ok and not lo <= e["params"][name] <= hi:
                outside.append(f"{e['id']}.{name}")
    claimed = [e["id"] for e in report["effects"] if any(e["identified"].values())]
    improved = {k: v for k, v in report["improved_flights"].items()}
    return {"claimed": claimed, "claimed_at_bound": at_bound, "claimed_outside_bounds": outside,
            "improved_flights": improved, "repair": report["repair"]}


def _mass_lines(flights, report) -> list[str]:
    """What the thrust-in-N logs say of the mass: the command and the accelerometer per flight, and the mass
    claimed, or the one implied were the command the thrust made (`diagnosis_crazyflie._command_scale_text`)."""
    import numpy as np

    lines = []
    for f in flights:
        command, acc = np.median(f.channels["thrust_si"]), np.median(np.linalg.norm(f.channels["acc_body"], axis=1))
        lines.append(f"- {f.name}: median commanded thrust {command:.3f} N, median |accelerometer| {acc:.2f} m/s², "
                     f"command / |acc| = {1e3 * command / acc:.1f} g")
    declared = report["declared_mass_kg"]
    mass = next((e for e in report["effects"] if e["id"] == "mass" and e["identified"].get("m_kg")), None)
    scale = next((e for e in report["effects"] if "implied_mass_kg" in e), None)
    if mass is not None:
        m = mass["params"]["m_kg"]
        met = declared is not None and abs(m - declared) <= 0.1 * declared
        lines.append(f"- mass from the data: {1e3 * m:.1f} g against the declared {1e3 * declared:.0f} g: "
                     f"{'MET' if met else 'NOT MET'} (within 10 %)")
    elif scale is not None:
        lo, hi = scale["implied_mass_ci95"] or (float("nan"), float("nan"))
        g_lo, g_hi = scale["ci95"]["gain"]
        implied, gain = 1e3 * scale["implied_mass_kg"], scale["params"]["gain"]
        lines.append(f"- mass from the data: none claimed.  Position and accelerometer give the thrust made over the "
                     f"mass only; were the command the thrust made, the mass would be {implied:.1f} g "
                     f"[{1e3 * lo:.1f}, {1e3 * hi:.1f}] against the declared {1e3 * declared:.0f} g; with the "
                     f"declared mass the thrust made is ×{gain:.3f} [{g_lo:.3f}, {g_hi:.3f}] of the commanded "
                     "thrust.  Within 10 % of the declared mass: NOT MET (these logs cannot determine the mass)")
    return lines


def main() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    lines = ["# Crazyflie diagnosis on real logs", "",
             "Command: `.venv/bin/python benchmarks/crazyflie_diagnosis_real.py > "
             "benchmarks/results/crazyflie_diagnosis_real/results.md` (reports as JSON beside it).",
             f"Estimators scored before/after: {', '.join(METHODS)} (prior only: the KNODE is not retrained here).", ""]
    for i, (title, paths, prior) in enumerate(_cases()):
        started = time.perf_counter()
        flights = read_flights([str(p) for p in paths])
        report = diagnose_crazyflie(flights, methods=METHODS, prior=prior)
        seconds = time.perf_counter() - started
        (OUT / f"case{i}.json").write_text(json.dumps(report, indent=1, default=float))
        check = _check(report)
        print(json.dumps({"case": title, **check}, default=float), file=sys.stderr)
        lines += [f"## {title}", "", f"{len(flights)} flights, {report['split']}, {seconds:.0f} s wall.", "",
                  "```", format_diagnosis(report), "```", "",
                  f"- thrust source: {report['thrust_source']}; declared mass: {report['declared_mass_kg']}",
                  f"- vehicle fits the prior: {json.dumps(report['vehicle_fits_prior'], ensure_ascii=False)}",
                  f"- claimed: {check['claimed'] or 'nothing'}; "
                  f"claimed at a bound: {check['claimed_at_bound'] or 'none'};"
                  f" claimed outside the physical range: {check['claimed_outside_bounds'] or 'none'}",
                  f"- held-out flights improved: {check['improved_flights']}; repair verdict: {check['repair']}", ""]
        if report["thrust_source"] == "thrust_n":
            lines += _mass_lines(flights, report) + [""]
        for e in report["effects"]:
            lines.append(f"  - {e['id']}: " + ", ".join(
                f"{k} = {v:.4g} {e['units'].get(k, '')} CI {[round(x, 5) for x in e['ci95'].get(k, [])]} "
                f"identified {e['identified'][k]} at_bound {e['at_bound'][k]}" for k, v in e["params"].items()))
        candidates = {c["id"]: {k: round(v, 5) for k, v in c["params"].items()} for c in report["candidates"]}
        lines += ["", f"  every candidate fitted alone: {json.dumps(candidates)}", ""]
    print("\n".join(lines))


if __name__ == "__main__":
    main()
