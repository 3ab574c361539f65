"""Decoding a uSD log: the header's event types, then every record framed and unpacked into numpy columns.

Damaged files (decode keeps what it can, lists the problem in UsdLog.warnings and emits a UsdLogWarning):
  - CRC mismatch or no trailer (a card cut off by power loss): every complete record is kept.
  - incomplete last record: dropped.
  - unknown event id mid-stream: the bytes after it cannot be framed any more, so decoding stops there and
    keeps the records before it; the warning names the byte offset.
A bad header (empty, bad magic, unknown version, cut off, malformed names) raises IngestError.
"""
from __future__ import annotations

import re
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...flight import IngestError
from .layout import MAGIC, TIMESTAMP_FORMATS, VALUE_TYPES, EventType

_VARIABLE_SPEC = re.compile(r"([^()]+)\((.)\)")


class UsdLogWarning(UserWarning):
    """A damaged but partly readable uSD log (cut off, CRC mismatch, unframeable tail)."""


@dataclass
class UsdLog:
    """A decoded uSD log: the header's event types and every event's records as numpy columns.

    Attributes
    ----------
    path : str
        The file read (or the name given to `decode_bytes`).
    version : int
        Log format version: 1 (uint32 timestamps, ms) or 2 (uint64 timestamps, µs).
    event_types : list of EventType
        As declared in the header, in header order.
    events : dict
        Event name -> {"t": (N,) float64 timestamps in s, variable name: (N,) values in the logged type}.
    crc_ok : bool
        Whether the CRC-32 trailer matched (False when it is missing, e.g. a card cut off by power loss).
    warnings : list of str
        The damage met while decoding (also emitted as UsdLogWarning).
    """
    path: str
    version: int
    event_types: list[EventType]
    events: dict[str, dict[str, np.ndarray]]    # event name -> {"t": seconds (float64), variable: values}
    crc_ok: bool
    warnings: list[str] = field(default_factory=list)


# -- header ------------------------------------------------------------------------------------------------

class _HeaderReader:
    """Cursor over the header bytes: running off the end is an IngestError, never a struct/Index error."""

    def __init__(self, data: bytes, path):
        self.data, self.path, self.pos = data, path, 0

    def uint(self, size: int, what: str) -> int:
        end = self.pos + size
        if end > len(self.data):
            raise IngestError(self.path, f"uSD header cut off while reading the {what} "
                                         f"(byte {self.pos} of {len(self.data)})")
        value = int.from_bytes(self.data[self.pos:end], "little")
        self.pos = end
        return value

    def text(self, what: str) -> str:
        start, end = self.pos, self.data.find(b"\0", self.pos)
        if end < 0:
            raise IngestError(self.path, f"uSD header cut off inside the {what} at byte {start}")
        self.pos = end + 1
        try:
            return self.data[start:end].decode("ascii")
        except UnicodeDecodeError:
            raise IngestError(self.path, f"uSD header: the {what} at byte {start} is not ASCII text "
                                         f"({self.data[start:end][:40]!r})") from None


def parse_header(data: bytes, path) -> tuple[int, list[EventType], int]:
    """(version, event types, offset of the first record); IngestError for anything that is not a uSD header."""
    if not data:
        raise IngestError(path, "empty file, not a uSD log")
    reader = _HeaderReader(data, path)
    magic = reader.uint(1, "magic byte")
    if magic != MAGIC:
        raise IngestError(path, f"not a uSD log: first byte is 0x{magic:02X}, expected 0x{MAGIC:02X}")
    version = reader.uint(2, "version")
    if version not in TIMESTAMP_FORMATS:
        raise IngestError(path, f"unsupported uSD log version {version} (known: 1, 2)")
    count = reader.uint(2, "number of event types")
    if count == 0:
        raise IngestError(path, "uSD header declares no event types")
    event_types = [_parse_event_type(reader) for _ in range(count)]
    for attribute in ("id", "name"):
        values = [getattr(event_type, attribute) for event_type in event_types]
        if len(set(values)) != len(values):
            raise IngestError(path, f"uSD header: two event types share an {attribute}")
    return version, event_types, reader.pos


