"""Uploads: the log file(s) of one flight -> staged, deduplicated, read and stored (blobs + one row).

The one way a flight gets in, whoever brings it: POST /flights, the upload form of the web pages and the
CLI's `learnest train FILE...` all call `add_flight`.  One upload is one flight: its files (a NanoBench CSV
[+ its *_metadata.yaml], a uSD log, an MCAP file, a ROS bag (.bag, .db3), or a Vicon export + cfclient log)
must make exactly one flight, otherwise InvalidInput (422) - several flights are several uploads, so each gets
its own id, dedupe key and error.  A recording with several vehicles is one upload per vehicle, each naming
its pose (and IMU) topic: the chosen topics are part of the dedupe key.
Several flights at once (POST /flights/batch, the upload form): `add_flights` groups the files into flights
(`group_uploads`, the rule of `learnest.ingest.group_files`) and stores each with `add_flight`, answering per
file what was stored, found stored already or refused and why; one bad file does not stop the others.
Client file names are metadata only: files are staged under names of ours, and messages
name the client's file, never our temp paths.
"""
from __future__ import annotations

import hashlib
import logging
import re
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Protocol

from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from learnest.errors import Conflict
from learnest.ingest.align import cut_text, parse_cut
from learnest.ingest.flight import Flight as CanonicalFlight
from learnest.ingest.flight import IngestError
from learnest.ingest.sidecar import CRAZYSWARM_CONFIG

from ..jobs.reading import StagedFile, read_uploaded_flight
from ..storage.blobs import CHUNK, BlobStore, storage_errors
from ..storage.database import Database, discard_blobs
from ..storage.tables import FlightFile, FlightRecord, utcnow

log = logging.getLogger("learnest.uploads")

SIDECAR_SUFFIXES = ("_metadata.yaml", "_metadata.yml")   # NanoBench: <stem>_metadata.yaml next to <stem>.csv
INFO_SIDECAR = re.compile(r"info(\d+)\.ya?ml")            # crazyswarm2-tools: infoNNN.yaml next to the uSD log logNNN


class Upload(Protocol):
    """What the upload code reads of a file: FastAPI's UploadFile, or a LocalFile."""

    @property
    def filename(self) -> str | None:
        """The client's file name (None when it sent none)."""

    @property
    def file(self) -> BinaryIO:
        """The content as a binary file object (the copy seeks to its start)."""


@dataclass
class LocalFile:
    """A file on disk in the shape of an uploaded file (the CLI's uploads)."""

    filename: str
    file: BinaryIO


def add_flight(db: Database, blobs: BlobStore, uploads: Sequence[Upload], vehicle: str | None = None,
               notes: str | None = None, *, pose_topic: str | None = None, imu_topic: str | None = None,
               cut: str | None = None, decode: Callable[..., CanonicalFlight] | None = None,
               created_by: str | None = None) -> tuple[FlightRecord, bool]:
    """Store the log file(s) of one flight, unless the same content is stored already.

    Parameters
    ----------
    db, blobs
        Where the row and the files go.
    uploads
        The file(s) of ONE flight (see the module docstring for what makes one flight).
    vehicle, notes
        Free text kept on the row; the vehicle defaults to what the log itself says.
    pose_topic, imu_topic
        For MCAP recordings and ROS bags: the topics to read (see learnest.ingest.read_group); checked
        before anything is stored.
    cut
        The stretch to keep (`learnest.ingest.align.parse_cut`: "auto", "none", "START:STOP" s); checked before
        anything is stored.  A cut other than "auto" is part of the dedupe key (another stretch, another flight).
    decode
        ``decode(staged, pose_topic=..., imu_topic=...)`` -> the flight: the server passes its decoder pool's
        (service.jobs.decoding: worker processes, a time limit); default `read_uploaded_flight`, here.
    created_by
        The name of the token that uploads it (kept on a new row; None without a token).

    Returns
    -------
    (row, created)
        ``created`` is False when identical content was uploaded before: ``row`` is then that upload's row,
        and nothing is read or written.

    Raises
    ------
    InvalidInput
        A file cannot be read, the files make no flight or several (the message names the file), or a topic
        is not a topic name.
    """
    topics = {"pose_topic": _topic_or_none(pose_topic, "pose_topic"),
              "imu_topic": _topic_or_none(imu_topic, "imu_topic")}
    window = cut_text(parse_cut(cut))   # InvalidInput (422) for a malformed cut, before anything is stored
    choice = {**topics, "cut": None if window == "auto" else window}
    with blobs.temp_dir() as directory:
        staged = stage_uploads(uploads, directory)
        sha = content_sha256(staged, choice)
        row = find_by_sha(db, sha)
        if row is not None:
            return row, False
        flight = (decode or read_uploaded_flight)(staged, **topics, cut=window)
        return store_flight(db, blobs, staged, flight, sha, vehicle, notes, created_by)


