"""MCAP recordings (ROS 2 bags and JSON-encoded channels) -> canonical Flight; plus writers for the
simulator and the tests.

What is read
  ROS 2 channels (message encoding "cdr", schema encoding "ros2msg", decoded with mcap_ros2):
    pose          geometry_msgs/msg/PoseStamped, geometry_msgs/msg/TransformStamped (vicon_bridge style);
                  position in m, orientation quaternion (x, y, z, w)
    acceleration  sensor_msgs/msg/Imu: linear_acceleration, m/s², body (IMU) frame, specific force (REP 145)
                  crazyflie_interfaces/msg/LogDataGeneric: `values` in the order of the log block's
                  variables, which the message does not carry.  `log_variables` maps a topic to its
                  variable names; without an entry, a topic whose last name part contains "acc" is read
                  as [acc.x, acc.y, acc.z] in g (what the Crazyflie logs).  `timestamp` (ms since boot)
                  is another clock and is not used.
  JSON channels (message encoding "json"):
    pose          foxglove.PoseInFrame  {timestamp: {sec, nsec}, frame_id, pose: {position: {x, y, z},
                                         orientation: {x, y, z, w}}}
                  foxglove.FrameTransform {timestamp, parent_frame_id, child_frame_id,
                                           translation: {x, y, z}, rotation: {x, y, z, w}}
    acceleration  learnest.Acceleration (ACCELERATION_JSON_SCHEMA)
                                        {timestamp: {sec, nsec}, frame_id: "body", x, y, z, unit}
                  body-frame specific force (+1 g along body z at rest); unit "g" or "m/s^2".
                  Also a Vector3-like schema (name ending in "Vector3" or "Vector3Stamped") on a topic
                  whose name contains "acc": {timestamp, x, y, z} with an optional unit.
                  Without a unit the topic's unit is inferred from its median magnitude (≈ 1 -> g,
                  ≈ 9.8 -> m/s²) and the inference is noted in meta["mcap"]["warnings"].

Topic choice: automatic when exactly one pose topic and one acceleration topic carry messages;
otherwise `read(path, pose_topic=..., accel_topic=...)`.  Ambiguity and absence are IngestErrors that
list the candidates / all topics with their schemas.

Time: a topic's header stamps (JSON: "timestamp") when every message has a nonzero one, otherwise the
MCAP log_time of every message of that topic.  If the pose and acceleration topics end up on different
sources, both use log_time (one clock; noted in the warnings).  Times are taken relative to the earliest
selected message (meta["mcap"]["time_origin_ns"]) so that float seconds keep nanosecond resolution.

Damage: the file is read front to back with mcap's non-seeking StreamReader, so a file cut off mid-write
(no summary, half a chunk) still yields every complete chunk before the cut.  A chunk that does not
decompress or fails its CRC check is skipped and reading goes on.  Both are noted in meta["mcap"]["warnings"].  What
cannot become a Flight (not MCAP, empty, nothing usable) is an IngestError naming the file.  Messages are
sorted by time; repeated time stamps, non-finite values and non-unit quaternions are dropped and counted
in meta["mcap"]["streams"].
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import struct
from collections import Counter, defaultdict
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import lz4.frame
import numpy as np
import zstandard
from mcap.exceptions import McapError
from mcap.records import Channel, Chunk, Message, Schema
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2.decoder import DecoderFactory
from mcap_ros2.writer import Writer as Ros2McapWriter

from ...align import build_flight, samples_per_second
from ...flight import Flight, IngestError, existing_file, sha256_file
from ...frames import GRAVITY
from ...limits import QUATERNION_NORM_TOLERANCE

MAGIC = b"\x89MCAP0\r\n"
DEFAULT_START_NS = 1_700_000_000 * 10**9     # writers: an epoch time, like a real bag
DEFAULT_CHUNK_SIZE = 1 << 20                 # the mcap library's default

# A single chunk bigger than this is a damaged size field, not a recording (rosbag2 writes ~1 MiB chunks).
MAX_CHUNK_BYTES = 256 << 20
# Decompression budget of a whole file (a "zip bomb" guard): what its chunks may expand to in total is at
# most MAX_EXPANSION x the file's size (sensor data compresses 2-10x; zeros compress 10^5x) and never more
# than MAX_DECOMPRESSED_BYTES.  Checked against each chunk's declared size BEFORE it is decompressed, so
# a bomb is refused in the time it takes to read its headers, and the parsing work (pure Python, per
# record) stays proportional to what the uploader sent.
MAX_EXPANSION = 100
MAX_DECOMPRESSED_BYTES = 4 << 30
# Payloads of messages whose channel is not declared yet are kept (the declaration may come later, in
# the summary) only up to this many bytes; past it they are counted and dropped.
MAX_PENDING_BYTES = 32 << 20
# A recording whose pose and acceleration overlap for longer than this has corrupt time stamps (a
# Crazyflie battery lasts minutes); the bound also caps the memory of the resampled grid.
MAX_DURATION_S = 3600.0
# Mocap quaternions further than this from unit length are not attitudes (lost object, zeros).
# A flight's median specific force is ≈ 1 g (hover or rest); outside these bounds the unit is wrong.
PLAUSIBLE_MEDIAN_ACC_G = (0.25, 4.0)

# What the mcap reader raises on damaged framing (cut-off reads, bad lengths, bad UTF-8, CRC mismatch,
# corrupt compressed data; lz4 reports corruption as RuntimeError).
FRAMING_ERRORS = (McapError, struct.error, ValueError, EOFError, OverflowError, RuntimeError)


# -- ROS 2 message definitions (concatenated "ros2msg" text, as rosbag2 stores them) ----------------------

ROS2MSG_SEPARATOR = "=" * 80
MSG_TEXT = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Quaternion": "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1",
    "geometry_msgs/msg/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/msg/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/msg/PoseStamped": "std_msgs/Header header\nPose pose",
    "geometry_msgs/msg/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform",
    "sensor_msgs/msg/Imu": ("std_msgs/Header header\n"
                            "geometry_msgs/Quaternion orientation\nfloat64[9] orientation_covariance\n"
                            "geometry_msgs/Vector3 angular_velocity\nfloat64[9] angular_velocity_covariance\n"
                            "geometry_msgs/Vector3 linear_acceleration\n"
                            "float64[9] linear_acceleration_covariance"),
    # crazyswarm2's definition (timestamp: uint32 ms since boot).  Some releases use float32[] values;
    # the reader decodes whatever definition the file carries.
    "crazyflie_interfaces/msg/LogDataGeneric": "std_msgs/Header header\nuint32 timestamp\nfloat64[] values",
}
MSG_DEPENDENCIES = {
    "std_msgs/msg/Header": ["builtin_interfaces/msg/Time"],
    "geometry_msgs/msg/Pose": ["geometry_msgs/msg/Point", "geometry_msgs/msg/Quaternion"],
    "geometry_msgs/msg/Transform": ["geometry_msgs/msg/Vector3", "geometry_msgs/msg/Quaternion"],
    "geometry_msgs/msg/PoseStamped": ["std_msgs/msg/Header", "geometry_msgs/msg/Pose"],
    "geometry_msgs/msg/TransformStamped": ["std_msgs/msg/Header", "geometry_msgs/msg/Transform"],
    "sensor_msgs/msg/Imu": ["std_msgs/msg/Header", "geometry_msgs/msg/Quaternion", "geometry_msgs/msg/Vector3"],
    "crazyflie_interfaces/msg/LogDataGeneric": ["std_msgs/msg/Header"],
}


def _all_dependencies(type_name: str) -> list[str]:
    """Every type `type_name` uses, depth first, each once (rosbag2's order)."""
    found: list[str] = []
    for dependency in MSG_DEPENDENCIES.get(type_name, []):
        for name in [dependency, *_all_dependencies(dependency)]:
            if name not in found:
                found.append(name)
    return found


def ros2msg_definition(type_name: str) -> str:
    """The complete message definition of a type: its own text, then each dependency after a
    separator line and "MSG: <type>"."""
    blocks = [MSG_TEXT[type_name]]
    blocks += [f"{ROS2MSG_SEPARATOR}\nMSG: {name}\n{MSG_TEXT[name]}" for name in _all_dependencies(type_name)]
    return "\n".join(blocks) + "\n"


POSE_STAMPED = "geometry_msgs/msg/PoseStamped"
TRANSFORM_STAMPED = "geometry_msgs/msg/TransformStamped"
IMU = "sensor_msgs/msg/Imu"
LOG_DATA_GENERIC = "crazyflie_interfaces/msg/LogDataGeneric"
LOG_DATA_GENERIC_DEFINITION = ros2msg_definition(LOG_DATA_GENERIC)
ACC_VARIABLES = ("acc.x", "acc.y", "acc.z")

# -- JSON schemas ------------------------------------------------------------------------------------------

POSE_IN_FRAME = "foxglove.PoseInFrame"
FRAME_TRANSFORM = "foxglove.FrameTransform"
ACCELERATION = "learnest.Acceleration"
VECTOR3_SCHEMA_SUFFIXES = ("Vector3", "Vector3Stamped")
UNIT_NAMES = {"g": "g", "m/s^2": "m/s^2", "m/s2": "m/s^2", "m/s²": "m/s^2", "m s^-2": "m/s^2"}

_TIME_SCHEMA = {"type": "object", "properties": {"sec": {"type": "integer", "minimum": 0},
                                                 "nsec": {"type": "integer", "minimum": 0}}}
_XYZ = {"type": "object", "properties": {axis: {"type": "number"} for axis in "xyz"}}
_XYZW = {"type": "object", "properties": {axis: {"type": "number"} for axis in "xyzw"}}
POSE_IN_FRAME_JSON_SCHEMA = {
    "title": POSE_IN_FRAME, "description": "A timestamped pose in a named coordinate frame",
    "type": "object",
    "properties": {"timestamp": _TIME_SCHEMA, "frame_id": {"type": "string"},
                   "pose": {"type": "object", "properties": {"position": _XYZ, "orientation": _XYZW}}},
}
FRAME_TRANSFORM_JSON_SCHEMA = {
    "title": FRAME_TRANSFORM, "description": "The pose of the child frame in the parent frame",
    "type": "object",
    "properties": {"timestamp": _TIME_SCHEMA, "parent_frame_id": {"type": "string"},
                   "child_frame_id": {"type": "string"}, "translation": _XYZ, "rotation": _XYZW},
}
ACCELERATION_JSON_SCHEMA = {
    "title": ACCELERATION,
    "description": "Accelerometer reading: specific force in the body frame (+1 g along body z at rest)",
    "type": "object",
    "properties": {"timestamp": _TIME_SCHEMA, "frame_id": {"type": "string", "default": "body"},
                   **{axis: {"type": "number"} for axis in "xyz"},
                   "unit": {"type": "string", "enum": ["g", "m/s^2"]}},
    "required": ["x", "y", "z"],
}
VECTOR3_JSON_SCHEMA = {"title": "Vector3Stamped", "type": "object",
                       "properties": {"timestamp": _TIME_SCHEMA, **{axis: {"type": "number"} for axis in "xyz"}}}


# -- sniffing ----------------------------------------------------------------------------------------------

def sniff(path) -> bool:
    """True when the file starts with the MCAP magic bytes (content, not extension)."""
    try:
        with open(path, "rb") as handle:
            return handle.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


# -- reading the container ---------------------------------------------------------------------------------

@dataclass
class McapChannel:
    """One channel of the file with the messages kept from it (only for channels that may be read)."""
    id: int
    topic: str
    message_encoding: str
    schema: Schema | None
    count: int = 0
    messages: list[tuple[int, bytes]] = field(default_factory=list)    # (log_time ns, payload)

    @property
    def schema_name(self) -> str:
        return self.schema.name if self.schema is not None else ""

    def describe(self) -> str:
        return f"{self.topic} ({self.schema_name or 'no schema'}, {self.message_encoding}, {self.count} messages)"


@dataclass
class McapContent:
    channels: list[McapChannel]
    warnings: list[str]


class _ClampedFile:
    """File reads clamped to the bytes that are left, so that a damaged length field (up to 2^64)
    reads to the end of the file instead of allocating its claimed size."""

    def __init__(self, handle: io.BufferedReader, size: int):
        self.handle, self.size, self.position = handle, size, 0

    def read(self, length: int = -1) -> bytes:
        left = self.size - self.position
        data = self.handle.read(left if length is None or length < 0 else min(length, left))
        self.position += len(data)
        return data


class DecompressionLimit(ValueError):
    """A file whose chunks would expand past the decompression budget (see MAX_EXPANSION)."""


class _Collector:
    """Schemas, channels and messages as the stream reader meets them.  Schema and channel records
    appear twice (data section and summary): the first copy wins.  ``budget`` is how many bytes the
    chunks may decompress to in total."""

    def __init__(self, budget: int = MAX_DECOMPRESSED_BYTES):
        self.budget, self.decompressed, self.pending_bytes = budget, 0, 0
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.counts: Counter = Counter()
        self.messages: dict[int, list[tuple[int, bytes]]] = defaultdict(list)
        self.damaged_chunks: list[str] = []

    def add(self, record) -> None:
        if isinstance(record, Chunk):
            self._add_chunk(record)
        elif isinstance(record, Schema) and record.id != 0:
            self.schemas.setdefault(record.id, record)
        elif isinstance(record, Channel):
            self.channels.setdefault(record.id, record)
        elif isinstance(record, Message):
            self.counts[record.channel_id] += 1
            if self._may_be_read(record.channel_id, len(record.data)):
                self.messages[record.channel_id].append((record.log_time, record.data))

    def _add_chunk(self, chunk: Chunk) -> None:
        self.decompressed += chunk.uncompressed_size
        if self.decompressed > self.budget:  # not a FRAMING_ERROR: the whole file is refused
            raise DecompressionLimit(
                f"chunks expand to more than {self.budget} bytes (the cap is {MAX_EXPANSION}x the file's size, "
                f"at most {MAX_DECOMPRESSED_BYTES >> 30} GiB): a decompression bomb or not a flight recording")
        try:
            records = _chunk_records(chunk)
        except FRAMING_ERRORS as err:
            self.damaged_chunks.append(f"{type(err).__name__}: {err}"[:200])
            return
        for record in records:
            self.add(record)

    def _may_be_read(self, channel_id: int, size: int) -> bool:
        # Keep payloads of pose/acceleration candidates only (a bag may hold GBs of images).  A channel
        # not declared yet keeps its payloads: its declaration may be in the summary (first chunk damaged).
        channel = self.channels.get(channel_id)
        if channel is None:
            self.pending_bytes += size
            return self.pending_bytes <= MAX_PENDING_BYTES
        schema = self.schemas.get(channel.schema_id)
        return _is_candidate_schema(channel.message_encoding, schema.name if schema else "")


def _chunk_records(chunk: Chunk) -> list:
    """The records inside a chunk, after checking its size and CRC (raises FRAMING_ERRORS)."""
    if chunk.uncompressed_size > MAX_CHUNK_BYTES:
        raise ValueError(f"chunk claims {chunk.uncompressed_size} bytes uncompressed")
    data = _decompress(chunk)
    if len(data) != chunk.uncompressed_size:
        raise ValueError(f"chunk decompresses to {len(data)} bytes, its header says {chunk.uncompressed_size}")
    plain = Chunk(compression="", data=data, message_start_time=chunk.message_start_time,
                  message_end_time=chunk.message_end_time, uncompressed_crc=chunk.uncompressed_crc,
                  uncompressed_size=chunk.uncompressed_size)
    return breakup_chunk(plain, validate_crc=True)


def _decompress(chunk: Chunk) -> bytes:
    """Chunk data decompressed in pieces, never more than one byte past the declared size: a corrupt
    frame header cannot make the decompressor allocate what it claims."""
    if chunk.compression == "":
        return chunk.data
    if chunk.compression == "zstd":
        try:
            stream = zstandard.ZstdDecompressor().stream_reader(chunk.data)
            return _read_at_most(stream.read, chunk.uncompressed_size + 1)
        except zstandard.ZstdError as err:
            raise ValueError(f"zstd: {err}") from None
    if chunk.compression == "lz4":
        decompressor = lz4.frame.LZ4FrameDecompressor()
        return decompressor.decompress(chunk.data, max_length=chunk.uncompressed_size + 1)
    raise ValueError(f"unsupported chunk compression {chunk.compression!r}")


def _read_at_most(read: Callable[[int], bytes], limit: int) -> bytes:
    pieces, total = [], 0
    while total < limit:
        piece = read(min(1 << 20, limit - total))
        if not piece:
            break
        pieces.append(piece)
        total += len(piece)
    return b"".join(pieces)


def _check_file(path: Path) -> None:
    if path.is_dir():
        inside = sorted(p.name for p in path.glob("*.mcap"))
        hint = f" (a rosbag2 folder? pass the .mcap file inside: {', '.join(inside)})" if inside else ""
        raise IngestError(path, f"is a directory, not an MCAP file{hint}")
    existing_file(path, "MCAP recording")
    with open(path, "rb") as handle:
        start = handle.read(len(MAGIC))
    if start != MAGIC:
        if MAGIC.startswith(start):
            raise IngestError(path, f"MCAP file cut off inside its magic bytes ({len(start)} bytes long)")
        raise IngestError(path, f"not an MCAP file: starts with {start!r}, expected the MCAP magic {MAGIC!r}")


def scan(path) -> McapContent:
    """Every schema, channel and (for pose/acceleration candidates) message the file holds, read front to
    back.  Damage ends the reading (cut-off file) or skips one chunk; both become warnings."""
    path = Path(path)
    _check_file(path)
    size = path.stat().st_size
    collector, warnings = _Collector(budget=min(MAX_DECOMPRESSED_BYTES, MAX_EXPANSION * size)), []
    with open(path, "rb") as handle:
        clamped = _ClampedFile(handle, size)
        reader = StreamReader(clamped, emit_chunks=True, record_size_limit=size)
        try:
            for record in reader.records:
                collector.add(record)
        except DecompressionLimit as err:
            raise IngestError(path, str(err)) from None
        except FRAMING_ERRORS as err:
            detail = f"{type(err).__name__}{': ' + str(err) if str(err) else ''}"[:200]
            warnings.append(f"file cut off or damaged at byte {clamped.position} of {size} ({detail}): "
                            f"kept the {sum(collector.counts.values())} complete messages before it")
    if collector.damaged_chunks:
        warnings.append(f"skipped {len(collector.damaged_chunks)} damaged chunk(s), their messages are lost "
                        f"(first: {collector.damaged_chunks[0]})")
    channels = [McapChannel(channel.id, channel.topic, channel.message_encoding,
                            collector.schemas.get(channel.schema_id), collector.counts[channel.id],
                            collector.messages.get(channel.id, []))
                for channel in collector.channels.values()]
    orphans = sum(n for channel_id, n in collector.counts.items() if channel_id not in collector.channels)
    if orphans:
        warnings.append(f"{orphans} message(s) on undeclared channels ignored")
    return McapContent(sorted(channels, key=lambda c: (c.topic, c.id)), warnings)


def topics(path) -> list[tuple[str, str, str, int]]:
    """[(topic, schema name, message encoding, message count)] for every channel, sorted by topic."""
    return [(c.topic, c.schema_name, c.message_encoding, c.count) for c in scan(path).channels]


# -- which channel is what ---------------------------------------------------------------------------------

class _Rejected(Exception):
    """A message that decodes but is not a usable sample; the text is the reason, counted per topic."""


# An extractor turns one decoded message into (stamp ns or None, values, unit or None).
Extractor = Callable[[Any], tuple[int | None, tuple[float, ...], str | None]]


@dataclass(frozen=True)
class Reading:
    role: str             # "pose" (x, y, z, qx, qy, qz, qw) or "accel" (x, y, z with a unit)
    extract: Extractor
    stamp_name: str       # what the message's own time stamp is called, for meta


def _ros_type(schema_name: str) -> str:
    """"pkg/Type" and "pkg/msg/Type" name the same ROS 2 type."""
    parts = schema_name.split("/")
    return f"{parts[0]}/msg/{parts[1]}" if len(parts) == 2 else schema_name


def _is_vector3_schema(schema_name: str) -> bool:
    return schema_name.replace("/", ".").split(".")[-1] in VECTOR3_SCHEMA_SUFFIXES


def _is_candidate_schema(message_encoding: str, schema_name: str) -> bool:
    if message_encoding == "cdr":
        return _ros_type(schema_name) in (POSE_STAMPED, TRANSFORM_STAMPED, IMU, LOG_DATA_GENERIC)
    if message_encoding == "json":
        return schema_name in (POSE_IN_FRAME, FRAME_TRANSFORM, ACCELERATION) or _is_vector3_schema(schema_name)
    return False


def _looks_like_acc_topic(topic: str) -> bool:
    return "acc" in topic.rstrip("/").split("/")[-1].lower()


def _log_data_layout(topic: str, log_variables: dict | None) -> tuple[list[int], int] | None:
    """(indices of acc.x/y/z in `values`, expected number of values), or None when the topic does not
    carry the accelerometer."""
    if log_variables and topic in log_variables:
        names = list(log_variables[topic])
        if not set(ACC_VARIABLES) <= set(names):
            return None
        return [names.index(name) for name in ACC_VARIABLES], len(names)
    return ([0, 1, 2], 3) if _looks_like_acc_topic(topic) else None


def classify(channel: McapChannel, log_variables: dict | None = None) -> Reading | None:
    """How to read a channel as pose or acceleration, or None when it is neither."""
    name = channel.schema_name
    if channel.message_encoding == "cdr" and channel.schema is not None:
        ros_type = _ros_type(name)
        if ros_type == POSE_STAMPED:
            return Reading("pose", _pose_stamped, "header.stamp")
        if ros_type == TRANSFORM_STAMPED:
            return Reading("pose", _transform_stamped, "header.stamp")
        if ros_type == IMU:
            return Reading("accel", _imu, "header.stamp")
        if ros_type == LOG_DATA_GENERIC:
            layout = _log_data_layout(channel.topic, log_variables)
            if layout is not None:
                return Reading("accel", partial(_log_data, indices=layout[0], expected=layout[1]), "header.stamp")
    elif channel.message_encoding == "json":
        if name == POSE_IN_FRAME:
            return Reading("pose", _json_pose_in_frame, "timestamp")
        if name == FRAME_TRANSFORM:
            return Reading("pose", _json_frame_transform, "timestamp")
        if name == ACCELERATION or (_is_vector3_schema(name) and _looks_like_acc_topic(channel.topic)):
            return Reading("accel", _json_acceleration, "timestamp")
    return None


# -- extractors: one decoded message -> (stamp, values, unit) -----------------------------------------------

def _ros_stamp_ns(header) -> int | None:
    stamp_ns = header.stamp.sec * 10**9 + header.stamp.nanosec
    return stamp_ns if stamp_ns > 0 else None


def _pose_stamped(msg):
    position, orientation = msg.pose.position, msg.pose.orientation
    return _ros_stamp_ns(msg.header), (position.x, position.y, position.z, *_xyzw(orientation)), None


def _transform_stamped(msg):
    translation, rotation = msg.transform.translation, msg.transform.rotation
    return _ros_stamp_ns(msg.header), (translation.x, translation.y, translation.z, *_xyzw(rotation)), None


def _xyzw(quaternion) -> tuple[float, float, float, float]:
    return quaternion.x, quaternion.y, quaternion.z, quaternion.w


def _imu(msg):
    acc = msg.linear_acceleration
    return _ros_stamp_ns(msg.header), (acc.x, acc.y, acc.z), "m/s^2"


def _log_data(msg, indices: list[int], expected: int):
    values = msg.values
    if len(values) != expected:
        raise _Rejected(f"{len(values)} values instead of {expected}")
    return _ros_stamp_ns(msg.header), tuple(float(values[i]) for i in indices), "g"


def _json_field(obj, key: str):
    if not isinstance(obj, dict) or key not in obj:
        raise _Rejected(f"no field {key!r}")
    return obj[key]


def _json_number(obj, key: str) -> float:
    value = _json_field(obj, key)
    if value is None:                # some JSON writers turn NaN into null
        return math.nan
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise _Rejected(f"field {key!r} is not a number")
    return float(value)


def _json_stamp_ns(obj) -> int | None:
    stamp = obj.get("timestamp")
    if stamp is None:
        return None
    if not isinstance(stamp, dict):
        raise _Rejected("timestamp is not an object {sec, nsec}")
    sec, nsec = stamp.get("sec", 0), stamp.get("nsec", stamp.get("nanosec", 0))
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (sec, nsec)):
        raise _Rejected("timestamp sec/nsec are not integers")
    stamp_ns = sec * 10**9 + nsec
    return stamp_ns if 0 < stamp_ns < 2**63 else None