def _parse_event_type(reader: _HeaderReader) -> EventType:
    event_id = reader.uint(2, "event id")
    name = reader.text("event name")
    if not name:
        raise IngestError(reader.path, f"uSD header: event 0x{event_id:04X} has an empty name")
    names, types = [], []
    for _ in range(reader.uint(2, f"variable count of event {name!r}")):
        spec = reader.text(f"variable name of event {name!r}")
        match = _VARIABLE_SPEC.fullmatch(spec)
        if not match or match[2] not in VALUE_TYPES or match[1] == "t":
            raise IngestError(reader.path, f"uSD header: event {name!r} has a malformed variable {spec!r} "
                                           f"(expected 'group.name(T)', T one of {''.join(VALUE_TYPES)})")
        names.append(match[1])
        types.append(match[2])
    if len(set(names)) != len(names):
        raise IngestError(reader.path, f"uSD header: event {name!r} lists a variable twice")
    return EventType(event_id, name, tuple(names), tuple(types))


# -- records -----------------------------------------------------------------------------------------------

def _frame_records(data: bytes, start: int, end: int, sizes: dict[int, int]):
    """Walk the record boundaries (records of different events interleave, so each id tells the next size).

    Returns (start offsets per event id, offset where framing stopped, the unknown id which ended it or None).
    """
    offsets: dict[int, list[int]] = {event_id: [] for event_id in sizes}
    pos = start
    while pos + 2 <= end:
        event_id = data[pos] | (data[pos + 1] << 8)
        size = sizes.get(event_id)
        if size is None:
            return offsets, pos, event_id
        if pos + size > end:
            break
        offsets[event_id].append(pos)
        pos += size
    return offsets, pos, None


def _unpack(data: bytes, offsets: list[int], event_type: EventType, version: int) -> dict[str, np.ndarray]:
    dtype = event_type.record_dtype(version)
    size, count = dtype.itemsize, len(offsets)
    if count and offsets[-1] - offsets[0] == (count - 1) * size:     # back to back: view the bytes directly
        records = np.frombuffer(data, dtype, count=count, offset=offsets[0])
    else:                                                             # interleaved: gather the rows first
        rows = np.frombuffer(data, np.uint8)[np.asarray(offsets, np.int64)[:, None] + np.arange(size)]
        records = rows.view(dtype).reshape(count)
    columns = {"t": records["time"].astype(np.float64) * TIMESTAMP_FORMATS[version][1]}
    for i, name in enumerate(event_type.var_names):
        column = records[f"v{i}"]
        columns[name] = column.astype(column.dtype.newbyteorder("="))
    return columns


def decode_bytes(data: bytes, path="<bytes>") -> UsdLog:
    """Decode a uSD log held in memory; `path` only names it in messages."""
    data = bytes(data)
    version, event_types, body_start = parse_header(data, path)
    crc_ok = (len(data) >= body_start + 4
              and zlib.crc32(data[:-4]) == int.from_bytes(data[-4:], "little"))
    body_end = len(data) - 4 if crc_ok else len(data)   # without a valid trailer the file may just stop
    sizes = {event_type.id: event_type.record_dtype(version).itemsize for event_type in event_types}
    offsets, stop, unknown_id = _frame_records(data, body_start, body_end, sizes)
    kept = sum(len(found) for found in offsets.values())

    problems = []
    if not crc_ok:
        problems.append(f"CRC-32 trailer missing or wrong: the file was probably cut off (power loss) or is "
                        f"damaged; kept {kept} complete records")
    # Records that end exactly where a trailer belongs: the last 4 bytes are a wrong CRC, not a record.
    damaged_trailer_only = not crc_ok and stop == len(data) - 4
    if unknown_id is not None and not damaged_trailer_only:
        problems.append(f"unknown event id 0x{unknown_id:04X} at byte offset {stop}: decoding stopped there, "
                        f"kept the {kept} records before it")
    elif stop < body_end and not damaged_trailer_only:
        problems.append(f"dropped {body_end - stop} bytes at byte offset {stop}: an incomplete last record "
                        f"(no complete record fits)")
    for problem in problems:
        warnings.warn(f"{path}: {problem}", UsdLogWarning, stacklevel=3)

    events = {event_type.name: _unpack(data, offsets[event_type.id], event_type, version)
              for event_type in event_types}
    return UsdLog(str(path), version, event_types, events, crc_ok, problems)


def decode(path) -> UsdLog:
    """Decode a uSD log file: every event's records as numpy columns, timestamps in seconds."""
    try:
        data = Path(path).read_bytes()
    except OSError as err:
        raise IngestError(path, f"cannot read the file ({err.strerror or err})") from None
    return decode_bytes(data, path)
