"""Reading many logs at once: one unreadable file is reported and the rest are read (`read_batch`), and flights
whose names collide get a disambiguating suffix (`unique_names`).

A batch of logs from another lab often holds one file that cannot be a flight (no accelerometer, cut short
before its first frame, a README the glob brought along).  `read_flights` raises on the first such file, as
a library call should; the commands that read many files want every good flight and a list of the bad ones
instead: ``BatchRead.errors`` = ``[{"file": path, "message": why}]``.
"""
from __future__ import annotations

import re
from collections import Counter, defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

from learnest.errors import InvalidInput

from .flight import Flight, IngestError

# A suffix built from a folder name keeps the characters a stored flight name may hold.
_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
SHA_DIGITS = 8


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


def unique_names(flights: list[Flight]) -> list[str]:
    """Give flights whose names collide a disambiguating suffix, in place (``meta["name"]``), and return
    the names.

    Two different files named ``eckart06`` in two folders become ``eckart06-runA`` and ``eckart06-runB``
    (their parent folders' names, when those differ); otherwise ``eckart06-1a2b3c4d`` (the first 8 hex
    digits of the log's sha256).  Flights read twice from the same file keep a counter (``eckart06-2``).
    Names that do not collide are left as they are.
    """
    names = [flight.name for flight in flights]
    by_name = defaultdict(list)
    for index, name in enumerate(names):
        by_name[name].append(index)
    for name, indices in by_name.items():
        if len(indices) < 2:
            continue
        folders = [_folder(flights[i]) for i in indices]
        shas = [_sha(flights[i]) for i in indices]
        if all(folders) and len(set(folders)) == len(folders):
            suffixes = folders
        elif all(shas) and len(set(shas)) == len(shas):
            suffixes = shas
        else:
            suffixes = [str(k) for k in range(1, len(indices) + 1)]
        for i, suffix in zip(indices, suffixes):
            names[i] = f"{name}-{suffix}"
    taken = Counter(names)
    for i, name in enumerate(names):   # a suffixed name may meet a real one ("a-b" next to "a" in folder "b")
        if taken[name] > 1:
            names[i] = f"{name}-{i + 1}"
    for flight, name in zip(flights, names):
        if flight.name != name:
            flight.meta["name"] = name
    return names


def _source(flight: Flight) -> dict:
    sources = flight.meta.get("sources") or [{}]
    return sources[0] if isinstance(sources[0], dict) else {}


def _folder(flight: Flight) -> str:
    path = _source(flight).get("path")
    return _UNSAFE.sub("_", Path(path).parent.name).strip("._-") if path else ""


def _sha(flight: Flight) -> str:
    return str(_source(flight).get("sha256") or "")[:SHA_DIGITS]
