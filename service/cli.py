"""The `learnest` command line."""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from tqdm import tqdm


def _reproduce(args) -> int:
    from service.reproduce import ReproduceSettings, format_table, reproduce

    settings = ReproduceSettings(task=args.task, eval_samples=args.samples, epochs=args.epochs, horizon=args.horizon)
    with tqdm(total=args.seeds, desc=f"Table I {args.task}", unit="seed", file=sys.stderr) as bar:
        report = reproduce(settings, args.seeds, workers=args.workers, progress=lambda _r: bar.update(1))
    print(format_table(report))
    print(f"wall time {report['wall_time_s']:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=2))
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="learnest", description="Learning-enhanced state estimation "
                                     "for Crazyflie flight logs (LEARNEST).")
    sub = parser.add_subparsers(dest="command", required=True)

    rep = sub.add_parser("reproduce", help="reproduce Table I of the paper on simulated systems")
    rep.add_argument("--task", choices=["cartpole", "robot"], required=True)
    rep.add_argument("--seeds", type=int, default=15)
    rep.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    rep.add_argument("--samples", type=int, default=None, help="evaluation trajectory length in samples (default: the paper's)")
    rep.add_argument("--epochs", type=int, default=None, help="training epochs (default: the paper's)")
    rep.add_argument("--horizon", type=int, default=20, help="MHE horizon N (default 20)")
    rep.add_argument("--workers", type=int, default=1, help="processes to spread the seeds over")
    rep.set_defaults(func=_reproduce)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ValueError as err:  # bad input: one clear line, no traceback
        print(f"learnest: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
