"""Storing flights from local files as an upload would: a flight's files with the sidecars their readers use,
and several files grouped into flights, those that cannot be read listed (or, strictly, raised)."""
from __future__ import annotations

from contextlib import ExitStack
from pathlib import Path

from learnest.errors import InvalidInput
from learnest.ingest.flight import existing_file
from learnest.ingest.sidecar import info_sidecar

from ..jobs.services import Services
from ..operations.uploads import LocalFile
from ..operations.uploads import add_flight as add_uploaded_flight
from ..operations.uploads import readable_groups as group_readable
from ..storage.tables import FlightRecord


def flight_files(paths) -> list[Path]:
    """The given files plus the sidecars their readers would use: for a NanoBench CSV the *_metadata.yaml
    next to it, for a uSD log logNNN crazyswarm2's infoNNN.yaml."""
    files: dict[Path, Path] = {}
    for path in map(Path, paths):
        existing_file(path, "flight log")
        files.setdefault(path.resolve(), path)
        sidecar = path.with_name(f"{path.stem}_metadata.yaml")
        if path.suffix.lower() == ".csv" and sidecar.is_file():
            files.setdefault(sidecar.resolve(), sidecar)
        info = info_sidecar(path)
        if info is not None:
            files.setdefault(info.resolve(), info)
    return list(files.values())


def add_flight(services: Services, paths, *, pose_topic: str | None = None,
               imu_topic: str | None = None, cut: str | None = None) -> tuple[FlightRecord, bool]:
    """Store the log file(s) of one flight exactly as an upload would (with the topics chosen, for MCAP
    recordings and ROS bags, and the cut, `learnest.ingest.align.parse_cut`).  -> (row, created); created is
    False when the same content was stored before (its existing row)."""
    with ExitStack() as stack:
        uploads = [LocalFile(path.name, stack.enter_context(open(path, "rb"))) for path in flight_files(paths)]
        return add_uploaded_flight(services.db, services.blobs, uploads, pose_topic=pose_topic, imu_topic=imu_topic,
                                   cut=cut)


class UnreadableFile(InvalidInput):
    """``train(..., strict=True)``: a given file could not be read, so nothing was trained (the message names
    the file and why; `learnest train --strict` exits with status 1 on it)."""


def log_groups(paths, strict: bool) -> tuple[list, list[dict]]:
    """The flights among ``paths`` (files or folders) as `learnest.ingest.group_files` groups them, and the
    files that cannot be one (``[{"file", "message"}]``); with ``strict`` the first of those is raised."""
    from learnest.ingest import IngestError, collect_logs

    logs, errors = [], []
    for path in paths:
        try:
            logs += collect_logs([path])[0]
        except IngestError as err:
            errors.append({"file": err.path, "message": err.problem})
    groups, unreadable = readable_groups(logs)
    errors += unreadable
    if strict and errors:
        raise UnreadableFile(f"{errors[0]['file']}: not read: {errors[0]['message']}")
    return groups, errors


def store_groups(services: Services, groups: list, errors: list[dict], strict: bool,
                  read: dict) -> list[tuple[FlightRecord, bool]]:
    """Store each group as `add_flight` does -> [(row, created)]; a group that cannot be read is appended to
    ``errors`` (raised as `UnreadableFile` with ``strict``) and the others are stored."""
    stored = []
    for _, files in groups:
        try:
            stored.append(add_flight(services, files, **read))
        except InvalidInput as err:
            message = str(err).removeprefix(f"{Path(files[0]).name}: ")   # the upload's message names the file
            if strict:
                raise UnreadableFile(f"{files[0]}: not read: {message}") from None
            errors.append({"file": str(files[0]), "message": message})
    return stored


def nothing_read(what: str, errors: list[dict]) -> str:
    return what + "".join(f"; {e['file']}: {e['message']}" for e in errors)


def readable_groups(paths) -> tuple[list, list[dict]]:
    """The flights among ``paths`` as an upload groups them (`service.operations.uploads.readable_groups`),
    leaving out (and listing) the files no adapter recognises or that lack their pair:
    ``(groups, [{"file", "message"}])``."""
    groups, left_out = group_readable([Path(path) for path in paths])
    return groups, [{"file": err.path, "message": err.problem} for _, err in left_out]