def _json_xyz(obj, keys: str = "xyz") -> tuple[float, ...]:
    return tuple(_json_number(obj, key) for key in keys)


def _json_pose_in_frame(obj):
    pose = _json_field(obj, "pose")
    position = _json_xyz(_json_field(pose, "position"))
    orientation = _json_xyz(_json_field(pose, "orientation"), "xyzw")
    return _json_stamp_ns(obj), position + orientation, None


def _json_frame_transform(obj):
    translation = _json_xyz(_json_field(obj, "translation"))
    rotation = _json_xyz(_json_field(obj, "rotation"), "xyzw")
    return _json_stamp_ns(obj), translation + rotation, None


def _json_acceleration(obj):
    xyz = _json_xyz(obj)
    unit = obj.get("unit")
    if unit is not None and unit not in UNIT_NAMES:
        raise _Rejected(f"unknown unit {unit!r} (expected 'g' or 'm/s^2')")
    return _json_stamp_ns(obj), xyz, UNIT_NAMES.get(unit)


# -- decoding the chosen topics ----------------------------------------------------------------------------

@dataclass
class _Decoded:
    channels: list[McapChannel]
    reading: Reading
    log_times: list[int] = field(default_factory=list)
    stamps: list[int | None] = field(default_factory=list)
    values: list[tuple] = field(default_factory=list)
    units: list[str | None] = field(default_factory=list)
    rejected: Counter = field(default_factory=Counter)


