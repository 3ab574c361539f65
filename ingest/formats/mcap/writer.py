"""Writers of MCAP recordings of a flight (for the simulator and the tests): ROS 2 bags (cdr messages,
ros2msg schemas) and JSON-encoded MCAPs (jsonschema schemas, the way Foxglove tools write them)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Schema
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_ros2.writer import Writer as Ros2McapWriter

from learnest.errors import InvalidInput

from ...frames import GRAVITY
from .schemas import (
    ACCELERATION,
    ACCELERATION_JSON_SCHEMA,
    FRAME_TRANSFORM,
    FRAME_TRANSFORM_JSON_SCHEMA,
    IMU,
    LOG_DATA_GENERIC,
    LOG_DATA_GENERIC_DEFINITION,
    POSE_IN_FRAME,
    POSE_IN_FRAME_JSON_SCHEMA,
    POSE_STAMPED,
    TRANSFORM_STAMPED,
    VECTOR3_JSON_SCHEMA,
    ros2msg_definition,
)

DEFAULT_START_NS = 1_700_000_000 * 10**9     # writers: an epoch time, like a real bag
DEFAULT_CHUNK_SIZE = 1 << 20                 # the mcap library's default

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
        self.chunk_size, self.compression, self.enable_crcs = chunk_size, COMPRESSION[compression], enable_crcs
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
        """Buffer a pose stream as geometry_msgs/PoseStamped or TransformStamped messages.

        Parameters
        ----------
        topic : str
            Channel topic.
        t : (N,) array
            Sample times, s from `start_ns` (the header stamps).
        p : (N, 3) array
            Positions, m.
        quat_xyzw : (N, 4) array
            Orientations, scalar last.
        message_type : {"PoseStamped", "TransformStamped"}
            Message type to write.
        frame_id, child_frame_id : str
            Header frame; child_frame_id is written only by TransformStamped.
        stamp_headers : bool
            False writes zero header stamps.
        log_t : (N,) array, optional
            Receive times, s from `start_ns`, used as log_time; default `t`.

        Raises
        ------
        ValueError
            Unknown `message_type`.
        """
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
            raise InvalidInput(f"pose message_type must be PoseStamped or TransformStamped, not {message_type!r}")
        self._add(topic, (type_name, ros2msg_definition(type_name)), t, log_t, message)

    def add_imu(self, topic: str, t, acc_body_g, *, gyro_rad_s=None, frame_id: str = "cf1",
                stamp_headers: bool = True, log_t=None):
        """sensor_msgs/Imu with linear_acceleration = acc_body_g · g (m/s²) and angular_velocity = gyro_rad_s
        (N, 3) when given; what is not given (orientation, and the angular velocity without gyro_rad_s) has
        element 0 of its covariance at -1, the ROS convention for "not provided"."""
        acc = np.asarray(acc_body_g, float) * GRAVITY
        gyro = None if gyro_rad_s is None else np.asarray(gyro_rad_s, float)
        not_provided = [-1.0] + [0.0] * 8

        def message(i, stamp_ns):
            rate, rate_cov = ((0.0, 0.0, 0.0), not_provided) if gyro is None else (gyro[i], [0.0] * 9)
            return {"header": self._header(stamp_ns, frame_id, stamp_headers),
                    "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}, "orientation_covariance": not_provided,
                    "angular_velocity": _xyz_dict(rate), "angular_velocity_covariance": rate_cov,
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
        """Write the buffered messages to `path` in log_time order (one ros2msg schema per message type)."""
        with open(self.path, "wb") as handle:
            writer = Ros2McapWriter(handle, chunk_size=self.chunk_size, compression=self.compression,
                                    enable_crcs=self.enable_crcs)
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
            raise InvalidInput(f"pose message_type must be PoseInFrame or FrameTransform, not {message_type!r}")
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
        """Write the buffered messages to `path` in log_time order (one JSON channel, jsonschema, per topic)."""
        with open(self.path, "wb") as handle:
            writer = McapWriter(handle, chunk_size=self.chunk_size, compression=self.compression,
                                enable_crcs=self.enable_crcs)
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


def write_ros2(path, t, p, quat_xyzw, acc_body_g, *, t_acc=None, gyro_rad_s=None, pose_type: str = "PoseStamped",
               accel_type: str = "Imu", pose_topic: str | None = None, accel_topic: str | None = None,
               stamp_headers: bool = True, start_ns: int = DEFAULT_START_NS, chunk_size: int = DEFAULT_CHUNK_SIZE,
               compression: str = "zstd") -> None:
    """A ROS 2 bag of one flight: mocap pose at times t, accelerometer (g, body frame) at t_acc (default t),
    and, with accel_type "Imu", the gyro (rad/s, body frame) at t_acc when gyro_rad_s is given.

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
            bag.add_imu(accel_topic or "/cf1/imu", t_acc, acc_body_g, gyro_rad_s=gyro_rad_s,
                        stamp_headers=stamp_headers)
        elif accel_type == "LogDataGeneric":
            bag.add_log_data(accel_topic or "/cf1/acc", t_acc, acc_body_g, stamp_headers=stamp_headers)
        else:
            raise InvalidInput(f"accel_type must be Imu or LogDataGeneric, not {accel_type!r}")


def write_json(path, t, p, quat_xyzw, acc_body_g, *, t_acc=None, pose_topic: str = "/cf1/mocap_pose",
               accel_topic: str = "/cf1/acceleration", unit: str = "g", start_ns: int = DEFAULT_START_NS,
               chunk_size: int = DEFAULT_CHUNK_SIZE, compression: str = "zstd") -> None:
    """A JSON-encoded MCAP of one flight: foxglove.PoseInFrame at t, learnest.Acceleration at t_acc."""
    t_acc = t if t_acc is None else t_acc
    with JsonMcapWriter(path, start_ns=start_ns, chunk_size=chunk_size, compression=compression) as recording:
        recording.add_pose(pose_topic, t, p, quat_xyzw)
        recording.add_acceleration(accel_topic, t_acc, acc_body_g, unit=unit)
