"""Write state estimates (`FlightEstimates`) as CSV, Parquet or MCAP.

- CSV and Parquet hold the tidy table of `estimates_table` (one row per flight, method and sample; unit-suffixed
  column names).  Parquet also carries each column's unit as field metadata (``b"unit"``) and the flights as
  schema metadata (``b"learnest"``, JSON).
- MCAP holds JSON messages with jsonschema schemas that Foxglove knows (``foxglove.Vector3``,
  ``foxglove.PoseInFrame``), so Foxglove or PlotJuggler show estimate vs reference next to the raw log.  For
  each source S (``reference``, ``measurement`` and every method) the topics are ``/learnest/S/position``,
  ``/learnest/S/velocity``, ``/learnest/S/acceleration`` (foxglove.Vector3 in m, m/s, m/s², world frame) and
  ``/learnest/S/pose`` (foxglove.PoseInFrame: that position with the mocap attitude, which the estimators
  take as given); the measurement has no velocity.  A file of several flights puts each under
  ``/learnest/<flight>/S/...`` so they do not overlay.  log_time is the sample's time on the log's own
  clock in ns (`FlightEstimates.log_times_ns`); each channel's metadata names its unit, flight and source.
"""
from __future__ import annotations

import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import IO

import numpy as np

from learnest.errors import InvalidInput
from learnest.ingest.formats.mcap.schemas import POSE_IN_FRAME, POSE_IN_FRAME_JSON_SCHEMA

from .estimates import FlightEstimates, estimates_table, table_units

FORMATS = {"csv": ".csv", "parquet": ".parquet", "mcap": ".mcap"}
MEDIA_TYPES = {"csv": "text/csv", "parquet": "application/vnd.apache.parquet", "mcap": "application/octet-stream"}
SUFFIXES = {".csv": "csv", ".parquet": "parquet", ".pq": "parquet", ".mcap": "mcap"}

VECTOR3 = "foxglove.Vector3"
VECTOR3_JSON_SCHEMA = {
    "title": VECTOR3, "description": "A vector in 3D space that represents a direction only", "type": "object",
    "properties": {axis: {"type": "number", "description": f"{axis} coordinate length"} for axis in "xyz"},
}
# (topic, columns of the 9-state vector, unit); the measurement y = [p, a] has no velocity
QUANTITIES = (("position", slice(0, 3), "m"), ("velocity", slice(3, 6), "m/s"), ("acceleration", slice(6, 9), "m/s^2"))


def check_format(fmt: str) -> str:
    """``fmt`` if it is one of `FORMATS`; InvalidInput naming the allowed ones otherwise."""
    if fmt not in FORMATS:
        raise InvalidInput(f"unknown export format {fmt!r}; choose one of {', '.join(FORMATS)}")
    return fmt


def format_of(path: str | Path) -> str:
    """The export format a file name asks for by its suffix (.csv, .parquet or .pq, .mcap)."""
    fmt = SUFFIXES.get(Path(path).suffix.lower())
    if fmt is None:
        raise InvalidInput(f"{path}: cannot tell the export format from the suffix {Path(path).suffix or '(none)'!r}; "
                           f"use one of {', '.join(SUFFIXES)}")
    return fmt


def write_estimates(flights: Sequence[FlightEstimates], target: str | Path | IO[bytes], fmt: str) -> None:
    """Write ``flights`` to ``target`` (a path or a binary file) as ``fmt`` ("csv", "parquet" or "mcap").

    Raises
    ------
    InvalidInput
        If ``fmt`` is unknown or ``flights`` is empty.
    """
    writer = {"csv": write_csv, "parquet": write_parquet, "mcap": write_mcap}[check_format(fmt)]
    if not flights:
        raise InvalidInput("no estimates to export (no flight was scored)")
    writer(flights, target)


def write_csv(flights: Sequence[FlightEstimates], target: str | Path | IO[bytes]) -> None:
    """The tidy table as CSV (a header row of unit-suffixed names; floats written exactly)."""
    estimates_table(flights).to_csv(target, index=False, float_format=None)