def recut_flight(db: Database, blobs: BlobStore, row: FlightRecord, cut: str | None, *,
                 decode: Callable[..., CanonicalFlight] | None = None,
                 created_by: str | None = None) -> tuple[FlightRecord, bool]:
    """Another stretch of a stored flight: its raw file(s), read again with ``cut`` and stored as an upload of
    those files with that cut would be (`add_flight`, with the topics the flight was read with).

    Parameters
    ----------
    row
        The stored flight (its raw files are read from the blob store).
    cut
        "auto", "none" or "START:STOP" in seconds from the recording's start (`learnest.ingest.align.parse_cut`).

    Returns
    -------
    (row, created)
        The flight holding that stretch: new, or the one already stored with the same files and cut (``row``
        itself for the cut it was read with).

    Raises
    ------
    InvalidInput
        A malformed cut, or one that leaves fewer than 2 samples.
    """
    choice = (row.meta or {}).get("topic_choice") or {}
    with ExitStack() as stack:
        uploads = [LocalFile(f.original_name, stack.enter_context(blobs.path(f.sha256).open("rb")))
                   for f in sorted(row.files, key=lambda f: f.position)]
        return add_flight(db, blobs, uploads, row.vehicle, row.notes, pose_topic=choice.get("pose_topic"),
                          imu_topic=choice.get("imu_topic"), cut=cut, decode=decode, created_by=created_by)


# -- staging uploads ----------------------------------------------------------------------------------
def original_basename(filename: str | None, index: int) -> str:
    """The client's file name without any directory part or control characters (for display only)."""
    name = re.split(r"[/\\]", filename or "")[-1]
    name = "".join(ch for ch in name if ch.isprintable()).strip()[:255]
    return name if name not in ("", ".", "..") else f"file{index + 1}"


def _safe_suffix(name: str) -> str:
    suffix = Path(name).suffix
    return suffix.lower() if re.fullmatch(r"\.[A-Za-z0-9]{1,10}", suffix) else ""


def _sidecar_owner(name: str, log_stems: dict[str, int]) -> tuple[int, str] | None:
    """(index of the log a sidecar belongs to, the name the reader looks for next to that log's staged copy)."""
    for suffix in SIDECAR_SUFFIXES:
        if name.endswith(suffix) and name[:-len(suffix)] in log_stems:
            return log_stems[name[:-len(suffix)]], "_metadata.yaml"
    info = INFO_SIDECAR.fullmatch(name)
    if info and f"log{info[1]}" in log_stems:
        return log_stems[f"log{info[1]}"], "_info.yaml"
    crazyswarm = CRAZYSWARM_CONFIG.fullmatch(name)   # <stem>_crazyflies.yaml, or crazyflies.yaml with one recording
    if crazyswarm and (crazyswarm["stem"] in log_stems or (crazyswarm["stem"] is None and len(log_stems) == 1)):
        return log_stems[crazyswarm["stem"]] if crazyswarm["stem"] else next(iter(log_stems.values())), \
            "_crazyflies.yaml"
    return None


def stage_uploads(uploads: Sequence[Upload], directory: Path) -> list[StagedFile]:
    """Copy the uploads to `directory` as upload_<i><.ext> (never the client's name), hashing on the way.
    A NanoBench metadata YAML uploaded with its CSV, a crazyswarm2 infoNNN.yaml with its uSD log logNNN, or a
    crazyswarm2 crazyflies.yaml with its MCAP recording / ROS 2 bag, is staged where the reader looks for it."""
    names = [original_basename(upload.filename, i) for i, upload in enumerate(uploads)]
    log_stems = {Path(name).stem: i for i, name in enumerate(names)
                 if not name.endswith(SIDECAR_SUFFIXES) and not INFO_SIDECAR.fullmatch(name)
                 and not CRAZYSWARM_CONFIG.fullmatch(name)}
    staged = []
    for i, (upload, name) in enumerate(zip(uploads, names, strict=True)):
        owner = _sidecar_owner(name, log_stems)
        if owner is not None:   # where the reader looks: upload_<i>_metadata.yaml, upload_<i><ext>_info.yaml,
            # upload_<i>_crazyflies.yaml
            index, suffix = owner
            log_name = f"upload_{index}{_safe_suffix(names[index])}" if suffix == "_info.yaml" else f"upload_{index}"
            path, role = directory / f"{log_name}{suffix}", "sidecar"
        else:
            path, role = directory / f"upload_{i}{_safe_suffix(name)}", "log"
        with storage_errors("accept uploads"):
            sha, size = _copy_and_hash(upload.file, path)
        staged.append(StagedFile(name, path, sha, size, role))
    return staged


