"""Reading one upload's staged files into a flight: the part of an upload that runs in a decoder process
(service.jobs.decoding), so it imports no SQL, web or job machinery (a worker starts in a second, not four).
Every failure is an InvalidInput naming the client's file, never our temp paths.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from pathlib import Path

from learnest.errors import InvalidInput
from learnest.ingest import IngestError, group_files, read_group
from learnest.ingest.flight import Flight as CanonicalFlight

log = logging.getLogger("learnest.uploads")


@dataclass
class StagedFile:
    """One uploaded file copied into the private temp folder.

    Attributes
    ----------
    original_name : str
        The client's file name (metadata only; see `original_basename`).
    path : Path
        Our name for it in the temp folder.
    sha256 : str
        Hex digest of its content.
    size : int
        Bytes.
    role : str
        "log", or "sidecar" for a NanoBench *_metadata.yaml uploaded with its CSV.
    """
    original_name: str      # the client's name: metadata only
    path: Path              # our name for it in the private temp folder
    sha256: str
    size: int
    role: str               # "log" or "sidecar"


def safe_stem(name: str) -> str:
    """A file name's stem reduced to [A-Za-z0-9._-] (other runs become "_"), at most 100 characters, "flight" if
    nothing is left: the flight's name.
    """
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(name).stem).strip("._-")[:100]
    return stem or "flight"


# -- reading ------------------------------------------------------------------------------------------
def read_uploaded_flight(staged: list[StagedFile], pose_topic: str | None = None,
                         imu_topic: str | None = None, cut: str | None = None) -> CanonicalFlight:
    """The adapters decide the format; every failure is InvalidInput naming the client's file."""
    originals = {str(f.path): f.original_name for f in staged}
    logs = [f.path for f in staged if f.role == "log"]
    try:
        groups = group_files(logs)
        if len(groups) != 1:
            raise InvalidInput(f"one flight per upload: {', '.join(originals.values())} make {len(groups)} flights; "
                          "upload each flight's file(s) separately")
        adapter, files = groups[0]
        flight = read_group(adapter, files, pose_topic=pose_topic, imu_topic=imu_topic, cut=cut)
    except IngestError as err:
        name = originals.get(err.path, Path(err.path).name)
        raise InvalidInput(f"{name}: {_scrub(err.problem, originals)}") from None
    except InvalidInput:
        raise
    except Exception as err:  # an adapter bug on odd input is still "this file cannot be read"
        log.exception("ingest failed unexpectedly")
        raise InvalidInput(f"{', '.join(originals.values())}: could not be read ({type(err).__name__})") from None
    _rename_sources(flight, originals)
    flight.meta["name"] = safe_stem(originals[str(files[0])])
    return flight


def _scrub(value, originals: dict[str, str]):
    """Replace our temp paths, and our staged file names (a reader's warning names "upload_0_metadata.yaml"),
    by the client's names anywhere in a message or metadata."""
    if isinstance(value, str):
        for path, name in originals.items():
            value = value.replace(path, name)
        # longest first: "upload_1.csv" is not to be mistaken for part of "upload_1.csv_info.yaml"
        for staged, name in sorted(((Path(p).name, n) for p, n in originals.items()), key=lambda pair: -len(pair[0])):
            value = re.sub(rf"(?<![\w.-]){re.escape(staged)}(?![\w.-])", name.replace("\\", "\\\\"), value)
        return value
    if isinstance(value, dict):
        return {k: _scrub(v, originals) for k, v in value.items()}
    if isinstance(value, list):
        return [_scrub(v, originals) for v in value]
    return value


def _rename_sources(flight: CanonicalFlight, originals: dict[str, str]) -> None:
    for source in flight.meta.get("sources", []):
        source["path"] = originals.get(source["path"], Path(source["path"]).name)
    flight.meta.update(_scrub(dict(flight.meta), originals))
