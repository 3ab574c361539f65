"""What a `learnest` command checks, and says, before it loads anything heavy.

The estimators, torch and the service stack take seconds to import. A usage error (`learnest evaluate`
without ``--model``, a misspelled method) must not wait for them, nor must the first line of a long command:
`check_usage` refuses what the arguments alone show is wrong, and `first_line` is what a slow command prints
at once. Both import only the light modules the argument types already use (no torch, SciPy or CasADi);
tests/service/cli/test_cli_usage.py runs them in a fresh interpreter to check.
"""
from __future__ import annotations

from pathlib import Path

from learnest.workflows.vocabulary import EVALUATION_METHODS, InvalidInput, parse_methods

from .arguments import evaluation_settings
from .commands import _demo, _diagnose, _evaluate, _thrust_map, _train
from .commands.common import _registry_grid


def check_usage(args) -> None:
    """Raise InvalidInput when the parsed ``args`` cannot run, whatever the files hold: a missing option,
    options that exclude each other, a method name, the registry's grid."""
    check = _CHECKS.get(args.func)
    if check is not None:
        check(args)


def first_line(args) -> str | None:
    """The line a slow command prints before it loads the estimators (None: the command's own output comes
    soon enough)."""
    if args.func is _demo:
        return (f"demo: reading the flight logs in {args.folder}, then training on one flight and scoring the "
                "others (loading the estimators first takes a few seconds)")
    return None


def _check_evaluate(args) -> None:
    evaluation_settings(args)
    if args.new:
        return
    if not args.model or not args.files:
        raise InvalidInput("evaluate needs --model REF and FILE..., or --new [--alias ALIAS]")
    if args.store:
        _registry_grid(args.rate, "pass --no-store to evaluate on another grid without storing")


def _check_diagnose(args) -> None:
    parse_methods(args.methods)
    if args.simulate is not None or args.system in ("cartpole", "robot"):
        if args.files:
            raise InvalidInput("give flight files or --simulate, not both")
        if args.register:
            raise InvalidInput("--register registers a repaired Crazyflie model: give flight files, not --simulate")
        return
    if not args.files:
        raise InvalidInput("diagnose needs flight files (or --system cartpole|robot --simulate ...)")
    if args.register:
        from ..local import check_name

        _registry_grid(args.rate)
        check_name(args.register)


def _check_thrust_map(args) -> None:
    if args.bench:
        if args.fit or args.score:
            raise InvalidInput("thrust-map: give --bench CSV, or --fit and --score flights, not both")
    elif not args.fit or not args.score:
        raise InvalidInput("thrust-map needs --fit and --score flight logs (or --bench CSV, a bench calibration)")


def _check_demo(args) -> None:
    _registry_grid(args.rate)
    if not Path(args.folder).is_dir():
        raise InvalidInput(f"{args.folder}: not a folder")
    parse_methods(args.methods, EVALUATION_METHODS)


_CHECKS = {_evaluate: _check_evaluate, _diagnose: _check_diagnose, _thrust_map: _check_thrust_map,
           _demo: _check_demo, _train: lambda args: _registry_grid(args.rate)}