def _copy_and_hash(source, target: Path) -> tuple[str, int]:
    """Copy the upload to `target`, hashing on the way -> (sha256, size in bytes)."""
    digest = hashlib.sha256()
    size = _copy(source, target, digest)
    return digest.hexdigest(), size


def _copy(source, target: Path, digest=None) -> int:
    """Copy the upload to `target` from its start (feeding `digest` when given) -> its size in bytes."""
    size = 0
    source.seek(0)
    with open(target, "wb") as handle:
        for chunk in iter(lambda: source.read(CHUNK), b""):
            if digest is not None:
                digest.update(chunk)
            size += len(chunk)
            handle.write(chunk)
    return size


def content_sha256(staged: list[StagedFile], topics: dict[str, str | None] | None = None) -> str:
    """The dedupe key: a single file's own sha256, else the sha256 of the sorted sha256s (one per line).  With
    chosen topics (one vehicle of a recording), the sha256 of that key and "name=topic" lines: each vehicle of
    one bag is its own flight."""
    if len(staged) == 1:
        key = staged[0].sha256
    else:
        key = hashlib.sha256("\n".join(sorted(f.sha256 for f in staged)).encode()).hexdigest()
    chosen = sorted(f"{name}={topic}" for name, topic in (topics or {}).items() if topic)
    return hashlib.sha256("\n".join([key, *chosen]).encode()).hexdigest() if chosen else key


def _topic_or_none(topic: str | None, what: str) -> str | None:
    from ..storage.references import check_topic

    return check_topic(topic, what) if topic and topic.strip() else None


# -- storing ------------------------------------------------------------------------------------------
def store_flight(db: Database, blobs: BlobStore, staged: list[StagedFile], flight: CanonicalFlight, sha: str,
                 vehicle: str | None, notes: str | None, created_by: str | None = None) -> tuple[FlightRecord, bool]:
    """Blobs first (fsync + rename), then the row; -> (row, created).  A concurrent upload of the same
    content makes our insert fail on the unique sha256: we answer with its row.  Names are unique (the
    evaluation matches a model's training flight by name): a taken name gets the content hash appended.

    The name is chosen before any blob is written (the normalized flight's bytes hold it), and a write that
    fails (a name taken meanwhile, a full blob folder: `StorageUnavailable`) removes the blobs no row names.
    The staged files stay in the scratch folder until the end (the blobs are links to them), so the attempt
    under the next name stores every file again: no row is committed naming a blob that is not there."""
    base = flight.meta["name"]
    for name in free_names(db, base, sha):
        flight.meta["name"] = name
        written: list[str] = []
        try:
            with blobs.writing():
                written.append(blobs.put_bytes(flight.to_bytes()))
                # kept: a retry under the other name stores them again once this attempt's blobs are collected
                written += [blobs.put_file(f.path, f.sha256, keep=True) for f in staged]
                with db.transaction() as session:
                    row = _flight_row(flight, sha, written[0], staged, vehicle, notes)
                    row.created_by = created_by
                    session.add(row)
                return row, True
        except IntegrityError:
            discard_blobs(db, blobs, written)
            existing = find_by_sha(db, sha)
            if existing is not None:
                return existing, False
        except BaseException:
            discard_blobs(db, blobs, written)
            raise
    # both names taken: by other content, or one of them by a concurrent upload of these very bytes, which
    # committed before our look at the free names (then it is the answer, as on the IntegrityError above)
    existing = find_by_sha(db, sha)
    if existing is not None:
        return existing, False
    raise Conflict(f"a flight named {base!r} already exists and so does {base}-{sha[:8]}")


