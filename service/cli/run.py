"""`learnest`'s entry point: parse, check the given paths, run the subcommand, turn errors into one line."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from learnest.workflows.vocabulary import InvalidInput, LearnestError

from .arguments import gap_options_problem
from .commands import (
    _alias_set,
    _audit,
    _export,
    _flights_list,
    _ingest,
    _models_list,
    _models_show,
    _serve,
    _tokens_create,
    _tokens_list,
    _tokens_revoke,
)
from .commands.common import _command_started
from .parser import build_parser
from .usage import check_usage, first_line

# commands that only read or move registry rows: no torch, no worker set-up
REGISTRY_COMMANDS = (_flights_list, _models_list, _models_show, _alias_set, _tokens_create, _tokens_list,
                     _tokens_revoke, _audit)


def _given_paths(args) -> list[str]:
    """The input files and folders a command was given (FILE..., --fit, --score, demo's FOLDER)."""
    paths = [*(getattr(args, "files", None) or []), *(getattr(args, "fit", None) or []),
             *(getattr(args, "score", None) or [])]
    return paths + ([args.folder] if getattr(args, "folder", None) else [])


def main(argv=None) -> int:
    """Run the `learnest` command line on `argv` (default: sys.argv[1:]) and return the exit status.

    0 on success or --help; 2 for a bad argument or a LearnestError (printed on one line, no traceback);
    otherwise the subcommand's status (e.g. `ingest --strict` returns 1 when a flight fails the quality checks).
    """
    _command_started[0] = time.perf_counter()
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as stop:  # a bad argument (argparse printed usage and why) or --help
        return int(stop.code or 0)
    if args.func is _export and not args.format:  # the format is checked before any work, like the other arguments
        from learnest.workflows.files import format_of

        try:
            format_of(args.output)
        except InvalidInput as err:
            print(f"learnest export: error: {err} (or give --format)", file=sys.stderr)
            return 2
    gaps = gap_options_problem(args)   # a gap plan that would never end is refused before any work
    if gaps:
        print(f"learnest {args.command}: error: {gaps}", file=sys.stderr)
        return 2
    given = _given_paths(args)
    missing = [p for p in given if not Path(p).expanduser().exists()]
    # nothing there at all: said before any import, progress bar or stored row (a typo costs nothing); some
    # there: the batch reads them and names each missing one with the other unreadable files
    if missing and (len(missing) == len(given) or getattr(args, "strict", False)):
        print(f"learnest {args.command}: error: no such file or folder: {', '.join(missing)}", file=sys.stderr)
        return 2
    try:   # what the arguments alone show is wrong, said before the estimators load (seconds)
        check_usage(args)
    except InvalidInput as err:
        print(f"learnest: error: {err}", file=sys.stderr)
        return 2
    if (line := first_line(args)) is not None:
        print(line, flush=True)
    if args.func not in (_ingest, _serve, _export) + REGISTRY_COMMANDS:  # the rest run the networks here
        from ..local import init_worker

        init_worker()  # the networks are tiny: extra threads only add contention
    try:
        return args.func(args)
    except LearnestError as err:  # bad input, unknown model, failed training: one clear line, no traceback
        print(f"learnest: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:  # Ctrl-C: the command cleaned up on the way out (train: nothing registered)
        print("learnest: interrupted", file=sys.stderr)
        return 130
