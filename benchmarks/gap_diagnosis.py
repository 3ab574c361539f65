"""Why a pooled Crazyflie KNODE can predict one step better and carry the estimate through a mocap gap worse.

For one held-out family: train the pooled KNODE on the other three (as `benchmarks/family_holdout.py`), then on
every flight of every family, from the pre-training observer's states ζ:

- the residual's output Δθ on the ȧ rows (m/s³) and what it does to the acceleration the model settles on,
  tau_s · Δθ (m/s²: ȧ = (a_cmd − a)/tau_s + Δθ relaxes a to a_cmd + tau_s Δθ);
- open-loop 0.5-s rollouts of the prior and of the KNODE from ζ_i (every 10th sample) with the logged inputs,
  scored against the mocap position 0.5 s later (m);
- in turns (horizontal acceleration above 0.5 m/s²): the share turning counter-clockwise, and the horizontal
  offset tau_s Δθ along the acceleration and ahead of it in the turn's sense (m/s²).

Run from the repository root (needs ../shared/data):
    .venv/bin/python benchmarks/gap_diagnosis.py [--family figure8] [--attitude blind|seen] [--battery blind|seen]
        [--out benchmarks/results/gap_diagnosis]
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from family_holdout import DATA, family_of  # noqa: E402

from learnest.estimators.algorithm1 import Algorithm1  # noqa: E402
from learnest.ingest import read_flights  # noqa: E402
from learnest.models.knode import HybridModel  # noqa: E402
from learnest.workflows.flights import train_on_flights  # noqa: E402

HORIZON_S = 0.5
EVERY = 10


def rollout_errors(model: HybridModel, zeta: np.ndarray, u: np.ndarray, p: np.ndarray, dt: float,
                   steps: int) -> np.ndarray:
    """Position error (B, 3) m of open-loop rollouts of ``steps`` steps from ζ at every EVERY-th sample."""
    starts = np.arange(0, len(zeta) - steps - 1, EVERY)
    x = zeta[starts].copy()
    for k in range(steps):
        x = model.step(x, u[starts + k], dt)
    return x[:, :3] - p[starts + steps]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default="figure8")
    parser.add_argument("--attitude", choices=("blind", "seen"), default="blind",
                        help="pooled residual blind to the attitude (the default of train_on_flights) or seeing it")
    parser.add_argument("--battery", choices=("blind", "seen"), default="blind",
                        help="with --attitude blind: the pooled residual blind to the battery voltage too")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/gap_diagnosis"))
    args = parser.parse_args(argv)
    paths = sorted(p for folder in DATA for p in folder.glob("B*.csv"))
    flights = [f for f in read_flights(paths) if family_of(f.name)]
    train = [f for f in flights if f.quality["ok"] and family_of(f.name) != args.family]
    trained = train_on_flights(train, system="crazyflie", blind_attitude=args.attitude == "blind",
                               blind_battery=args.battery == "blind", group_by="none")
    knode = trained.model
    tau = knode.system.prior_params["tau_s"]
    rows = []
    for flight in flights:
        system, zeta, u, _ = Algorithm1().observe_flight(flight, "crazyflie")
        prior = HybridModel(system, "prior")
        model = HybridModel(system, "knode", knode.residual, knode.meta)
        r = knode.residual(zeta, u)[:, 6:9]
        steps = int(round(HORIZON_S / flight.dt))
        e_prior = rollout_errors(prior, zeta, u, flight.p, flight.dt, steps)
        e_knode = rollout_errors(model, zeta, u, flight.p, flight.dt, steps)
        speed = np.linalg.norm(zeta[:, 3:6], axis=1)
        # the horizontal offset split along the observer's horizontal acceleration (centripetal in a turn) and
        # across it (+: e_z × a, ahead of a counter-clockwise turn), where |a_h| > 0.5 m/s²
        a_h, v_h, off = zeta[:, 6:8], zeta[:, 3:5], tau * r[:, :2]
        norm = np.linalg.norm(a_h, axis=1)
        turning = norm > 0.5
        ccw = (v_h[:, 0] * a_h[:, 1] - v_h[:, 1] * a_h[:, 0]) > 0
        along = np.sum(a_h * off, axis=1) / np.maximum(norm, 1e-9)
        across = (a_h[:, 0] * off[:, 1] - a_h[:, 1] * off[:, 0]) / np.maximum(norm, 1e-9)
        turns = {"ccw_share": float(np.mean(ccw[turning])) if turning.any() else None,
                 "offset_along_a_m_s2": float(np.mean(along[turning])) if turning.any() else None,
                 "offset_ahead_m_s2": float(np.mean(np.where(ccw, across, -across)[turning])) if turning.any()
                 else None}
        rows.append({"flight": flight.name, "family": family_of(flight.name),
                     "held_out": family_of(flight.name) == args.family,
                     "trained": flight.name in [t["name"] for t in knode.meta["training_flights"]],
                     "offset_mean_m_s2": (tau * r.mean(axis=0)).tolist(),
                     "offset_rms_m_s2": float(np.sqrt(np.mean((tau * r) ** 2))),
                     "speed_median_m_s": float(np.median(speed)), "speed_p95_m_s": float(np.quantile(speed, 0.95)),
                     "rollout_rmse_prior_m": float(np.sqrt(np.mean(np.sum(e_prior**2, axis=1)))),
                     "rollout_rmse_knode_m": float(np.sqrt(np.mean(np.sum(e_knode**2, axis=1)))),
                     "rollout_bias_prior_m": e_prior.mean(axis=0).tolist(),
                     "rollout_bias_knode_m": e_knode.mean(axis=0).tolist(), "turns": turns})
        row = rows[-1]
        print(f"{row['flight']:28s} {'H' if row['held_out'] else ('T' if row['trained'] else 'V')} "
              f"offset mean {np.round(row['offset_mean_m_s2'], 3)} rms {row['offset_rms_m_s2']:.3f}  "
              f"rollout prior {row['rollout_rmse_prior_m']:.4f} knode {row['rollout_rmse_knode_m']:.4f}  "
              f"speed {row['speed_median_m_s']:.2f}/{row['speed_p95_m_s']:.2f} turns {turns}", flush=True)
    groups = {}
    for row in rows:
        row["rollout_mse_gain_pct"] = 100 * (1 - (row["rollout_rmse_knode_m"] / row["rollout_rmse_prior_m"]) ** 2)
        group = "held out" if row["held_out"] else ("trained" if row["trained"] else "not trained")
        groups.setdefault(group, []).append(row["rollout_mse_gain_pct"])
    summary = {g: {"median_rollout_mse_gain_pct": float(np.median(v)), "better": sum(x > 0 for x in v),
                   "flights": len(v)} for g, v in groups.items()}
    print(summary)
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"gap_diagnosis_{args.family}_attitude_{args.attitude}"
    name += f"_battery_{args.battery}" if args.attitude == "blind" else ""
    result = {"command": "python benchmarks/gap_diagnosis.py " + " ".join(argv if argv is not None else sys.argv[1:]),
              "family": args.family, "attitude": args.attitude, "battery": args.battery,
              "best_epoch": knode.meta["best_epoch"], "tau_s": tau, "summary": summary, "flights": rows}
    (args.out / f"{name}.json").write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
