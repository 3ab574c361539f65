"""Extractors: one decoded message -> (stamp ns or None, values, unit or None).

Pose extractors give (x, y, z, qx, qy, qz, qw) without a unit; acceleration extractors give (x, y, z)
with their unit ("g", "m/s^2", or None when the message does not say).  A message that decodes but is no
usable sample raises `Rejected` with the reason, which the reader counts per topic.
"""
from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from .schemas import UNIT_NAMES


class Rejected(Exception):
    """A message that decodes but is not a usable sample; the text is the reason, counted per topic."""


# An extractor turns one decoded message into (stamp ns or None, values, unit or None).
Extractor = Callable[[Any], tuple[int | None, tuple[float, ...], str | None]]


def _ros_stamp_ns(header) -> int | None:
    stamp_ns = header.stamp.sec * 10**9 + header.stamp.nanosec
    return stamp_ns if stamp_ns > 0 else None


def pose_stamped(msg):
    """geometry_msgs/PoseStamped -> (header stamp ns, (x, y, z, qx, qy, qz, qw), None).

    The stamp is None when the header's stamp is zero.  Position and quaternion are passed on as written.
    """
    position, orientation = msg.pose.position, msg.pose.orientation
    return _ros_stamp_ns(msg.header), (position.x, position.y, position.z, *_xyzw(orientation)), None


def transform_stamped(msg):
    """geometry_msgs/TransformStamped -> (header stamp ns, (x, y, z, qx, qy, qz, qw), None).

    Translation and rotation as written; the stamp is None when the header's stamp is zero.
    """
    translation, rotation = msg.transform.translation, msg.transform.rotation
    return _ros_stamp_ns(msg.header), (translation.x, translation.y, translation.z, *_xyzw(rotation)), None


def pose_with_covariance_stamped(msg):
    """geometry_msgs/PoseWithCovarianceStamped -> (header stamp ns, pose.pose (x, y, z, qx, qy, qz, qw), None).

    The covariance is ignored; the stamp is None when the header's stamp is zero.
    """
    return _ros_stamp_ns(msg.header), _pose_values(msg.pose.pose), None


def odometry(msg):
    """nav_msgs/Odometry -> (header stamp ns, pose.pose (x, y, z, qx, qy, qz, qw), None).

    The twist and the covariances are ignored; the stamp is None when the header's stamp is zero.
    """
    return _ros_stamp_ns(msg.header), _pose_values(msg.pose.pose), None


# A multi-pose extractor turns one decoded message into [(body name, stamp ns or None, values)], one entry per
# body it carries a pose of.
MultiExtractor = Callable[[Any], list[tuple[str, int | None, tuple[float, ...]]]]

# Parent frames a tracked body's transform hangs from (case-insensitive, leading "/" ignored): a transform
# between two body frames (a propeller, a camera mount) is no trajectory.
WORLD_FRAMES = ("world", "map", "mocap", "vicon", "optitrack", "qualisys")


def tf_message(msg):
    """tf2_msgs/TFMessage -> [(child_frame_id, header stamp ns, (x, y, z, qx, qy, qz, qw))] for every transform
    whose parent frame is a world frame (WORLD_FRAMES); transforms between other frames are left out."""
    bodies = []
    for transform in msg.transforms:
        if transform.header.frame_id.lstrip("/").lower() in WORLD_FRAMES and transform.child_frame_id:
            _, values, _ = transform_stamped(transform)
            bodies.append((transform.child_frame_id.lstrip("/"), _ros_stamp_ns(transform.header), values))
    return bodies


def named_pose_array(msg):
    """motion_capture_tracking_interfaces/NamedPoseArray -> [(name, header stamp ns, (x, y, z, qx, qy, qz, qw))],
    one per named body; all share the array's header stamp."""
    stamp = _ros_stamp_ns(msg.header)
    return [(named.name, stamp, _pose_values(named.pose)) for named in msg.poses if named.name]


def _pose_values(pose) -> tuple[float, ...]:
    position = pose.position
    return (position.x, position.y, position.z, *_xyzw(pose.orientation))


def _xyzw(quaternion) -> tuple[float, float, float, float]:
    return quaternion.x, quaternion.y, quaternion.z, quaternion.w


def imu(msg):
    """sensor_msgs/Imu -> (header stamp ns, linear_acceleration (x, y, z), "m/s^2").

    Orientation is ignored, the angular velocity read apart (`imu_gyro`); the stamp is None when the header's
    stamp is zero.
    """
    acc = msg.linear_acceleration
    return _ros_stamp_ns(msg.header), (acc.x, acc.y, acc.z), "m/s^2"


