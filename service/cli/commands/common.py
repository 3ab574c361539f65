"""What the command handlers share: reading a batch of flights, the exit status of a batch, the registry's
grid and home."""
from __future__ import annotations

import sys
import time

from learnest.workflows.vocabulary import InvalidInput

_command_started = [time.perf_counter()]   # reset by main(): the command's whole time, imports included


def _read(paths, rate_hz, topics: dict | None = None, cut: str | None = None):
    from learnest.workflows.files import read_flights

    return read_flights(paths, rate_hz=rate_hz, **(topics or {}), cut=cut)


def _read_batch(paths, rate_hz, topics: dict | None = None, cut: str | None = None, *, need: int = 1):
    """Read every flight of ``paths`` past the files that cannot be read (`learnest.ingest.batch.read_batch`):
    each of those is named on stderr with its reason, and the batch goes on (the command then exits with
    status 1, `_batch_status`).  InvalidInput (status 2) when fewer than ``need`` flights were read: nothing
    to go on with."""
    from learnest.workflows.files import format_errors, read_batch

    batch = read_batch(paths, rate_hz=rate_hz, **(topics or {}), cut=cut)
    for note in batch.notes:
        print(note, file=sys.stderr)
    for line in format_errors(batch.errors):
        print(f"learnest: {line}", file=sys.stderr)
    if len(batch.flights) < need:
        failed = f" ({len(batch.errors)} file(s) could not be read)" if batch.errors else ""
        raise InvalidInput(f"no flight logs read from {', '.join(map(str, paths))}{failed}")
    return batch


def _batch_status(errors: list) -> int:
    """Exit status of a command that read several files: 1 when any could not be read."""
    if errors:
        print(f"learnest: {len(errors)} file(s) could not be read (listed above); the others were used",
              file=sys.stderr)
    return 1 if errors else 0


def _registry_grid(rate: float, hint: str = "") -> None:
    if rate != 100.0:
        raise InvalidInput("--rate: flights in the model registry are on the service's 100 Hz grid"
                           + (f"; {hint}" if hint else ""))


def _home() -> str:
    from ...local import Settings

    return str(Settings().home)
