"""Reading many logs at once: one unreadable file is reported and the rest are read (`read_batch`), and flights
whose names collide get a disambiguating suffix (`unique_names`).

A batch of logs from another lab often holds one file that cannot be a flight (no accelerometer, cut short
before its first frame, a README the glob brought along).  `read_flights` raises on the first such file, as
a library call should; the commands that read many files want every good flight and a list of the bad ones
instead: ``BatchRead.errors`` = ``[{"file": path, "message": why}]``.
"""
from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from learnest.errors import InvalidInput

from .flight import IngestError
from .names import unique_names


@dataclass
class BatchRead:
    """What reading a batch of logs gave.

    Attributes
    ----------
    flights : list of Flight
        One per flight read, names made unique (`unique_names`).
    errors : list of dict
        ``{"file": path, "message": why}`` per file (or pair) that could not be read.
    notes : list of str
        Files left out on purpose (documents, sidecars read with their logs), as `collect_logs` says.
    """
    flights: list = field(default_factory=list)
    errors: list = field(default_factory=list)
    notes: list = field(default_factory=list)


def read_batch(paths: Iterable[str | Path], rate_hz: float = 100.0, *, pose_topic: str | None = None,
               imu_topic: str | None = None, cut: str | bool | tuple | None = None) -> BatchRead:
    """Read every flight among ``paths`` (files or folders), going on past the ones that cannot be read.

    Parameters
    ----------
    paths : iterable of str or Path
        Log files and folders, as for `collect_logs`.
    rate_hz : float
        Grid rate, Hz.
    pose_topic, imu_topic, cut
        As for `read_flights` (a malformed cut is raised before any file is read: it is the caller's
        mistake, not a file's).

    Returns
    -------
    BatchRead
    """
    from . import collect_logs, detect, group_files, read_group
    from .align import parse_cut

    parse_cut(cut)
    out = BatchRead()
    logs: list[Path] = []
    for path in paths:
        try:
            found, notes = collect_logs([path])
        except IngestError as err:
            out.errors.append(_error(err.path, err.problem))
            continue
        logs += found
        out.notes += notes
    readable = []
    for log in logs:
        try:
            detect(log)
            readable.append(log)
        except IngestError as err:
            out.errors.append(_error(err.path, err.problem))
    groups = []
    while readable:
        try:
            groups = group_files(readable)
            break
        except IngestError as err:   # e.g. a Vicon export without its cfclient log: that file alone fails
            remaining = [log for log in readable if str(log) != err.path]
            out.errors += [_error(err.path, err.problem)] if len(remaining) < len(readable) else \
                [_error(log, str(err)) for log in readable]
            readable = remaining if len(remaining) < len(readable) else []
    for adapter, files in groups:
        try:
            out.flights.append(read_group(adapter, files, rate_hz, pose_topic=pose_topic, imu_topic=imu_topic,
                                          cut=cut))
        except IngestError as err:
            out.errors.append(_error(err.path, err.problem))
        except InvalidInput as err:
            out.errors.append(_error(files[0], str(err)))
        except (ValueError, TypeError, IndexError, KeyError, OverflowError, MemoryError) as err:
            # an adapter that trips over odd content: this file cannot be read, the batch goes on
            out.errors.append(_error(files[0], f"could not be read ({type(err).__name__}: {err})"))
    unique_names(out.flights)
    return out


def _error(path, message: str) -> dict:
    return {"file": str(path), "message": message}


def format_errors(errors: list[dict]) -> list[str]:
    """One line per file that could not be read: ``"FILE: not read: WHY"``."""
    return [f"{e['file']}: not read: {e['message']}" for e in errors]