def write_parquet(flights: Sequence[FlightEstimates], target: str | Path | IO[bytes]) -> None:
    """The tidy table as Parquet (pyarrow): each field's unit in its metadata, the flights in the schema's."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    frame = estimates_table(flights)
    units = table_units()
    table = pa.Table.from_pandas(frame, preserve_index=False)
    fields = [f.with_metadata({"unit": units[f.name]}) if units.get(f.name) else f for f in table.schema]
    about = {"units": units, "flights": [_flight_info(f) for f in flights]}
    schema = pa.schema(fields, metadata={**(table.schema.metadata or {}), b"learnest": json.dumps(about).encode()})
    pq.write_table(table.cast(schema), target, compression="zstd")


def _flight_info(flight: FlightEstimates) -> dict:
    return {"flight": flight.flight, "flight_id": flight.flight_id, "sha256": flight.sha256,
            "samples": len(flight.t), "methods": flight.methods, "log_start_ns": int(flight.log_start_ns)}


# -- MCAP ------------------------------------------------------------------------------------------------
def topic_root(flight: FlightEstimates, several: bool) -> str:
    """``/learnest``, or ``/learnest/<flight>`` in a file of several flights (name made topic-safe)."""
    return f"/learnest/{re.sub(r'[^A-Za-z0-9_]+', '_', flight.flight).strip('_') or 'flight'}" if several \
        else "/learnest"


def mcap_sources(flight: FlightEstimates) -> dict[str, np.ndarray]:
    """{source: (T, 9) states} of the MCAP topics: the reference, the measurement (velocity NaN), each method."""
    measured = np.full((len(flight.t), 9), np.nan)
    measured[:, 0:3], measured[:, 6:9] = flight.measurement[:, 0:3], flight.measurement[:, 3:6]
    return {"reference": np.asarray(flight.reference, float), "measurement": measured,
            **{m: np.asarray(v, float) for m, v in flight.estimates.items()}}


def write_mcap(flights: Sequence[FlightEstimates], target: str | Path | IO[bytes]) -> None:
    """The estimates as an MCAP of JSON messages with Foxglove schemas (module docstring: topics, times)."""
    from mcap.writer import CompressionType, Writer

    if isinstance(target, (str, Path)):
        with open(target, "wb") as handle:
            write_mcap(flights, handle)
        return
    writer = Writer(target, compression=CompressionType.ZSTD)
    writer.start(profile="", library="learnest")
    vector3 = writer.register_schema(VECTOR3, "jsonschema", json.dumps(VECTOR3_JSON_SCHEMA).encode())
    pose = writer.register_schema(POSE_IN_FRAME, "jsonschema", json.dumps(POSE_IN_FRAME_JSON_SCHEMA).encode())
    several = len(flights) > 1
    for flight in flights:
        root, times = topic_root(flight, several), flight.log_times_ns()
        channels: list[tuple[int, np.ndarray, slice | None]] = []  # (channel id, states (T, 9), columns; None: pose)
        for source, states in mcap_sources(flight).items():
            info = {"flight": flight.flight, "flight_id": str(flight.flight_id or ""), "source": source,
                    "frame_id": "world"}
            for quantity, axes, unit in QUANTITIES:
                if np.isnan(states[:, axes]).all():
                    continue
                channel = writer.register_channel(f"{root}/{source}/{quantity}", "json", vector3,
                                                  metadata={**info, "unit": unit})
                channels.append((channel, states, axes))
            channel = writer.register_channel(f"{root}/{source}/pose", "json", pose, metadata={**info, "unit": "m"})
            channels.append((channel, states, None))
        for i, stamp in enumerate(times.tolist()):
            timestamp = {"sec": stamp // 10**9, "nsec": stamp % 10**9}
            for channel, states, columns in channels:
                if columns is None:
                    x, y, z = states[i, 0:3].tolist()
                    qx, qy, qz, qw = flight.quat[i].tolist()
                    message: dict = {"timestamp": timestamp, "frame_id": "world",
                                     "pose": {"position": {"x": x, "y": y, "z": z},
                                              "orientation": {"x": qx, "y": qy, "z": qz, "w": qw}}}
                else:
                    x, y, z = states[i, columns].tolist()
                    message = {"x": x, "y": y, "z": z}
                writer.add_message(channel, log_time=stamp, publish_time=stamp, data=json.dumps(message).encode())
    writer.add_metadata("learnest", {"content": "state estimates vs Savitzky-Golay reference",
                                     "flights": json.dumps([_flight_info(f) for f in flights])})
    writer.finish()