def free_names(db: Database, base: str, sha: str) -> list[str]:
    """The names a flight may take, in order: ``base`` and ``base-<sha[:8]>``, less those already taken."""
    candidates = [base, f"{base}-{sha[:8]}"]
    with db.transaction() as session:
        taken = set(session.scalars(select(FlightRecord.name).where(FlightRecord.name.in_(candidates))))
    return [name for name in candidates if name not in taken]


def _flight_row(flight: CanonicalFlight, sha: str, flight_blob: str, staged: list[StagedFile],
                vehicle: str | None, notes: str | None) -> FlightRecord:
    meta = flight.meta
    return FlightRecord(sha256=sha, name=meta["name"], adapter=meta.get("adapter") or "unknown",
                  vehicle=vehicle or _text_or_none(meta.get("vehicle")), notes=notes,
                  duration_s=flight.duration_s, rate_hz=flight.rate_hz, samples=len(flight.t),
                  quality_ok=bool(flight.quality["ok"]), quality=flight.quality,
                  clock_offset_s=meta.get("clock_offset_s"), flight_blob=flight_blob, meta=meta,
                  created_at=utcnow(),
                  files=[FlightFile(position=i, original_name=f.original_name, sha256=f.sha256, size_bytes=f.size,
                                    role=f.role) for i, f in enumerate(staged)])


def _text_or_none(value) -> str | None:
    return None if value is None else str(value)[:200]


def find_by_sha(db: Database, sha: str) -> FlightRecord | None:
    """The flight stored under this content sha256 (see `content_sha256`), or None."""
    with db.transaction() as session:
        return session.scalar(select(FlightRecord).where(FlightRecord.sha256 == sha))


# -- several flights in one upload ----------------------------------------------------------------------
MAX_BATCH_FILES = 200   # files in one batch upload: a folder's worth of flights with their sidecars


@dataclass
class FileOutcome:
    """What became of one file of a batch upload.

    Attributes
    ----------
    file : str
        The client's file name.
    status : str
        "stored" (a new flight), "existing" (identical content was stored before: that flight) or "refused".
    flight : FlightRecord or None
        The flight the file is part of (stored or existing).
    message : str or None
        Why it was refused, naming the file.
    http_status : int or None
        The status the refusal would have had as an upload of its own (422 unreadable, 503 busy, ...).
    """
    file: str
    status: str
    flight: FlightRecord | None = None
    message: str | None = None
    http_status: int | None = None


def _is_sidecar(name: str) -> bool:
    return (name.endswith(SIDECAR_SUFFIXES) or INFO_SIDECAR.fullmatch(name) is not None
            or CRAZYSWARM_CONFIG.fullmatch(name) is not None)


def readable_groups(paths: Sequence[Path]) -> tuple[list[tuple[str, list[Path]]], list[tuple[Path, IngestError]]]:
    """The flights among ``paths`` as `learnest.ingest.group_files` groups them, leaving out the files no adapter
    recognises and those that lack their other half (a Vicon export without its cfclient log, or the reverse).

    Returns
    -------
    (groups, left_out)
        groups: ``[(adapter, [files])]``, one per flight; left_out: ``[(path, IngestError)]``, each file left
        out with the error that says why (in the order found).
    """
    from learnest.ingest import detect, group_files

    left_out: list[tuple[Path, IngestError]] = []
    readable: list[Path] = []
    for path in paths:
        try:
            detect(path)
            readable.append(path)
        except IngestError as err:
            left_out.append((path, err))
    while readable:
        try:
            return group_files(readable), left_out
        except IngestError as err:   # a file without its other half: that file only (the one the error names)
            named = [path for path in readable if str(path) == err.path] or readable[-1:]
            left_out.append((named[0], err))
            readable.remove(named[0])
    return [], left_out