def imu_gyro(msg):
    """sensor_msgs/Imu -> (header stamp ns, angular_velocity (x, y, z), "rad/s"), body (IMU) frame.

    Raises
    ------
    Rejected
        The message says it has no angular velocity (element 0 of its covariance is -1, the ROS convention).
    """
    if len(msg.angular_velocity_covariance) and msg.angular_velocity_covariance[0] == -1:
        raise Rejected("no angular velocity (covariance -1)")
    rate = msg.angular_velocity
    return _ros_stamp_ns(msg.header), (rate.x, rate.y, rate.z), "rad/s"


def log_data(msg, indices: list[int], expected: int):
    """crazyflie_interfaces/LogDataGeneric -> (header stamp ns, the values at `indices` (acc.x, acc.y, acc.z), "g").

    Parameters
    ----------
    msg
        The decoded message.
    indices : list of int
        Positions of acc.x, acc.y, acc.z in ``msg.values``.
    expected : int
        How many values the log block holds.

    Raises
    ------
    Rejected
        The message does not hold `expected` values.
    """
    stamp, values, _ = log_values(msg, expected)
    return stamp, tuple(values[i] for i in indices), "g"


def log_values(msg, expected: int):
    """crazyflie_interfaces/LogDataGeneric -> (header stamp ns, every value of the log block, None).

    Raises
    ------
    Rejected
        The message does not hold `expected` values.
    """
    values = msg.values
    if len(values) != expected:
        raise Rejected(f"{len(values)} values instead of {expected}")
    return _ros_stamp_ns(msg.header), tuple(float(v) for v in values), None


def _json_field(obj, key: str):
    if not isinstance(obj, dict) or key not in obj:
        raise Rejected(f"no field {key!r}")
    return obj[key]


def _json_number(obj, key: str) -> float:
    value = _json_field(obj, key)
    if value is None:                # some JSON writers turn NaN into null
        return math.nan
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise Rejected(f"field {key!r} is not a number")
    return float(value)


def _json_stamp_ns(obj) -> int | None:
    stamp = obj.get("timestamp")
    if stamp is None:
        return None
    if not isinstance(stamp, dict):
        raise Rejected("timestamp is not an object {sec, nsec}")
    sec, nsec = stamp.get("sec", 0), stamp.get("nsec", stamp.get("nanosec", 0))
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (sec, nsec)):
        raise Rejected("timestamp sec/nsec are not integers")
    stamp_ns = sec * 10**9 + nsec
    return stamp_ns if 0 < stamp_ns < 2**63 else None


def _json_xyz(obj, keys: str = "xyz") -> tuple[float, ...]:
    return tuple(_json_number(obj, key) for key in keys)


def json_pose_in_frame(obj):
    """foxglove.PoseInFrame (JSON) -> (timestamp ns, position + orientation (x, y, z, qx, qy, qz, qw), None).

    A null number reads as NaN; the stamp is None without a timestamp or when it is outside (0, 2^63) ns.

    Raises
    ------
    Rejected
        A field is missing or not a number, or the timestamp is malformed.
    """
    pose = _json_field(obj, "pose")
    position = _json_xyz(_json_field(pose, "position"))
    orientation = _json_xyz(_json_field(pose, "orientation"), "xyzw")
    return _json_stamp_ns(obj), position + orientation, None


def json_frame_transform(obj):
    """foxglove.FrameTransform (JSON) -> (timestamp ns, translation + rotation (x, y, z, qx, qy, qz, qw), None).

    A null number reads as NaN; the stamp is None without a timestamp or when it is outside (0, 2^63) ns.

    Raises
    ------
    Rejected
        A field is missing or not a number, or the timestamp is malformed.
    """
    translation = _json_xyz(_json_field(obj, "translation"))
    rotation = _json_xyz(_json_field(obj, "rotation"), "xyzw")
    return _json_stamp_ns(obj), translation + rotation, None


def json_acceleration(obj):
    """learnest.Acceleration or a Vector3-like message (JSON) -> (timestamp ns, (x, y, z), unit).

    The unit is "g" or "m/s^2" (spellings normalised by UNIT_NAMES), None when the message has no unit field.

    Raises
    ------
    Rejected
        x, y or z missing or not a number, an unknown unit, or a malformed timestamp.
    """
    xyz = _json_xyz(obj)
    unit = obj.get("unit")
    if unit is not None and unit not in UNIT_NAMES:
        raise Rejected(f"unknown unit {unit!r} (expected 'g' or 'm/s^2')")
    return _json_stamp_ns(obj), xyz, UNIT_NAMES.get(unit)
