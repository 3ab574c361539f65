"""Raw flight logs -> canonical Flights.

`read_flights(paths)` looks at each file's content (never only its extension), pairs files that belong to
one flight (a Vicon export with a cfclient log), runs the adapter and the quality checks, and returns one
Flight per flight.  Every problem is an `IngestError` naming the file.
"""
from __future__ import annotations

import importlib
from pathlib import Path

from .flight import Flight, IngestError, existing_file

# adapter name -> (module, sniff function); order matters only for speed (cheap binary magic first)
SINGLE_FILE_ADAPTERS = {
    "usd": (".usd", "sniff"),
    "mcap": (".mcap_log", "sniff"),
    "nanobench": (".nanobench", "sniff"),
}
PAIR_ROLES = {"vicon": (".vicon_csv", "sniff_vicon"), "cfclient": (".vicon_csv", "sniff_cfclient")}


def _sniffer(module: str, function: str):
    return getattr(importlib.import_module(module, __name__), function)  # imported on first use: CLI start stays fast


def detect(path) -> str:
    """The adapter (or pair role) that reads this file, decided from its content."""
    path = existing_file(path, "flight log")
    for name, (module, function) in {**SINGLE_FILE_ADAPTERS, **PAIR_ROLES}.items():
        sniff = _sniffer(module, function)
        if sniff(path):
            return name
    raise IngestError(path, "unrecognised format (expected a NanoBench CSV, a Crazyflie uSD log, an MCAP "
                            "file, or a Vicon CSV export together with a cfclient CSV log)")


def group_files(paths) -> list[tuple[str, list[Path]]]:
    """[(adapter, [files])]: one entry per flight.  Vicon exports and cfclient logs given together are
    paired in name order (each pair is one flight); every other file is a flight of its own."""
    singles, roles = [], {"vicon": [], "cfclient": []}
    for path in map(Path, paths):
        kind = detect(path)
        (roles[kind] if kind in roles else singles).append((kind, [path]))
    vicon, cfclient = sorted(roles["vicon"]), sorted(roles["cfclient"])
    if len(vicon) != len(cfclient):
        longer, shorter = (vicon, cfclient) if len(vicon) > len(cfclient) else (cfclient, vicon)
        missing = "cfclient log" if longer is vicon else "Vicon export"
        raise IngestError(longer[len(shorter)][1][0], f"needs a {missing} of the same flight given with it")
    pairs = [("vicon+cfclient", [v[1][0], c[1][0]]) for v, c in zip(vicon, cfclient)]
    return singles + pairs


def read_group(adapter: str, files: list[Path], rate_hz: float = 100.0) -> Flight:
    from .quality import assess

    if adapter == "vicon+cfclient":
        from .vicon_csv import read_pair
        flight = read_pair(files[0], files[1], rate_hz=rate_hz)
    else:
        module = importlib.import_module(SINGLE_FILE_ADAPTERS[adapter][0], __name__)
        flight = module.read(files[0], rate_hz=rate_hz)
    # the adapter may already know of problems (e.g. an ambiguous clock alignment): keep them
    earlier = flight.meta.get("quality", {}).get("issues", [])
    checked = assess(flight)
    issues = list(dict.fromkeys(earlier + checked["issues"]))
    flight.meta["quality"] = {"ok": not issues, "issues": issues}
    flight.meta.setdefault("name", files[0].stem)
    return flight


def read_flights(paths, rate_hz: float = 100.0) -> list[Flight]:
    return [read_group(adapter, files, rate_hz) for adapter, files in group_files(paths)]


def summary(flight: Flight) -> dict:
    """The per-flight record `learnest ingest --json` prints."""
    return {"source": [s["path"] for s in flight.meta.get("sources", [])], "adapter": flight.meta.get("adapter"),
            "duration_s": round(flight.duration_s, 3), "rate_hz": round(flight.rate_hz, 3),
            "samples": len(flight.t), "clock_offset_s": flight.meta.get("clock_offset_s"),
            "quality": flight.quality}


__all__ = ["Flight", "IngestError", "detect", "group_files", "read_flights", "read_group", "summary"]