def group_uploads(uploads: Sequence[Upload], directory: Path) -> tuple[list[list[int]], dict[int, str]]:
    """The flights among uploaded files, grouped as `learnest.ingest.group_files` groups files on disk.

    Vicon exports and cfclient logs are paired in the order of their client names; a cfclient log carrying the
    received pose is a flight of its own when the Vicon exports are paired without it; every other log is a
    flight of its own; a metadata sidecar goes with its log.  What cannot be placed is refused, not the batch.

    Parameters
    ----------
    uploads
        The files, in the order posted.
    directory
        A scratch folder: the logs are copied there (under names of ours) to tell their formats from their content.

    Returns
    -------
    (groups, refused)
        groups: per flight, the indices of its files in `uploads` (the log(s) first, then its sidecars);
        refused: {index: why}, the reason naming the client's file.
    """
    names = [original_basename(upload.filename, i) for i, upload in enumerate(uploads)]
    logs = [i for i, name in enumerate(names) if not _is_sidecar(name)]
    log_stems = {Path(names[i]).stem: i for i in logs}
    refused: dict[int, str] = {}
    owner_of: dict[int, int] = {}
    for i, name in enumerate(names):
        if i in logs:
            continue
        owner = _sidecar_owner(name, log_stems)
        if owner is None:
            refused[i] = f"{name}: a metadata sidecar without its flight log in this upload (give the log with it)"
        else:
            owner_of[i] = owner[0]
    # copies named by rank in client-name order: group_files pairs Vicon exports and cfclient logs in path order
    paths: dict[int, Path] = {}
    for rank, i in enumerate(sorted(logs, key=lambda i: (names[i], i))):
        paths[i] = directory / f"{rank:06d}{_safe_suffix(names[i])}"
        with storage_errors("accept uploads"):
            _copy(uploads[i].file, paths[i])   # to tell the format only: stage_uploads hashes what is stored
    index_of = {str(path): i for i, path in paths.items()}

    def reason(err: IngestError) -> str:
        i = index_of.get(str(err.path))
        problem = err.problem
        for path, j in index_of.items():
            problem = problem.replace(path, names[j])
        return f"{names[i] if i is not None else Path(str(err.path)).name}: {problem}"

    groups, left_out = readable_groups(sorted(paths.values(), key=str))
    for path, err in left_out:
        refused[index_of[str(path)]] = reason(err)
    flights = []
    for _adapter, files in groups:
        members = [index_of[str(path)] for path in files]
        flights.append(members + sorted(s for s, owner in owner_of.items() if owner in members))
    return flights, refused


def add_flights(db: Database, blobs: BlobStore, uploads: Sequence[Upload], vehicle: str | None = None,
                notes: str | None = None, *, pose_topic: str | None = None, imu_topic: str | None = None,
                cut: str | None = None, decode: Callable[..., CanonicalFlight] | None = None,
                created_by: str | None = None) -> list[FileOutcome]:
    """Store the flights among several files (several flights, or a folder's worth): each flight as `add_flight`
    stores one, each file answered on its own; one bad file or flight does not stop the others.

    Parameters
    ----------
    uploads
        Log files of any number of flights, with their sidecars (grouped by `group_uploads`), at most
        MAX_BATCH_FILES.
    vehicle, notes, pose_topic, imu_topic, cut, created_by
        As for `add_flight`, for every flight of the batch (a topic chosen for a log without topics refuses that
        flight).

    Returns
    -------
    list of FileOutcome
        One per upload, in the order posted.

    Raises
    ------
    InvalidInput
        No file, more than MAX_BATCH_FILES, a malformed cut or topic (the request's own mistakes, before any file
        is read).
    """
    from learnest.errors import InvalidInput, LearnestError

    if not uploads:
        raise InvalidInput("no file: give the log file(s) of one or more flights")
    if len(uploads) > MAX_BATCH_FILES:
        raise InvalidInput(f"{len(uploads)} files in one upload: at most {MAX_BATCH_FILES}; upload them in parts")
    _topic_or_none(pose_topic, "pose_topic"), _topic_or_none(imu_topic, "imu_topic")
    parse_cut(cut)
    names = [original_basename(upload.filename, i) for i, upload in enumerate(uploads)]
    with blobs.temp_dir() as directory:
        groups, refused = group_uploads(uploads, directory)
    outcomes = {i: FileOutcome(names[i], "refused", message=why, http_status=422) for i, why in refused.items()}
    for members in groups:
        try:
            row, created = add_flight(db, blobs, [uploads[i] for i in members], vehicle, notes, pose_topic=pose_topic,
                                      imu_topic=imu_topic, cut=cut, decode=decode, created_by=created_by)
        except LearnestError as err:
            log.info("batch upload: %s refused: %s", ", ".join(names[i] for i in members), err)
            for i in members:
                outcomes[i] = FileOutcome(names[i], "refused", message=str(err), http_status=err.status)
            continue
        for i in members:
            outcomes[i] = FileOutcome(names[i], "stored" if created else "existing", flight=row)
    return [outcomes[i] for i in range(len(uploads))]
