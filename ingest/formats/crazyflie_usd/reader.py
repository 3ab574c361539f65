"""Crazyflie uSD-card binary logs (firmware usddeck, versions 1 and 2) -> Flight; plus a writer for tests.

Format (little-endian, no padding; ../shared/data/README.md, "The uSD binary format"):
  header   uint8 0xBC, uint16 version, uint16 number of event types; per event type: uint16 id
           (0xFFFF = "fixedFrequency"), name NUL, uint16 nvars, nvars x "group.name(T)" NUL (T a struct code)
  records  uint16 event id, timestamp (v2 uint64 us, v1 uint32 ms), values packed '<' + types
  trailer  uint32 zlib CRC-32 of every byte before it

Damaged files (decode keeps what it can, lists the problem in UsdLog.warnings and emits a UsdLogWarning):
  - CRC mismatch or no trailer (a card cut off by power loss): every complete record is kept.
  - incomplete last record: dropped.
  - unknown event id mid-stream: the bytes after it cannot be framed any more, so decoding stops there and
    keeps the records before it; the warning names the byte offset.
A bad header (empty, bad magic, unknown version, cut off, malformed names) raises IngestError.

`read` picks the streams a Flight needs (see its docstring) and hands them to `ingest.align.build_flight`.
"""
from __future__ import annotations

import re
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ... import units
from ...align import build_flight, resample_quaternions, samples_per_second
from ...flight import Flight, IngestError, sha256_file
from ...limits import QUATERNION_NORM_TOLERANCE

MAGIC = 0xBC
FIXED_FREQUENCY = "fixedFrequency"
FIXED_FREQUENCY_ID = 0xFFFF
TIMESTAMP_FORMATS = {1: ("<u4", 1e-3), 2: ("<u8", 1e-6)}   # version -> (record dtype, seconds per tick)
VALUE_TYPES = {"B": "u1", "b": "i1", "H": "<u2", "h": "<i2", "I": "<u4", "i": "<i4", "f": "<f4", "e": "<f2"}
SNIFF_BYTES = 1 << 20          # headers are a few kB; a MiB is plenty
_VARIABLE_SPEC = re.compile(r"([^()]+)\((.)\)")

