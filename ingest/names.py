"""Unique flight names in a batch: two different files named ``eckart06`` in two folders must not appear as
the same flight in reports, flagged lists and fallbacks.

A module of its own so `read_flights` (the package's ``__init__``) and `ingest.batch` (which reads through
the package) share it without importing each other.
"""
from __future__ import annotations

import re
from collections import Counter, defaultdict
from pathlib import Path

from .flight import Flight

_UNSAFE = re.compile(r"[^A-Za-z0-9._-]+")
SHA_DIGITS = 8


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
