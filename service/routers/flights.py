"""/flights: upload (ingest + dedupe), list, detail, normalized data as CSV, raw files, delete.

One upload is one flight: its files (a NanoBench CSV [+ its *_metadata.yaml], a uSD log, an MCAP file, or
a Vicon export + cfclient log) must make exactly one flight, otherwise 422 — several flights are several
uploads, so each gets its own id, dedupe key and error.
"""
from __future__ import annotations

import hashlib
import io
import logging
import re
import shutil
import tempfile
import zipfile
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Literal

import numpy as np
from fastapi import APIRouter, Depends, File, Form, Query, Response, UploadFile
from fastapi.responses import FileResponse
from sqlalchemy import delete, func, select
from sqlalchemy.exc import IntegrityError
from starlette.background import BackgroundTask

from learnest.errors import Conflict, InvalidInput, NotFound
from learnest.ingest import IngestError, group_files, read_group
from learnest.ingest.flight import Flight as CanonicalFlight

from ..blobs import CHUNK, BlobStore
from ..db import Database, Flight, FlightFile, Result, blob_is_referenced, utcnow
from ..schemas import FlightDetail, FlightOut, FlightPage
from .deps import get_blobs, get_db, require_api_key

log = logging.getLogger("learnest.flights")
router = APIRouter(prefix="/flights", tags=["flights"])

SIDECAR_SUFFIXES = ("_metadata.yaml", "_metadata.yml")   # NanoBench: <stem>_metadata.yaml next to <stem>.csv
CSV_COLUMNS = "t,px,py,pz,ax,ay,az,qx,qy,qz,qw"


# -- staging uploads ----------------------------------------------------------------------------------
@dataclass
class StagedFile:
    original_name: str      # the client's name: metadata only
    path: Path              # our name for it in the private temp folder
    sha256: str
    size: int
    role: str               # "log" or "sidecar"


def original_basename(filename: str | None, index: int) -> str:
    """The client's file name without any directory part or control characters (for display only)."""
    name = re.split(r"[/\\]", filename or "")[-1]
    name = "".join(ch for ch in name if ch.isprintable()).strip()[:255]
    return name if name not in ("", ".", "..") else f"file{index + 1}"


def safe_stem(name: str) -> str:
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(name).stem).strip("._-")[:100]
    return stem or "flight"


def _safe_suffix(name: str) -> str:
    suffix = Path(name).suffix
    return suffix.lower() if re.fullmatch(r"\.[A-Za-z0-9]{1,10}", suffix) else ""


def _sidecar_owner(name: str, log_stems: dict[str, int]) -> int | None:
    for suffix in SIDECAR_SUFFIXES:
        if name.endswith(suffix) and name[:-len(suffix)] in log_stems:
            return log_stems[name[:-len(suffix)]]
    return None


def stage_uploads(uploads: list[UploadFile], directory: Path) -> list[StagedFile]:
    """Copy the uploads to `directory` as upload_<i><.ext> (never the client's name), hashing on the way.
    A NanoBench metadata YAML uploaded with its CSV is staged where the reader looks for it."""
    names = [original_basename(upload.filename, i) for i, upload in enumerate(uploads)]
    log_stems = {Path(name).stem: i for i, name in enumerate(names)
                 if not name.endswith(SIDECAR_SUFFIXES)}
    staged = []
    for i, (upload, name) in enumerate(zip(uploads, names)):
        owner = _sidecar_owner(name, log_stems)
        if owner is not None:
            path, role = directory / f"upload_{owner}_metadata.yaml", "sidecar"
        else:
            path, role = directory / f"upload_{i}{_safe_suffix(name)}", "log"
        sha, size = _copy_and_hash(upload.file, path)
        staged.append(StagedFile(name, path, sha, size, role))
    return staged


def _copy_and_hash(source, target: Path) -> tuple[str, int]:
    digest, size = hashlib.sha256(), 0
    source.seek(0)
    with open(target, "wb") as handle:
        for chunk in iter(lambda: source.read(CHUNK), b""):
            digest.update(chunk)
            size += len(chunk)
            handle.write(chunk)
    return digest.hexdigest(), size


def content_sha256(staged: list[StagedFile]) -> str:
    """The dedupe key: a single file's own sha256, else the sha256 of the sorted sha256s (one per line)."""
    if len(staged) == 1:
        return staged[0].sha256
    return hashlib.sha256("\n".join(sorted(f.sha256 for f in staged)).encode()).hexdigest()


