"""/flights: upload (ingest + dedupe; several flights at once: /flights/batch), list, detail, normalized data
as CSV, raw files, delete.

The routes shape answers; what an upload is and how it is stored is service.operations.uploads (the upload form and the
CLI use it too), and reading rows is service.operations.catalog.
"""
from __future__ import annotations

import re
import shutil
import tempfile
import zipfile
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import BinaryIO, Literal

import numpy as np
from fastapi import APIRouter, Depends, File, Form, Query, Request, Response, UploadFile
from fastapi.encoders import jsonable_encoder
from fastapi.responses import FileResponse, JSONResponse, StreamingResponse
from starlette.background import BackgroundTask
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile as StarletteUpload

from learnest.errors import InvalidInput
from learnest.ingest.flight import stored_array_blocks

from ...jobs.services import Services
from ...operations import catalog, deletion
from ...operations.uploads import MAX_BATCH_FILES, FileOutcome, add_flight, add_flights, recut_flight
from ...storage.blobs import CHUNK, BlobStore, temp_prefix
from ...storage.database import Database
from ...storage.tables import FlightRecord
from ..deps import Offset, RowId, actor, creator, get_blobs, get_db, get_services
from ..schemas import Dependents, FlightDetail, FlightOut, FlightPage
from ..server import FORM_FIELD_BYTES

router = APIRouter(prefix="/flights", tags=["flights"])

CSV_COLUMNS = "t,px,py,pz,ax,ay,az,qx,qy,qz,qw"


# -- JSON shapes ---------------------------------------------------------------------------------------
def flight_out(row: FlightRecord, detail: bool = False) -> dict:
    """A flight row as the API's JSON (FlightOut; with `detail`, FlightDetail: plus the ingest metadata)."""
    out = {"id": row.id, "name": row.name, "adapter": row.adapter, "vehicle": row.vehicle, "notes": row.notes,
           "duration_s": row.duration_s, "rate_hz": row.rate_hz, "samples": row.samples,
           "quality": row.quality, "clock_offset_s": row.clock_offset_s, "sha256": row.sha256,
           "sources": [{"name": f.original_name, "sha256": f.sha256, "size_bytes": f.size_bytes, "role": f.role}
                       for f in row.files],
           "created_at": row.created_at, "created_by": row.created_by}
    if detail:
        out["meta"] = row.meta
    return out


# -- routes -------------------------------------------------------------------------------------------
@router.post("", status_code=201, response_model=FlightOut,
             responses={200: {"model": FlightOut, "description": "identical content was already uploaded"},
                        413: {"description": "upload larger than LEARNEST_MAX_UPLOAD_MB"},
                        422: {"description": "a file cannot be read, or its decode passed the time limit "
                                              "(the message names it)"},
                        503: {"description": "too many uploads being decoded: retry later"}})
def upload_flight(request: Request, response: Response,
                  files: list[UploadFile] = File(..., description="the log file(s) of one flight"),
                  vehicle: str | None = Form(None, max_length=200), notes: str | None = Form(None, max_length=10_000),
                  pose_topic: str | None = Form(None, max_length=300, description=(
                      "MCAP/ROS bag: the pose topic, e.g. /poses:cf1 (one body of a NamedPoseArray or /tf topic); "
                      "default: the only motion-capture topic")),
                  imu_topic: str | None = Form(None, max_length=300, description=(
                      "MCAP/ROS bag: the acceleration topic (sensor_msgs/Imu or LogDataGeneric), e.g. /cf1/imu")),
                  cut: str | None = Form(None, max_length=60, description=(
                      "the stretch to keep: auto (default: the flying part, take-off and landing cut), none (the "
                      "whole recording) or START:STOP in seconds from the recording's start, e.g. 2.5:14")),
                  services: Services = Depends(get_services)):
    """One flight's file(s) (see service.operations.uploads): 201 and the new flight, or 200 and the flight that
    already holds identical content (and the same topic choice).  The file(s) are decoded in a worker process
    within LEARNEST_DECODE_TIMEOUT_S (service.jobs.decoding); the answer comes when the flight is stored."""
    row, created = add_flight(services.db, services.blobs, files, vehicle, notes, pose_topic=pose_topic,
                              imu_topic=imu_topic, cut=cut, decode=services.decoder.decode,
                              created_by=creator(request))
    response.status_code = 201 if created else 200
    response.headers["Location"] = f"/flights/{row.id}"
    return flight_out(row)


BATCH_FIELDS = {"vehicle": 200, "notes": 10_000, "pose_topic": 300, "imu_topic": 300, "cut": 60}  # max lengths
BATCH_BODY = {"content": {"multipart/form-data": {"schema": {
    "type": "object", "required": ["files"],
    "properties": {"files": {"type": "array", "items": {"type": "string", "format": "binary"},
                             "description": f"the log files of one or more flights, with their sidecars "
                                            f"(at most {MAX_BATCH_FILES})"},
                   **{name: {"type": "string", "maxLength": limit} for name, limit in BATCH_FIELDS.items()}}}}}}