ACC = ("acc.x", "acc.y", "acc.z")                                                   # g, body frame
POSE = ("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw")
ONBOARD_RPY = ("ctrlLee.rpyx", "ctrlLee.rpyy", "ctrlLee.rpyz")                      # rad, onboard estimate
# Optional Flight channels: (channel, variables, converter to the channel's unit, ingest.units). The first
# source present wins.  uSD-card and cfclient logs share the firmware's variable names, so this one table
# serves both adapters.
OPTIONAL_SOURCES = (
    ("p_onboard", ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z"), units.identity),
    ("p_onboard", ("stateEstimateZ.x", "stateEstimateZ.y", "stateEstimateZ.z"), units.millimetres),  # int16 mm
    ("v_onboard", ("stateEstimate.vx", "stateEstimate.vy", "stateEstimate.vz"), units.identity),
    ("v_onboard", ("stateEstimateZ.vx", "stateEstimateZ.vy", "stateEstimateZ.vz"), units.millimetres),
    ("gyro", ("gyro.x", "gyro.y", "gyro.z"), units.degrees_per_second),
    ("setpoint", ("ctrltarget.x", "ctrltarget.y", "ctrltarget.z"), units.identity),
    ("setpoint", ("ctrltargetZ.x", "ctrltargetZ.y", "ctrltargetZ.z"), units.millimetres),
    ("motors", ("motor.m1", "motor.m2", "motor.m3", "motor.m4"), units.pwm_16bit),
    ("motors", ("pwm.m1_pwm", "pwm.m2_pwm", "pwm.m3_pwm", "pwm.m4_pwm"), units.pwm_16bit),
    ("vbat", ("pm.vbat",), units.identity),
    ("vbat", ("pm.vbatMV",), units.millivolts),
    ("rotor_speed", ("rpm.m1", "rpm.m2", "rpm.m3", "rpm.m4"), units.rpm),
    ("thrust_cmd", ("controller.cmd_thrust",), units.identity),
    ("thrust_si", ("ctrlLee.thrustSI",), units.identity),
)
EDGE_GAP_S = 0.5               # a pause this long in the accelerometer stream splits the recording ...
EDGE_FRAGMENT_S = 1.0          # ... and a piece shorter than this before the first/after the last split is dropped
MAX_DURATION_S = 3600.0        # longer means corrupt timestamps (a Crazyflie battery lasts minutes)


class UsdLogWarning(UserWarning):
    """A damaged but partly readable uSD log (cut off, CRC mismatch, unframeable tail)."""


@dataclass(frozen=True)
class EventType:
    id: int
    name: str
    var_names: tuple[str, ...]
    var_types: tuple[str, ...]      # struct codes, one per variable

    def record_dtype(self, version: int) -> np.dtype:
        """One record as a packed numpy dtype; positional field names cannot clash with variable names."""
        fields = [("id", "<u2"), ("time", TIMESTAMP_FORMATS[version][0])]
        fields += [(f"v{i}", VALUE_TYPES[code]) for i, code in enumerate(self.var_types)]
        return np.dtype(fields)


@dataclass
class UsdLog:
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


def _parse_header(data: bytes, path) -> tuple[int, list[EventType], int]:
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

    Returns (start offsets per event id, offset where framing stopped, the unknown id that stopped it or None).
    """
    offsets = {event_id: [] for event_id in sizes}
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
    version, event_types, body_start = _parse_header(data, path)
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


def sniff(path) -> bool:
    """True when the file's content starts with a parsable uSD header (magic 0xBC, version 1 or 2)."""
    try:
        with open(path, "rb") as handle:
            _parse_header(handle.read(SNIFF_BYTES), path)
    except (OSError, IngestError):
        return False
    return True


# -- adapter -----------------------------------------------------------------------------------------------

@dataclass
class _Stream:
    """Some variables of one event stream as float columns."""
    event: str
    t: np.ndarray           # (N,) s
    values: np.ndarray      # (N, k)

    def select(self, mask) -> _Stream:
        return _Stream(self.event, self.t[mask], self.values[mask])

    def within(self, window: tuple[float, float]) -> _Stream:
        return self.select((self.t >= window[0]) & (self.t <= window[1]))


def _find_stream(log: UsdLog, names, prefer_own_event=False) -> _Stream | None:
    """The variables from the first event stream that has them all (for locSrv, a dedicated event stream
    carries the true mocap timestamps, so it beats the sample-and-hold copy in the fixed stream)."""
    candidates = [event for event, columns in log.events.items() if all(name in columns for name in names)]
    if not candidates:
        return None
    candidates.sort(key=lambda event: (len(log.events[event]["t"]) == 0,
                                       prefer_own_event and event == FIXED_FREQUENCY))
    columns = log.events[candidates[0]]
    values = np.column_stack([columns[name].astype(np.float64) for name in names])
    return _usable(_Stream(candidates[0], columns["t"], values))


def _require_stream(log: UsdLog, names, what: str, prefer_own_event=False) -> _Stream:
    stream = _find_stream(log, names, prefer_own_event)
    if stream is None:
        logged = set().union(*(columns.keys() for columns in log.events.values()))
        missing = [name for name in names if name not in logged]
        why = f"missing {', '.join(missing)}" if missing else "they are split across event streams"
        raise IngestError(log.path, f"no {what} in this uSD log: needs {', '.join(names)} "
                                    f"in one event stream ({why})")
    return stream


def _usable(stream: _Stream) -> _Stream:
    """Rows with finite values and a timestamp later than every earlier one (interpolation needs both)."""
    finite = np.all(np.isfinite(stream.values), axis=1)
    later = stream.t > np.maximum.accumulate(np.r_[-np.inf, stream.t[:-1]])
    return stream.select(finite & later)


def _main_window(t: np.ndarray, notes: list[str]) -> tuple[float, float]:
    """Time span of the recording without short pieces split off by a long pause at its start or end.

    The real logs begin with a few records, then ~1.5 s of nothing (the card starting up) while the vehicle
    keeps flying; interpolating across that pause would invent data.  Pauses inside stay (build_flight
    counts them in meta["gaps"]).
    """
    if len(t) < 2:
        return -np.inf, np.inf
    breaks = np.flatnonzero(np.diff(t) > EDGE_GAP_S)
    starts, stops = np.r_[0, breaks + 1], np.r_[breaks, len(t) - 1]
    first, last = 0, len(starts) - 1
    while first < last and t[stops[first]] - t[starts[first]] < EDGE_FRAGMENT_S:
        first += 1
    while last > first and t[stops[last]] - t[starts[last]] < EDGE_FRAGMENT_S:
        last -= 1
    if first > 0:
        notes.append(f"skipped the first {starts[first]} accelerometer records: they precede a "
                     f"{t[starts[first]] - t[stops[first - 1]]:.2f} s pause in the recording")
    if last < len(starts) - 1:
        notes.append(f"skipped the last {len(t) - 1 - stops[last]} accelerometer records: they follow a "
                     f"{t[starts[last + 1]] - t[stops[last]]:.2f} s pause in the recording")
    return float(t[starts[first]]), float(t[stops[last]])


def _distinct_frames(pose: _Stream) -> _Stream:
    """The fixed stream repeats the last mocap pose until the next arrives; keep each frame's first sample
    so that resampling interpolates between true frames instead of following a staircase."""
    if len(pose.t) == 0:
        return pose
    return pose.select(np.r_[True, np.any(np.diff(pose.values, axis=0) != 0, axis=1)])


def _after_first_frame(pose: _Stream) -> _Stream:
    """locSrv reads all zero until the first mocap frame arrives; those zeros are no pose."""
    received = np.flatnonzero(np.any(pose.values != 0, axis=1))
    return pose.select(slice(received[0] if received.size else len(pose.t), None))


def rpy_to_quat(rpy) -> np.ndarray:
    """(N, 3) roll, pitch, yaw in rad (Z-Y-X, the firmware's quat2rpy) -> (N, 4) scalar-last quaternions."""
    return Rotation.from_euler("ZYX", np.asarray(rpy, dtype=float).reshape(-1, 3)[:, ::-1]).as_quat()


def _attitude(log: UsdLog, pose: _Stream, window, notes: list[str]) -> tuple[_Stream, np.ndarray, str]:
    """(pose frames kept, their quaternions, where the attitude came from).

    Position-only mocap (Crazyswarm2 sending extpos, as in the real logs) leaves locSrv's quaternion at
    zero; then the onboard attitude estimate (ctrlLee.rpy*) is interpolated to the mocap frames.
    """
    unit = np.abs(np.linalg.norm(pose.values[:, 3:], axis=1) - 1.0) < QUATERNION_NORM_TOLERANCE
    if unit.any():
        if not unit.all():
            notes.append(f"dropped {int((~unit).sum())} mocap frames whose locSrv quaternion is not unit length")
        kept = pose.select(unit)
        return kept, kept.values[:, 3:], "mocap (locSrv quaternion)"
    onboard = _find_stream(log, ONBOARD_RPY)
    onboard = onboard.within(window) if onboard is not None else None
    if onboard is None or len(onboard.t) < 2:
        raise IngestError(log.path, "locSrv quaternion is zero or invalid in every frame (position-only "
                                    "mocap?) and there is no onboard attitude (ctrlLee.rpyx/y/z) to use instead")
    notes.append("locSrv has no attitude (quaternion all zero: position-only mocap); attitude taken from "
                 "the onboard estimate ctrlLee.rpyx/y/z, interpolated to the mocap frames")
    quat = resample_quaternions(onboard.t, rpy_to_quat(onboard.values), pose.t)
    return pose, quat, "onboard estimate (ctrlLee.rpy), locSrv quaternion is zero"


def _optional_channels(log: UsdLog, window) -> dict:
    channels = {}
    for channel, names, to_si in OPTIONAL_SOURCES:
        stream = None if channel in channels else _find_stream(log, names)
        if stream is not None:
            stream = stream.within(window)
            values = to_si(stream.values)
            values = values.reshape(len(stream.t), -1)
            finite = np.all(np.isfinite(values), axis=1)
            if finite.sum() >= 2:
                channels[channel] = (stream.t[finite], values[finite])
    return channels


def read(path, rate_hz: float = 100.0) -> Flight:
    """A uSD log as a Flight.

    Accelerometer from acc.x/y/z (g, body frame).  Mocap pose from locSrv.* (its own event stream if there
    is one, otherwise the fixed-frequency stream with repeated samples removed).  Attitude from the locSrv
    quaternion, or from the onboard estimate when the quaternion is all zero (position-only mocap; noted in
    meta["usd"]["warnings"] and meta["attitude_source"]).  Optional channels: p_onboard, v_onboard (from
    stateEstimateZ.*, mm -> m), gyro (deg/s -> rad/s), setpoint (ctrltargetZ.*, mm -> m), motors, vbat.
    """
    log = decode(path)
    notes = list(log.warnings)
    acc = _require_stream(log, ACC, "accelerometer")
    pose = _require_stream(log, POSE, "motion-capture pose", prefer_own_event=True)
    window = _main_window(acc.t, notes)
    if window[1] - window[0] > MAX_DURATION_S:
        raise IngestError(path, f"timestamps span {window[1] - window[0]:.0f} s, more than {MAX_DURATION_S:.0f} s: "
                                f"corrupt timestamps?")
    acc, pose = acc.within(window), pose.within(window)
    pose = _after_first_frame(pose)
    if pose.event == FIXED_FREQUENCY:
        pose = _distinct_frames(pose)
    if len(pose.t) < 2:
        raise IngestError(path, f"fewer than 2 mocap frames (locSrv) in this uSD log ({len(pose.t)})")
    pose, quat, attitude_source = _attitude(log, pose, window, notes)

    meta = {
        "adapter": "usd",
        "sources": [{"path": str(path), "sha256": sha256_file(path)}],
        "original_rates": {"acc": samples_per_second(acc.t), "mocap": samples_per_second(pose.t)},
        "clock_offset_s": None,
        "attitude_source": attitude_source,
        "usd": {"version": log.version, "crc_ok": log.crc_ok, "warnings": notes,
                "records": {event: int(len(columns["t"])) for event, columns in log.events.items()}},
    }
    return build_flight(path, t_mocap=pose.t, p=pose.values[:, :3], quat=quat, t_acc=acc.t,
                        acc_body_g=acc.values, channels=_optional_channels(log, window), rate_hz=rate_hz,
                        meta=meta)


# -- writer (simulator and tests) --------------------------------------------------------------------------

def encode(events: dict, version: int = 2) -> bytes:
    """The bytes of a valid uSD log.

    events maps event name -> {"t": times in s, "vars": {"group.name": (struct code, values)}, "id": optional}.
    The id defaults to 0xFFFF for "fixedFrequency" and to the event's position in `events` otherwise.
    Timestamps are rounded to the version's tick (v2 us, v1 ms), integer values to the nearest integer;
    records of all events are merged by time (ties keep the order of `events`).
    """
    if version not in TIMESTAMP_FORMATS:
        raise ValueError(f"uSD log version must be 1 or 2, not {version}")
    event_types, tables = [], []
    for position, (name, spec) in enumerate(events.items()):
        variables = spec.get("vars", {})
        event_id = spec.get("id", FIXED_FREQUENCY_ID if name == FIXED_FREQUENCY else position)
        event_type = EventType(event_id, name, tuple(variables), tuple(code for code, _ in variables.values()))
        event_types.append(event_type)
        tables.append(_record_table(event_type, spec["t"], [values for _, values in variables.values()], version))
    if len({event_type.id for event_type in event_types}) != len(event_types):
        raise ValueError("two events share an id")
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
                raise ValueError(f"variable {name!r}: type {code!r} is not one of {''.join(VALUE_TYPES)}")
            parts.append(_c_string(f"{name}({code})"))
    return b"".join(parts)


def _c_string(text: str) -> bytes:
    raw = text.encode("ascii")
    if b"\0" in raw or not raw:
        raise ValueError(f"name {text!r} must be non-empty ASCII without NUL")
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
            raise ValueError(f"{event_type.name}/{name}: {values.shape} values for {t.shape} timestamps")
        table[f"v{i}"] = _fitted(values, dtype[f"v{i}"], f"{event_type.name}/{name}")
    return table


def _fitted(values: np.ndarray, dtype: np.dtype, what: str) -> np.ndarray:
    """Values rounded to an integer dtype, refusing the silent wrap-around a cast would do."""
    if dtype.kind not in "ui":
        return values
    rounded = np.rint(np.asarray(values, dtype=float))
    limits = np.iinfo(dtype)
    if rounded.size and (not np.all(np.isfinite(rounded)) or rounded.min() < limits.min or rounded.max() > limits.max):
        raise ValueError(f"{what}: values do not fit {dtype} [{limits.min}, {limits.max}]")
    return rounded.astype(dtype)


def _merge_by_time(tables: list[np.ndarray]) -> bytes:
    rows = [(table.tobytes(), table.dtype.itemsize) for table in tables]
    times = np.concatenate([table["time"].astype(np.float64) for table in tables])
    which = np.concatenate([np.full(len(table), k) for k, table in enumerate(tables)])
    index = np.concatenate([np.arange(len(table)) for table in tables])
    order = np.argsort(times, kind="stable")
    return b"".join(rows[k][0][j * rows[k][1]:(j + 1) * rows[k][1]] for k, j in zip(which[order], index[order]))