def _payload_decoder(path: Path, channel: McapChannel) -> Callable[[bytes], Any]:
    if channel.message_encoding == "json":
        return json.loads
    try:
        with contextlib.redirect_stderr(io.StringIO()):   # the vendored msg parser prints its errors too
            decoder = DecoderFactory().decoder_for(channel.message_encoding, channel.schema)
    except Exception as err:   # third-party parser on schema text from the file: any error means unusable
        raise IngestError(path, f"topic {channel.topic}: cannot parse its {channel.schema_name} message "
                                f"definition ({type(err).__name__}: {err})") from None
    if decoder is None:
        encoding = channel.schema.encoding if channel.schema else "none"
        raise IngestError(path, f"topic {channel.topic}: schema encoding {encoding!r} is not supported "
                                f"(ROS 2 topics need 'ros2msg' definitions)")
    return decoder


def _decode(path: Path, channels: list[McapChannel], reading: Reading) -> _Decoded:
    decoded = _Decoded(channels, reading)
    for channel in channels:
        decode = _payload_decoder(path, channel)
        for log_time, payload in channel.messages:
            try:
                stamp, values, unit = reading.extract(decode(payload))
            except _Rejected as reason:
                decoded.rejected[str(reason)] += 1
                continue
            except Exception as err:   # third-party decoder on bytes from the file: count, never crash
                decoded.rejected[f"undecodable ({type(err).__name__})"] += 1
                continue
            decoded.log_times.append(log_time)
            decoded.stamps.append(stamp)
            decoded.values.append(values)
            decoded.units.append(unit)
    if not decoded.values:
        reasons = "; ".join(f"{n} {why}" for why, n in decoded.rejected.most_common()) or "no messages kept"
        total = sum(len(c.messages) for c in channels)
        raise IngestError(path, f"topic {channels[0].topic}: none of its {total} messages is usable ({reasons})")
    return decoded