def file_outcome(outcome: FileOutcome) -> dict:
    """One file of a batch upload as the API's JSON."""
    row = outcome.flight
    return {"file": outcome.file, "status": outcome.status, "flight_id": row.id if row else None,
            "flight_name": row.name if row else None, "message": outcome.message,
            "http_status": outcome.http_status}


@router.post("/batch", status_code=201,
             openapi_extra={"requestBody": BATCH_BODY},
             responses={200: {"description": "every flight read was stored already"},
                        201: {"description": "at least one new flight stored; `files` says per file what was stored"},
                        400: {"description": f"more than {MAX_BATCH_FILES} files, or a malformed body"},
                        413: {"description": "upload larger than LEARNEST_MAX_UPLOAD_MB"},
                        422: {"description": "no file could be stored (each named in `files` and `errors`), or a "
                                             "malformed cut, topic or field"}})
async def upload_flights(request: Request):
    """Several flights at once (several files, or a folder's worth): grouped into flights as `learnest ingest`
    groups them (a Vicon export with its cfclient log, a CSV with its *_metadata.yaml, ...), each stored as
    POST /flights stores one (service.operations.uploads.add_flights).  The answer says per file ``status`` "stored"
    (a new flight), "existing" (identical content stored before) or "refused" with its ``message``; one bad
    file does not stop the others.  The token is checked before the body is read (api.request_guard), the
    body's size and time are limited as every upload's, and the multipart parser stops past MAX_BATCH_FILES
    files."""
    services: Services = request.app.state.services
    async with request.form(max_files=MAX_BATCH_FILES, max_fields=len(BATCH_FIELDS) + 10,
                            max_part_size=FORM_FIELD_BYTES) as form:
        files = [f for f in form.getlist("files") if isinstance(f, StarletteUpload) and f.filename]
        fields = {}
        for name, limit in BATCH_FIELDS.items():
            value = form.get(name)
            text = value.strip() if isinstance(value, str) else ""
            if len(text) > limit:
                raise InvalidInput(f"{name}: at most {limit} characters")
            fields[name] = text or None
        outcomes = await run_in_threadpool(add_flights, services.db, services.blobs, files, fields["vehicle"],
                                           fields["notes"], pose_topic=fields["pose_topic"],
                                           imu_topic=fields["imu_topic"], cut=fields["cut"],
                                           decode=services.decoder.decode, created_by=creator(request))
    return JSONResponse(jsonable_encoder(batch_answer(outcomes)), status_code=batch_status(outcomes))


def batch_answer(outcomes: list[FileOutcome]) -> dict:
    """The batch upload's JSON: ``files`` (one per file, in the order posted), ``flights`` (each flight stored
    or found once) and ``errors`` ([{file, message}] of the refused files, as `learnest ingest --json`)."""
    flights, seen = [], set()
    for outcome in outcomes:
        if outcome.flight is not None and outcome.flight.id not in seen:
            seen.add(outcome.flight.id)
            flights.append({**flight_out(outcome.flight), "status": outcome.status})
    return {"files": [file_outcome(o) for o in outcomes], "flights": flights,
            "errors": [{"file": o.file, "message": o.message} for o in outcomes if o.status == "refused"]}


def batch_status(outcomes: list[FileOutcome]) -> int:
    """201 when a new flight was stored, 200 when every flight read was stored already, 422 when none was read."""
    statuses = {o.status for o in outcomes}
    return 201 if "stored" in statuses else 200 if "existing" in statuses else 422


@router.post("/{flight_id}/cut", status_code=201, response_model=FlightOut,
             responses={200: {"model": FlightOut, "description": "that stretch of these files is stored already"},
                        422: {"description": "a malformed cut, or one that leaves no flight"}})
def cut_flight(flight_id: RowId, request: Request, response: Response,
               cut: str = Form(..., max_length=60, description=(
                   "the stretch to keep: auto (the flying part), none (the whole recording) or START:STOP in "
                   "seconds from the recording's start, e.g. 2.5:14")),
               services: Services = Depends(get_services)):
    """Read a stored flight's raw file(s) again with another cut (service.operations.uploads.recut_flight): 201 and the
    flight holding that stretch, or 200 when it is stored already."""
    row = catalog.get_flight(services.db, flight_id)
    new, created = recut_flight(services.db, services.blobs, row, cut, decode=services.decoder.decode,
                                created_by=creator(request))
    response.status_code = 201 if created else 200
    response.headers["Location"] = f"/flights/{new.id}"
    return flight_out(new)