# -- reading ------------------------------------------------------------------------------------------
def read_uploaded_flight(staged: list[StagedFile]) -> CanonicalFlight:
    """The adapters decide the format; every failure is InvalidInput naming the client's file."""
    originals = {str(f.path): f.original_name for f in staged}
    logs = [f.path for f in staged if f.role == "log"]
    try:
        groups = group_files(logs)
        if len(groups) != 1:
            raise InvalidInput(f"one flight per upload: {', '.join(originals.values())} make {len(groups)} flights; "
                          "upload each flight's file(s) separately")
        adapter, files = groups[0]
        flight = read_group(adapter, files)
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
    """Replace our temp paths by the client's names anywhere in a message or metadata."""
    if isinstance(value, str):
        for path, name in originals.items():
            value = value.replace(path, name)
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


# -- storing ------------------------------------------------------------------------------------------
def store_flight(db: Database, blobs: BlobStore, staged: list[StagedFile], flight: CanonicalFlight, sha: str,
                 vehicle: str | None, notes: str | None) -> tuple[Flight, bool]:
    """Blobs first (fsync + rename), then the row; -> (row, created).  A concurrent upload of the same
    content makes our insert fail on the unique sha256: we answer with its row.  Names are unique (the
    evaluation matches a model's training flight by name): a taken name gets the content hash appended."""
    base = flight.meta["name"]
    for name in (base, f"{base}-{sha[:8]}"):
        flight.meta["name"] = name
        with blobs.writing():
            flight_blob = blobs.put_bytes(flight.to_bytes())
            for f in staged:
                if f.path.exists():
                    blobs.put_file(f.path, f.sha256)
            try:
                with db.transaction() as session:
                    row = _flight_row(flight, sha, flight_blob, staged, vehicle, notes)
                    session.add(row)
                return row, True
            except IntegrityError:
                existing = find_by_sha(db, sha)
                if existing is not None:
                    return existing, False
    raise Conflict(f"a flight named {base!r} already exists and so does {base}-{sha[:8]}")


def _flight_row(flight: CanonicalFlight, sha: str, flight_blob: str, staged: list[StagedFile],
                vehicle: str | None, notes: str | None) -> Flight:
    meta = flight.meta
    return Flight(sha256=sha, name=meta["name"], adapter=meta.get("adapter") or "unknown",
                  vehicle=vehicle or _text_or_none(meta.get("vehicle")), notes=notes,
                  duration_s=flight.duration_s, rate_hz=flight.rate_hz, samples=len(flight.t),
                  quality_ok=bool(flight.quality["ok"]), quality=flight.quality,
                  clock_offset_s=meta.get("clock_offset_s"), flight_blob=flight_blob, meta=meta,
                  created_at=utcnow(),
                  files=[FlightFile(position=i, original_name=f.original_name, sha256=f.sha256, size_bytes=f.size,
                                    role=f.role) for i, f in enumerate(staged)])


def _text_or_none(value) -> str | None:
    return None if value is None else str(value)[:200]


def find_by_sha(db: Database, sha: str) -> Flight | None:
    with db.transaction() as session:
        return session.scalar(select(Flight).where(Flight.sha256 == sha))


def get_flight(db: Database, flight_id: int) -> Flight:
    with db.transaction() as session:
        row = session.get(Flight, flight_id)
    if row is None:
        raise NotFound(f"flight {flight_id} not found")
    return row


def flight_out(row: Flight, detail: bool = False) -> dict:
    out = {"id": row.id, "name": row.name, "adapter": row.adapter, "vehicle": row.vehicle, "notes": row.notes,
           "duration_s": row.duration_s, "rate_hz": row.rate_hz, "samples": row.samples,
           "quality": row.quality, "clock_offset_s": row.clock_offset_s, "sha256": row.sha256,
           "sources": [{"name": f.original_name, "sha256": f.sha256, "size_bytes": f.size_bytes, "role": f.role}
                       for f in row.files],
           "created_at": row.created_at}
    if detail:
        out["meta"] = row.meta
    return out


# -- routes -------------------------------------------------------------------------------------------
@router.post("", status_code=201, response_model=FlightOut, dependencies=[Depends(require_api_key)],
             responses={200: {"model": FlightOut, "description": "identical content was already uploaded"},
                        413: {"description": "upload larger than LEARNEST_MAX_UPLOAD_MB"},
                        422: {"description": "a file cannot be read (the message names it)"}})
def upload_flight(response: Response,
                  files: list[UploadFile] = File(..., description="the log file(s) of one flight"),
                  vehicle: str | None = Form(None, max_length=200), notes: str | None = Form(None, max_length=10_000),
                  db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs)):
    with blobs.temp_dir() as directory:
        staged = stage_uploads(files, directory)
        sha = content_sha256(staged)
        row, created = find_by_sha(db, sha), False
        if row is None:
            flight = read_uploaded_flight(staged)
            row, created = store_flight(db, blobs, staged, flight, sha, vehicle, notes)
    response.status_code = 201 if created else 200
    response.headers["Location"] = f"/flights/{row.id}"
    return flight_out(row)