def _has_all_stamps(decoded: _Decoded) -> bool:
    return all(stamp is not None for stamp in decoded.stamps)


def _times(decoded: _Decoded, use_stamps: bool) -> tuple[list[int], str]:
    if use_stamps:
        return list(decoded.stamps), decoded.reading.stamp_name
    return list(decoded.log_times), "log_time"


def _to_g(topic: str, values: np.ndarray, units: list[str | None], notes: list[str]) -> np.ndarray:
    """Acceleration rows in g; rows without a unit get the topic's unit inferred from their magnitude."""
    unknown = np.array([unit is None for unit in units])
    scale = np.array([1.0 / GRAVITY if unit == "m/s^2" else 1.0 for unit in units])
    if unknown.any():
        with np.errstate(invalid="ignore", over="ignore"):
            norms = np.linalg.norm(values[unknown], axis=1)
        median = float(np.median(norms[np.isfinite(norms)])) if np.isfinite(norms).any() else 1.0
        in_g = median < PLAUSIBLE_MEDIAN_ACC_G[1]
        scale[unknown] = 1.0 if in_g else 1.0 / GRAVITY
        notes.append(f"{topic}: no unit given, read as {'g' if in_g else 'm/s^2'} (median |acc| = {median:.3g})")
    return values * scale[:, None]