@router.get("", response_model=FlightPage)
def list_flights(vehicle: str | None = None,
                 quality: Literal["ok", "bad"] | None = Query(None, description="only flights that passed / failed "
                                                                               "the quality checks"),
                 since: datetime | None = Query(None, description="uploaded at or after (ISO 8601; UTC if no zone)"),
                 until: datetime | None = Query(None, description="uploaded before (ISO 8601; UTC if no zone)"),
                 q: str | None = Query(None, max_length=200, description="only flights whose name contains this "
                                                                         "(case-insensitive)"),
                 limit: int = Query(50, ge=1, le=500), offset: Offset = 0,
                 db: Database = Depends(get_db)):
    """One page of flights by id, filtered by name, vehicle, quality and upload time."""
    conditions = catalog.name_contains(q)
    if vehicle is not None:
        conditions.append(FlightRecord.vehicle == vehicle)
    if quality is not None:
        conditions.append(FlightRecord.quality_ok == (quality == "ok"))
    if since is not None:
        conditions.append(FlightRecord.created_at >= _naive_utc(since))
    if until is not None:
        conditions.append(FlightRecord.created_at < _naive_utc(until))
    total, rows = catalog.list_flights(db, *conditions, limit=limit, offset=offset)
    return {"items": [flight_out(row) for row in rows], "total": total, "limit": limit, "offset": offset}


def _naive_utc(moment: datetime) -> datetime:
    """The moment in UTC without a zone (how the rows store it); 422 for one outside years 1-9999 in UTC."""
    try:
        return moment.astimezone(UTC).replace(tzinfo=None) if moment.tzinfo else moment
    except OverflowError:  # e.g. 0001-01-01T00:00:00+14:00 is in year 0 in UTC
        raise InvalidInput(f"date {moment.isoformat()} is out of range in UTC (years 1-9999)") from None


@router.get("/{flight_id}", response_model=FlightDetail)
def flight_detail(flight_id: RowId, db: Database = Depends(get_db)):
    """One flight with its ingest metadata; 404 when there is none."""
    return flight_out(catalog.get_flight(db, flight_id), detail=True)


@router.get("/{flight_id}/data", response_class=StreamingResponse,
            responses={200: {"content": {"text/csv": {}}, "description": f"columns {CSV_COLUMNS}"}})
def flight_data(flight_id: RowId, db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs)):
    """The normalized flight: uniform grid, SI units, world frame z-up, a = a_meas (gravity removed).  Streamed
    in blocks of CSV_BLOCK_ROWS rows read from the stored flight as they are sent (`csv_blocks`)."""
    row = catalog.get_flight(db, flight_id)
    source = blobs.path(row.flight_blob).open("rb")   # opened here: a missing blob fails before the 200
    return StreamingResponse(csv_blocks(source), media_type="text/csv",
                             headers={"Content-Disposition": f'attachment; filename="{row.name}.csv"'})


CSV_BLOCK_ROWS = 2048   # rows formatted at once: ~0.3 MB of text, whatever the flight's length


def csv_blocks(source: BinaryIO, rows: int = CSV_BLOCK_ROWS) -> Iterator[bytes]:
    """A stored flight (an open `Flight.to_bytes` file, closed at the end) as CSV, ``rows`` rows per block:
    the bytes ``np.savetxt`` gives for the whole table, with the memory of one block (20 requests for a
    180k-sample flight each built its whole CSV, and the server grew by 1.5 GB)."""
    line = ",".join(["%.10g"] * len(CSV_COLUMNS.split(","))) + "\n"   # np.savetxt's row format, without its
    # file wrapper (a reference cycle per call: each block's text stayed until the garbage collector ran)
    with source:
        yield (CSV_COLUMNS + "\n").encode()
        for t, p, a, quat in stored_array_blocks(source, ("t", "p", "a_meas", "quat"), rows):
            yield "".join([line % tuple(row) for row in np.column_stack([t, p, a, quat]).tolist()]).encode()


@router.get("/{flight_id}/raw", response_class=FileResponse,
            responses={200: {"content": {"application/octet-stream": {}, "application/zip": {}}}})
def flight_raw(flight_id: RowId, db: Database = Depends(get_db), blobs: BlobStore = Depends(get_blobs)):
    """The original upload: the file itself, or a zip of the files when there were several."""
    row = catalog.get_flight(db, flight_id)
    if len(row.files) == 1:
        only = row.files[0]
        return FileResponse(blobs.path(only.sha256), media_type="application/octet-stream",
                            filename=_download_name(only.original_name))
    # in the blob folder's temp area, named after this process (see the evaluation export)
    archive = tempfile.NamedTemporaryFile(dir=blobs.tmp, prefix=temp_prefix(), suffix=".zip", delete=False)
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


@router.get("/{flight_id}/dependents", response_model=Dependents)
def flight_dependents(flight_id: RowId, db: Database = Depends(get_db)):
    """What a DELETE of this flight deletes with it (its cached results and their stored estimates) and what
    keeps a record of it (versions trained on it, evaluations and diagnoses that used it)."""
    return deletion.flight_dependents(db, flight_id)


@router.delete("/{flight_id}", status_code=204)
def delete_flight(flight_id: RowId, request: Request, db: Database = Depends(get_db),
                  blobs: BlobStore = Depends(get_blobs)):
    """Removes the flight, its cached results (with their stored estimates) and its blobs (unless another row
    still uses them), never refused: model versions trained on it keep its id and sha256, evaluations and
    diagnoses their reports (lineage; see GET .../dependents)."""
    deletion.delete_flight(db, blobs, flight_id, actor=actor(request))
    return Response(status_code=204)