@router.get("", response_model=FlightPage)
def list_flights(vehicle: str | None = None,
                 quality: Literal["ok", "bad"] | None = Query(None, description="only flights that passed / failed "
                                                                               "the quality checks"),
                 since: datetime | None = Query(None, description="uploaded at or after (ISO 8601; UTC if no zone)"),
                 until: datetime | None = Query(None, description="uploaded before (ISO 8601; UTC if no zone)"),
                 limit: int = Query(50, ge=1, le=500), offset: int = Query(0, ge=0),
                 db: Database = Depends(get_db)):
    conditions = []
    if vehicle is not None:
        conditions.append(Flight.vehicle == vehicle)
    if quality is not None:
        conditions.append(Flight.quality_ok == (quality == "ok"))
    if since is not None:
        conditions.append(Flight.created_at >= _naive_utc(since))
    if until is not None:
        conditions.append(Flight.created_at < _naive_utc(until))
    with db.transaction() as session:
        total = session.scalar(select(func.count(Flight.id)).where(*conditions))
        rows = session.scalars(select(Flight).where(*conditions).order_by(Flight.id).limit(limit).offset(offset)).all()
    return {"items": [flight_out(row) for row in rows], "total": total, "limit": limit, "offset": offset}


def _naive_utc(moment: datetime) -> datetime:
    return moment.astimezone(timezone.utc).replace(tzinfo=None) if moment.tzinfo else moment


@router.get("/{flight_id}", response_model=FlightDetail)
def flight_detail(flight_id: int, db: Database = Depends(get_db)):
    return flight_out(get_flight(db, flight_id), detail=True)


@router.get("/{flight_id}/data", response_class=Response,
            responses={200: {"content": {"text/csv": {}}, "description": f"columns {CSV_COLUMNS}"}})
def flight_data(flight_id: int, db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs)):
    """The normalized flight: uniform grid, SI units, world frame z-up, a = a_meas (gravity removed)."""
    row = get_flight(db, flight_id)
    flight = CanonicalFlight.from_bytes(blobs.read_bytes(row.flight_blob))
    table = np.column_stack([flight.t, flight.p, flight.a_meas, flight.quat])
    buffer = io.StringIO()
    np.savetxt(buffer, table, delimiter=",", fmt="%.10g", header=CSV_COLUMNS, comments="")
    return Response(buffer.getvalue(), media_type="text/csv",
                    headers={"Content-Disposition": f'attachment; filename="{row.name}.csv"'})


@router.get("/{flight_id}/raw", response_class=FileResponse,
            responses={200: {"content": {"application/octet-stream": {}, "application/zip": {}}}})
def flight_raw(flight_id: int, db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs)):
    """The original upload: the file itself, or a zip of the files when there were several."""
    row = get_flight(db, flight_id)
    if len(row.files) == 1:
        only = row.files[0]
        return FileResponse(blobs.path(only.sha256), media_type="application/octet-stream",
                            filename=_download_name(only.original_name))
    archive = tempfile.NamedTemporaryFile(suffix=".zip", delete=False)
    with archive, zipfile.ZipFile(archive, "w", zipfile.ZIP_DEFLATED) as bundle:
        used: set[str] = set()
        for f in row.files:
            name = _unique(_download_name(f.original_name), used)
            with blobs.path(f.sha256).open("rb") as source, bundle.open(name, "w") as target:
                shutil.copyfileobj(source, target, CHUNK)
    return FileResponse(archive.name, media_type="application/zip", filename=f"{row.name}.zip",
                        background=BackgroundTask(Path(archive.name).unlink, missing_ok=True))


def _download_name(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "file"


def _unique(name: str, used: set[str]) -> str:
    candidate, k = name, 1
    while candidate in used:
        k += 1
        candidate = f"{Path(name).stem}-{k}{Path(name).suffix}"
    used.add(candidate)
    return candidate


@router.delete("/{flight_id}", status_code=204, dependencies=[Depends(require_api_key)])
def delete_flight(flight_id: int, db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs)):
    """Removes the flight, its cached results and its blobs (unless another row still uses them).
    Model versions trained on it keep its id and sha256 (lineage)."""
    with db.transaction() as session:
        row = session.get(Flight, flight_id)
        if row is None:
            raise NotFound(f"flight {flight_id} not found")
        candidates = [row.flight_blob] + [f.sha256 for f in row.files]
        session.execute(delete(Result).where(Result.flight_sha256 == row.sha256))
        session.delete(row)
    blobs.collect(candidates, lambda sha: blob_is_referenced(db, sha))
    return Response(status_code=204)