def _clean(t_s: np.ndarray, values: np.ndarray, report: dict, valid_row: np.ndarray | None = None):
    """Time-sorted rows with finite values and distinct time stamps (the first of a repeat is kept)."""
    with np.errstate(invalid="ignore", over="ignore"):
        finite = np.all(np.isfinite(values), axis=1)
    report["non_finite"] = int((~finite).sum())
    keep = finite
    if valid_row is not None:
        report["invalid_quaternion"] = int((finite & ~valid_row).sum())
        keep = finite & valid_row
    t_s, values = t_s[keep], values[keep]
    order = np.argsort(t_s, kind="stable")
    report["out_of_order"] = int(np.sum(np.diff(t_s) < 0))
    t_s, values = t_s[order], values[order]
    repeated = np.r_[False, np.diff(t_s) == 0]
    report["duplicate_time"] = int(repeated.sum())
    report["kept"] = int((~repeated).sum())
    return t_s[~repeated], values[~repeated]


DROP_REASONS = ("non_finite", "invalid_quaternion", "duplicate_time")


def _unit_quaternion(values: np.ndarray) -> np.ndarray:
    with np.errstate(invalid="ignore", over="ignore"):
        return np.abs(np.linalg.norm(values[:, 3:7], axis=1) - 1.0) <= QUATERNION_NORM_TOLERANCE


def _check_acc_magnitude(path: Path, topic: str, acc_g: np.ndarray) -> None:
    median = float(np.median(np.linalg.norm(acc_g, axis=1)))
    low, high = PLAUSIBLE_MEDIAN_ACC_G
    if not low <= median <= high:
        hint = " — looks like m/s² labelled as g" if abs(median - GRAVITY) < 0.5 * GRAVITY else ""
        raise IngestError(path, f"topic {topic}: median |specific force| = {median:.4g} g, a flight has ≈ 1 g"
                                f"{hint} (expected body-frame specific force, gravity included)")


# -- topic choice ------------------------------------------------------------------------------------------

