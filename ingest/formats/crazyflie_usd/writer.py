"""`encode`/`write`: a valid uSD log from event streams (for the simulator and the tests)."""
from __future__ import annotations

import zlib
from pathlib import Path

import numpy as np

from learnest.errors import InvalidInput

from .layout import FIXED_FREQUENCY, FIXED_FREQUENCY_ID, MAGIC, TIMESTAMP_FORMATS, VALUE_TYPES, EventType


def encode(events: dict, version: int = 2) -> bytes:
    """The bytes of a valid uSD log.

    events maps event name -> {"t": times in s, "vars": {"group.name": (struct code, values)}, "id": optional}.
    The id defaults to 0xFFFF for "fixedFrequency" and to the event's position in `events` otherwise.
    Timestamps are rounded to the version's tick (v2 us, v1 ms), integer values to the nearest integer;
    records of all events are merged by time (ties keep the order of `events`).
    """
    if version not in TIMESTAMP_FORMATS:
        raise InvalidInput(f"uSD log version must be 1 or 2, not {version}")
    event_types, tables = [], []
    for position, (name, spec) in enumerate(events.items()):
        variables = spec.get("vars", {})
        event_id = spec.get("id", FIXED_FREQUENCY_ID if name == FIXED_FREQUENCY else position)
        event_type = EventType(event_id, name, tuple(variables), tuple(code for code, _ in variables.values()))
        event_types.append(event_type)
        tables.append(_record_table(event_type, spec["t"], [values for _, values in variables.values()], version))
    if len({event_type.id for event_type in event_types}) != len(event_types):
        raise InvalidInput("two events share an id")
    content = _encode_header(event_types, version) + _merge_by_time(tables)
    return content + zlib.crc32(content).to_bytes(4, "little")


def write(path, events: dict, version: int = 2, corrupt_crc: bool = False) -> None:
    """Write `encode(events, version)` to path; corrupt_crc flips the trailer's bits (for tests)."""
    data = encode(events, version)
    if corrupt_crc:
        data = data[:-4] + bytes(byte ^ 0xFF for byte in data[-4:])
    Path(path).write_bytes(data)


def _encode_header(event_types: list[EventType], version: int) -> bytes:
    parts = [bytes([MAGIC]), version.to_bytes(2, "little"), len(event_types).to_bytes(2, "little")]
    for event_type in event_types:
        parts += [event_type.id.to_bytes(2, "little"), _c_string(event_type.name),
                  len(event_type.var_names).to_bytes(2, "little")]
        for name, code in zip(event_type.var_names, event_type.var_types):
            if code not in VALUE_TYPES:
                raise InvalidInput(f"variable {name!r}: type {code!r} is not one of {''.join(VALUE_TYPES)}")
            parts.append(_c_string(f"{name}({code})"))
    return b"".join(parts)


def _c_string(text: str) -> bytes:
    raw = text.encode("ascii")
    if b"\0" in raw or not raw:
        raise InvalidInput(f"name {text!r} must be non-empty ASCII without NUL")
    return raw + b"\0"


def _record_table(event_type: EventType, t, columns, version: int) -> np.ndarray:
    dtype = event_type.record_dtype(version)
    t = np.asarray(t, dtype=float).reshape(-1)
    table = np.zeros(len(t), dtype)
    table["id"] = event_type.id
    table["time"] = _fitted(t / TIMESTAMP_FORMATS[version][1], dtype["time"], f"{event_type.name} timestamps")
    for i, (name, values) in enumerate(zip(event_type.var_names, columns)):
        values = np.asarray(values)
        if values.shape != t.shape:
            raise InvalidInput(f"{event_type.name}/{name}: {values.shape} values for {t.shape} timestamps")
        table[f"v{i}"] = _fitted(values, dtype[f"v{i}"], f"{event_type.name}/{name}")
    return table


def _fitted(values: np.ndarray, dtype: np.dtype, what: str) -> np.ndarray:
    """Values rounded to an integer dtype, refusing the silent wrap-around a cast would do."""
    if dtype.kind not in "ui":
        return values
    rounded = np.rint(np.asarray(values, dtype=float))
    limits = np.iinfo(dtype)
    if rounded.size and (not np.all(np.isfinite(rounded)) or rounded.min() < limits.min or rounded.max() > limits.max):
        raise InvalidInput(f"{what}: values do not fit {dtype} [{limits.min}, {limits.max}]")
    return rounded.astype(dtype)


def _merge_by_time(tables: list[np.ndarray]) -> bytes:
    rows = [(table.tobytes(), table.dtype.itemsize) for table in tables]
    times = np.concatenate([table["time"].astype(np.float64) for table in tables])
    which = np.concatenate([np.full(len(table), k) for k, table in enumerate(tables)])
    index = np.concatenate([np.arange(len(table)) for table in tables])
    order = np.argsort(times, kind="stable")
    return b"".join(rows[k][0][j * rows[k][1]:(j + 1) * rows[k][1]] for k, j in zip(which[order], index[order]))
