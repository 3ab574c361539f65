"""Which pre-training observer trains the best KNODE?  Table I's KNODE rows on a few seeds per observer.

Usage (from the repository root, with the package installed):

    .venv/bin/python benchmarks/observer_study.py --task cartpole --seeds 0 1 2 3 \\
        --out benchmarks/results/table1_observer_study_cartpole.jsonl

Each seed simulates Table I's training run (seed 10000 + s) and evaluation run (20000 + s).  The rows
that do not depend on the observer (UKF, MHE (true dynamics)) are computed once per seed; for every
observer variant the script records the observer's state error against the simulated truth, the KNODE-UKF
and KNODE-MHE MSE on the evaluation run, the rounds kept and the wall time.  One JSON line per seed and
variant is appended as it finishes, so an interrupted run keeps what it did.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from learnest.estimators.algorithm1 import Algorithm1, first_observation
from learnest.estimators.mhe import MHE
from learnest.estimators.params import EstimatorParams
from learnest.estimators.ukf import run_ukf
from learnest.models.knode import HybridModel
from learnest.models.presets import MHE_HORIZON, PAPER_TRAINING, TrainingConfig
from learnest.models.systems import make_system

VARIANTS = {"filter": ("filter", 0), "smoother": ("smoother", 0), "filter+iteration": ("filter", 3),
            "smoother+iteration": ("smoother", 3), "filter+6 rounds": ("filter", 6)}


def _scores(model, system, test) -> dict:
    params = EstimatorParams(model, system.dt, system.Q, system.R, system.P0, test.x_noisy[0])
    started = time.perf_counter()
    ukf = run_ukf(params, test.y, test.u).means
    mhe = MHE(params, horizon=MHE_HORIZON).run(test.y, test.u).means
    return {"ukf": float(np.mean((ukf - test.x) ** 2)), "mhe": float(np.mean((mhe - test.x) ** 2)),
            "estimators_s": time.perf_counter() - started}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", choices=sorted(PAPER_TRAINING))
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--out", required=True, help="JSON lines file (appended)")
    parser.add_argument("--summarize", action="store_true", help="print the table of --out and exit")
    args = parser.parse_args()
    if args.summarize:
        print(summarize([json.loads(line) for line in open(args.out) if line.strip()]))
        return
    if not args.task:
        parser.error("--task is required unless --summarize")
    system = make_system(args.task)
    for seed in args.seeds:
        train, test = system.simulate(10_000 + seed), system.simulate(20_000 + seed)
        config = TrainingConfig(**{**PAPER_TRAINING[args.task].as_dict(), "seed": seed})
        baseline = {"UKF": _scores(HybridModel(system, "prior"), system, test)["ukf"],
                    "MHE (true dynamics)": _scores(HybridModel(system, "true"), system, test)["mhe"]}
        for name in args.variants:
            kind, rounds = VARIANTS[name]
            started = time.perf_counter()
            zeta0 = first_observation(system, train.y, train.u, system.dt, kind)
            result = Algorithm1(kind, config, rounds).fit(system, train.y, train.u, system.dt)
            train_s = time.perf_counter() - started
            scores = _scores(result.model, system, test)
            line = {"task": args.task, "seed": seed, "variant": name, "baseline": baseline,
                    "knode_ukf": scores["ukf"], "knode_mhe": scores["mhe"],
                    "observer_state_mse": np.mean((zeta0 - train.x) ** 2, axis=0).tolist(),
                    "observer": result.model.meta["observer"], "train_s": train_s,
                    "estimators_s": scores["estimators_s"]}
            with open(args.out, "a") as out:
                out.write(json.dumps(line) + "\n")
            print(f"{args.task} seed {seed} {name:<20} KNODE-MHE/MHE(true) "
                  f"{scores['mhe'] / baseline['MHE (true dynamics)']:.2f}  UKF/KNODE-UKF "
                  f"{baseline['UKF'] / scores['ukf']:.1f}  kept round {result.model.meta['observer']['kept_round']}"
                  f"  ({train_s:.0f} s training)", flush=True)



def summarize(lines: list[dict]) -> str:
    """Markdown table: per task and variant, the seeds run, both ratios per seed and their medians."""
    out = ["| task | variant | seeds | KNODE-MHE / MHE (true), per seed | median "
           "| UKF / KNODE-UKF, per seed | median |", "|---|---|---|---|---|---|---|"]
    for task in sorted({line["task"] for line in lines}):
        for variant in VARIANTS:
            rows = sorted((line for line in lines if line["task"] == task and line["variant"] == variant),
                          key=lambda line: line["seed"])
            if not rows:
                continue
            mhe = [r["knode_mhe"] / r["baseline"]["MHE (true dynamics)"] for r in rows]
            ukf = [r["baseline"]["UKF"] / r["knode_ukf"] for r in rows]
            out.append(f"| {task} | {variant} | {', '.join(str(r['seed']) for r in rows)} | "
                       f"{', '.join(f'{x:.2f}' for x in mhe)} | {np.median(mhe):.2f} | "
                       f"{', '.join(f'{x:.1f}' for x in ukf)} | {np.median(ukf):.1f} |")
    return "\n".join(out)


if __name__ == "__main__":
    main()