ROLE_WORDS = {"pose": ("motion-capture pose", "pose_topic",
                       f"{POSE_STAMPED}, {TRANSFORM_STAMPED} (cdr); {POSE_IN_FRAME}, {FRAME_TRANSFORM} (json)"),
              "accel": ("acceleration", "accel_topic",
                        f"{IMU}, {LOG_DATA_GENERIC} on an 'acc' topic or mapped in log_variables (cdr); "
                        f"{ACCELERATION}, *Vector3 on an 'acc' topic (json)")}


def _listing(channels: list[McapChannel]) -> str:
    return "; ".join(c.describe() for c in channels) or "none"


def _choose(path: Path, content: McapContent, role: str, requested: str | None,
            readings: dict[int, Reading]) -> list[McapChannel]:
    """The channels (normally one) of the topic that plays `role`."""
    what, argument, supported = ROLE_WORDS[role]
    if requested is not None:
        named = [c for c in content.channels if c.topic == requested]
        if not named:
            raise IngestError(path, f"no topic {requested!r} in this file; topics: {_listing(content.channels)}")
        usable = [c for c in named if c.id in readings and readings[c.id].role == role]
        if not usable:
            hint = (f"; for a LogDataGeneric topic pass log_variables={{{requested!r}: [variable names in log "
                    f"order, including acc.x, acc.y, acc.z]}}"
                    if any(_ros_type(c.schema_name) == LOG_DATA_GENERIC for c in named) else "")
            raise IngestError(path, f"topic {requested} ({named[0].schema_name}) cannot be read as {what} "
                                    f"(supported: {supported}){hint}")
        return usable
    candidates = [c for c in content.channels if c.id in readings and readings[c.id].role == role and c.messages]
    by_topic: dict[str, list[McapChannel]] = defaultdict(list)
    for channel in candidates:
        by_topic[channel.topic].append(channel)
    if len(by_topic) == 1:
        return next(iter(by_topic.values()))
    if not by_topic:
        raise IngestError(path, f"no usable {what} topic (supported: {supported}); topics in the file: "
                                f"{_listing(content.channels)}")
    raise IngestError(path, f"{len(by_topic)} candidate {what} topics: {_listing(candidates)}; choose one with "
                            f"read(path, {argument}=...)")


def _no_usable_topics(path: Path, content: McapContent, readings: dict[int, Reading]) -> IngestError | None:
    if any(c.messages and c.id in readings for c in content.channels):
        return None
    found = _listing(content.channels)
    notes = f" [{'; '.join(content.warnings)}]" if content.warnings else ""
    return IngestError(path, f"no usable topics (need a pose topic: {ROLE_WORDS['pose'][2]}; and an "
                             f"acceleration topic: {ROLE_WORDS['accel'][2]}); topics in the file: {found}{notes}")


# -- public entry ------------------------------------------------------------------------------------------

def _stream(path: Path, decoded: _Decoded, t_ns: list[int], origin_ns: int,
            notes: list[str]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Seconds since origin_ns, cleaned values (pose as-is, acceleration in g), and the topic's report."""
    channel = decoded.channels[0]
    report = {"messages": sum(c.count for c in decoded.channels), "rejected": dict(decoded.rejected)}
    t_s = np.array([(ns - origin_ns) / 1e9 for ns in t_ns], dtype=float)  # exact ints, then one rounding
    values = np.array(decoded.values, dtype=float)
    if decoded.reading.role == "pose":
        t_s, values = _clean(t_s, values, report, valid_row=_unit_quaternion(values))
    else:
        values = _to_g(channel.topic, values, decoded.units, notes)
        t_s, values = _clean(t_s, values, report)
    if len(t_s) < 2:
        dropped = {**report["rejected"], **{k: v for k, v in report.items() if k in DROP_REASONS and v}}
        raise IngestError(path, f"topic {channel.topic}: {len(t_s)} usable message(s) of {report['messages']} "
                                f"(dropped: {dropped or 'none'})")
    return t_s, values, report


def read(path, pose_topic: str | None = None, accel_topic: str | None = None, rate_hz: float = 100.0, *,
         log_variables: dict[str, list[str]] | None = None) -> Flight:
    """An MCAP recording as a Flight (see the module docstring for the supported topics).

    pose_topic / accel_topic choose the topics when the automatic choice is ambiguous.  log_variables
    maps LogDataGeneric topics to the names of their values, e.g. {"/cf1/imu": ["gyro.x", "gyro.y",
    "gyro.z", "acc.x", "acc.y", "acc.z"]}.
    """
    path = Path(path)
    content = scan(path)
    notes = list(content.warnings)
    readings = {c.id: r for c in content.channels if (r := classify(c, log_variables)) is not None}
    if (error := _no_usable_topics(path, content, readings)) is not None:
        raise error
    pose_channels = _choose(path, content, "pose", pose_topic, readings)
    accel_channels = _choose(path, content, "accel", accel_topic, readings)
    pose = _decode(path, pose_channels, readings[pose_channels[0].id])
    accel = _decode(path, accel_channels, readings[accel_channels[0].id])

    # One clock: message stamps only when both topics have them throughout.
    use_stamps = _has_all_stamps(pose) and _has_all_stamps(accel)
    if _has_all_stamps(pose) != _has_all_stamps(accel):
        notes.append("only one of the two topics has time stamps in every message: both use the MCAP log_time")
    (t_pose_ns, pose_source), (t_acc_ns, acc_source) = _times(pose, use_stamps), _times(accel, use_stamps)
    origin_ns = min(min(t_pose_ns), min(t_acc_ns))
    t_pose, mocap, pose_report = _stream(path, pose, t_pose_ns, origin_ns, notes)
    t_acc, acc_g, acc_report = _stream(path, accel, t_acc_ns, origin_ns, notes)
    _check_acc_magnitude(path, accel_channels[0].topic, acc_g)
    overlap = min(t_pose[-1], t_acc[-1]) - max(t_pose[0], t_acc[0])
    if overlap > MAX_DURATION_S:
        raise IngestError(path, f"pose and acceleration overlap for {overlap:.0f} s, more than "
                                f"{MAX_DURATION_S:.0f} s: corrupt time stamps?")

    encodings = {pose_channels[0].message_encoding, accel_channels[0].message_encoding}
    meta = {
        "adapter": {frozenset({"cdr"}): "mcap-ros2", frozenset({"json"}): "mcap-json"}.get(
            frozenset(encodings), "mcap-ros2+json"),
        "sources": [{"path": str(path), "sha256": sha256_file(path)}],
        "original_rates": {"mocap": samples_per_second(t_pose), "acc": samples_per_second(t_acc)},
        "clock_offset_s": None,     # one recorder clock for every topic in a bag
        "mcap": {"pose_topic": pose_channels[0].topic, "accel_topic": accel_channels[0].topic,
                 "pose_type": pose_channels[0].schema_name, "accel_type": accel_channels[0].schema_name,
                 "time_source": {"pose": pose_source, "accel": acc_source}, "time_origin_ns": origin_ns,
                 "streams": {"pose": pose_report, "accel": acc_report}, "warnings": notes},
    }
    return build_flight(path, t_mocap=t_pose, p=mocap[:, :3], quat=mocap[:, 3:7], t_acc=t_acc,
                        acc_body_g=acc_g, rate_hz=rate_hz, meta=meta)


# -- writers (simulator and tests) -------------------------------------------------------------------------

COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


def _stamp_ns(start_ns: int, t: float) -> int:
    return start_ns + int(round(float(t) * 1e9))


def _xyz_dict(v) -> dict:
    return {"x": float(v[0]), "y": float(v[1]), "z": float(v[2])}


def _xyzw_dict(q) -> dict:
    return {"x": float(q[0]), "y": float(q[1]), "z": float(q[2]), "w": float(q[3])}


class _BufferedRecording:
    """What both writers share.  Messages of all streams are buffered and written in log_time order on
    close, the way a recorder interleaves topics (so that a cut-off file loses the end of every topic,
    not a whole topic).  Times `t` are seconds from `start_ns`; log_time is `log_t` (default: t), the
    recorder's receive time."""

    def __init__(self, path, *, start_ns: int = DEFAULT_START_NS, chunk_size: int = DEFAULT_CHUNK_SIZE,
                 compression: str = "zstd", enable_crcs: bool = True):
        self.path, self.start_ns = Path(path), start_ns
        self.options = {"chunk_size": chunk_size, "compression": COMPRESSION[compression],
                        "enable_crcs": enable_crcs}
        self.pending: list[tuple[int, int, str, Any]] = []    # (log_time, insertion order, topic, message)
        self.topic_schemas: dict[str, tuple[str, Any]] = {}   # topic -> (schema name, schema)

    def _add(self, topic: str, schema: tuple[str, Any], t, log_t, make_message) -> None:
        """make_message(i, stamp_ns) builds the i-th message of the stream."""
        self.topic_schemas.setdefault(topic, schema)
        log_t = t if log_t is None else log_t
        for i, (sample_t, receive_t) in enumerate(zip(t, log_t)):
            message = make_message(i, _stamp_ns(self.start_ns, sample_t))
            self.pending.append((_stamp_ns(self.start_ns, receive_t), len(self.pending), topic, message))

    def _in_log_time_order(self):
        return sorted(self.pending, key=lambda item: item[:2])

    def close(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        if exc_info[0] is None:
            self.close()


class Ros2BagWriter(_BufferedRecording):
    """A ROS 2 MCAP bag (cdr messages, ros2msg schemas) with pose, Imu and LogDataGeneric streams.
    Header stamps are the sample times t (zero with stamp_headers=False)."""

    @staticmethod
    def _header(stamp_ns: int, frame_id: str, stamp_headers: bool) -> dict:
        stamp_ns = stamp_ns if stamp_headers else 0
        return {"stamp": {"sec": stamp_ns // 10**9, "nanosec": stamp_ns % 10**9}, "frame_id": frame_id}

    def add_pose(self, topic: str, t, p, quat_xyzw, *, message_type: str = "PoseStamped",
                 frame_id: str = "world", child_frame_id: str = "cf1", stamp_headers: bool = True, log_t=None):
        p, quat = np.asarray(p, float), np.asarray(quat_xyzw, float)
        if message_type == "PoseStamped":
            def message(i, stamp_ns):
                return {"header": self._header(stamp_ns, frame_id, stamp_headers),
                        "pose": {"position": _xyz_dict(p[i]), "orientation": _xyzw_dict(quat[i])}}
            type_name = POSE_STAMPED
        elif message_type == "TransformStamped":
            def message(i, stamp_ns):
                return {"header": self._header(stamp_ns, frame_id, stamp_headers), "child_frame_id": child_frame_id,
                        "transform": {"translation": _xyz_dict(p[i]), "rotation": _xyzw_dict(quat[i])}}
            type_name = TRANSFORM_STAMPED
        else:
            raise ValueError(f"pose message_type must be PoseStamped or TransformStamped, not {message_type!r}")
        self._add(topic, (type_name, ros2msg_definition(type_name)), t, log_t, message)

    def add_imu(self, topic: str, t, acc_body_g, *, frame_id: str = "cf1", stamp_headers: bool = True, log_t=None):
        """sensor_msgs/Imu with linear_acceleration = acc_body_g · g (m/s²); no orientation (covariance
        -1 by the ROS convention), zero angular velocity."""
        acc = np.asarray(acc_body_g, float) * GRAVITY
        no_orientation = [-1.0] + [0.0] * 8

        def message(i, stamp_ns):
            return {"header": self._header(stamp_ns, frame_id, stamp_headers),
                    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}, "orientation_covariance": no_orientation,
                    "angular_velocity": _xyz_dict((0.0, 0.0, 0.0)), "angular_velocity_covariance": [0.0] * 9,
                    "linear_acceleration": _xyz_dict(acc[i]), "linear_acceleration_covariance": [0.0] * 9}
        self._add(topic, (IMU, ros2msg_definition(IMU)), t, log_t, message)

    def add_log_data(self, topic: str, t, values, *, definition: str = LOG_DATA_GENERIC_DEFINITION,
                     frame_id: str = "cf1", stamp_headers: bool = True, log_t=None, boot_offset_s: float = 12.0):
        """crazyflie_interfaces/LogDataGeneric rows (values in log-block order); `timestamp` is the
        Crazyflie's ms since boot, which happened boot_offset_s before t = 0."""
        values = np.asarray(values, float)

        def message(i, stamp_ns):
            return {"header": self._header(stamp_ns, frame_id, stamp_headers),
                    "timestamp": int(round((t[i] + boot_offset_s) * 1000)), "values": [float(v) for v in values[i]]}
        self._add(topic, (LOG_DATA_GENERIC, definition), t, log_t, message)

    def close(self) -> None:
        with open(self.path, "wb") as handle:
            writer = Ros2McapWriter(handle, **self.options)
            registered: dict[tuple[str, str], Schema] = {}
            for log_time, _, topic, message in self._in_log_time_order():
                type_and_definition = self.topic_schemas[topic]
                if type_and_definition not in registered:
                    registered[type_and_definition] = writer.register_msgdef(*type_and_definition)
                writer.write_message(topic, registered[type_and_definition], message, log_time=log_time,
                                     publish_time=log_time)
            writer.finish()


class JsonMcapWriter(_BufferedRecording):
    """An MCAP file with JSON-encoded channels and jsonschema schemas, the way Foxglove tools write them."""

    @staticmethod
    def _timestamp(stamp_ns: int) -> dict:
        return {"sec": stamp_ns // 10**9, "nsec": stamp_ns % 10**9}

    def add_pose(self, topic: str, t, p, quat_xyzw, *, message_type: str = "PoseInFrame", frame_id: str = "world",
                 child_frame_id: str = "cf1", log_t=None):
        """foxglove.PoseInFrame or foxglove.FrameTransform messages."""
        p, quat = np.asarray(p, float), np.asarray(quat_xyzw, float)
        if message_type == "PoseInFrame":
            def message(i, stamp_ns):
                return {"timestamp": self._timestamp(stamp_ns), "frame_id": frame_id,
                        "pose": {"position": _xyz_dict(p[i]), "orientation": _xyzw_dict(quat[i])}}
            schema = (POSE_IN_FRAME, POSE_IN_FRAME_JSON_SCHEMA)
        elif message_type == "FrameTransform":
            def message(i, stamp_ns):
                return {"timestamp": self._timestamp(stamp_ns), "parent_frame_id": frame_id,
                        "child_frame_id": child_frame_id, "translation": _xyz_dict(p[i]),
                        "rotation": _xyzw_dict(quat[i])}
            schema = (FRAME_TRANSFORM, FRAME_TRANSFORM_JSON_SCHEMA)
        else:
            raise ValueError(f"pose message_type must be PoseInFrame or FrameTransform, not {message_type!r}")
        self._add(topic, schema, t, log_t, message)

    def add_acceleration(self, topic: str, t, acc_body_g, *, unit: str | None = "g", schema_name: str = ACCELERATION,
                         log_t=None):
        """Body-frame specific force as learnest.Acceleration in `unit` ("g" or "m/s^2"), or, with a
        Vector3-like schema_name, as {timestamp, x, y, z} (plus the unit if one is given).  unit=None writes
        the numbers as given, without a unit field."""
        acc = np.asarray(acc_body_g, float) * (GRAVITY if unit == "m/s^2" else 1.0)
        vector3_like = schema_name != ACCELERATION

        def message(i, stamp_ns):
            body = {"timestamp": self._timestamp(stamp_ns)}
            if not vector3_like:
                body["frame_id"] = "body"
            body.update(_xyz_dict(acc[i]))
            if unit is not None:
                body["unit"] = unit
            return body
        schema = VECTOR3_JSON_SCHEMA if vector3_like else ACCELERATION_JSON_SCHEMA
        self._add(topic, (schema_name, schema), t, log_t, message)

    def close(self) -> None:
        with open(self.path, "wb") as handle:
            writer = McapWriter(handle, **self.options)
            writer.start(profile="", library="learnest")
            channel_ids: dict[str, int] = {}
            for log_time, _, topic, message in self._in_log_time_order():
                if topic not in channel_ids:
                    name, schema = self.topic_schemas[topic]
                    schema_id = writer.register_schema(name, "jsonschema", json.dumps(schema).encode())
                    channel_ids[topic] = writer.register_channel(topic, "json", schema_id)
                writer.add_message(channel_ids[topic], log_time=log_time, publish_time=log_time,
                                   data=json.dumps(message).encode())
            writer.finish()


def write_ros2(path, t, p, quat_xyzw, acc_body_g, *, t_acc=None, pose_type: str = "PoseStamped",
               accel_type: str = "Imu", pose_topic: str | None = None, accel_topic: str | None = None,
               stamp_headers: bool = True, start_ns: int = DEFAULT_START_NS, chunk_size: int = DEFAULT_CHUNK_SIZE,
               compression: str = "zstd") -> None:
    """A ROS 2 bag of one flight: mocap pose at times t, accelerometer (g, body frame) at t_acc (default t).

    pose_type "PoseStamped" (default topic /mocap/cf1/pose) or "TransformStamped" (vicon_bridge's
    /vicon/cf1/cf1); accel_type "Imu" (m/s², /cf1/imu) or "LogDataGeneric" ([acc.x, acc.y, acc.z] in g,
    /cf1/acc).
    """
    t_acc = t if t_acc is None else t_acc
    with Ros2BagWriter(path, start_ns=start_ns, chunk_size=chunk_size, compression=compression) as bag:
        default_pose_topic = "/mocap/cf1/pose" if pose_type == "PoseStamped" else "/vicon/cf1/cf1"
        bag.add_pose(pose_topic or default_pose_topic, t, p, quat_xyzw, message_type=pose_type,
                     stamp_headers=stamp_headers)
        if accel_type == "Imu":
            bag.add_imu(accel_topic or "/cf1/imu", t_acc, acc_body_g, stamp_headers=stamp_headers)
        elif accel_type == "LogDataGeneric":
            bag.add_log_data(accel_topic or "/cf1/acc", t_acc, acc_body_g, stamp_headers=stamp_headers)
        else:
            raise ValueError(f"accel_type must be Imu or LogDataGeneric, not {accel_type!r}")


def write_json(path, t, p, quat_xyzw, acc_body_g, *, t_acc=None, pose_topic: str = "/cf1/mocap_pose",
               accel_topic: str = "/cf1/acceleration", unit: str = "g", start_ns: int = DEFAULT_START_NS,
               chunk_size: int = DEFAULT_CHUNK_SIZE, compression: str = "zstd") -> None:
    """A JSON-encoded MCAP of one flight: foxglove.PoseInFrame at t, learnest.Acceleration at t_acc."""
    t_acc = t if t_acc is None else t_acc
    with JsonMcapWriter(path, start_ns=start_ns, chunk_size=chunk_size, compression=compression) as recording:
        recording.add_pose(pose_topic, t, p, quat_xyzw)
        recording.add_acceleration(accel_topic, t_acc, acc_body_g, unit=unit)
