"""Which channel is what: a channel's message encoding, schema and topic decide whether it is read as a
pose, as an acceleration, or not at all, and with which extractor."""
from __future__ import annotations

from dataclasses import dataclass
from functools import partial

from ..crazyflie_variables import ACC
from . import extractors
from .container import McapChannel
from .extractors import Extractor
from .schemas import (
    ACCELERATION,
    FRAME_TRANSFORM,
    IMU,
    LOG_DATA_GENERIC,
    POSE_IN_FRAME,
    POSE_STAMPED,
    TRANSFORM_STAMPED,
    is_vector3_schema,
    ros_type,
)


@dataclass(frozen=True)
class Reading:
    """How one channel is read.

    Attributes
    ----------
    role : str
        "pose" (values x, y, z, qx, qy, qz, qw) or "accel" (values x, y, z, with the unit the extractor gives).
    extract : Extractor
        Decoded message -> (stamp ns or None, values, unit or None); raises extractors.Rejected.
    stamp_name : str
        Name of the message's own time stamp field ("header.stamp" or "timestamp"), for meta.
    """
    role: str             # "pose" (x, y, z, qx, qy, qz, qw) or "accel" (x, y, z with a unit)
    extract: Extractor
    stamp_name: str       # what the message's own time stamp is called, for meta


def _looks_like_acc_topic(topic: str) -> bool:
    return "acc" in topic.rstrip("/").split("/")[-1].lower()


def _log_data_layout(topic: str, log_variables: dict | None) -> tuple[list[int], int] | None:
    """(indices of acc.x/y/z in `values`, expected number of values), or None when the topic does not
    carry the accelerometer."""
    if log_variables and topic in log_variables:
        names = list(log_variables[topic])
        if not set(ACC) <= set(names):
            return None
        return [names.index(name) for name in ACC], len(names)
    return ([0, 1, 2], 3) if _looks_like_acc_topic(topic) else None


def classify(channel: McapChannel, log_variables: dict | None = None) -> Reading | None:
    """How to read a channel as pose or acceleration, or None when it is neither."""
    name = channel.schema_name
    if channel.message_encoding == "cdr" and channel.schema is not None:
        message_type = ros_type(name)
        if message_type == POSE_STAMPED:
            return Reading("pose", extractors.pose_stamped, "header.stamp")
        if message_type == TRANSFORM_STAMPED:
            return Reading("pose", extractors.transform_stamped, "header.stamp")
        if message_type == IMU:
            return Reading("accel", extractors.imu, "header.stamp")
        if message_type == LOG_DATA_GENERIC:
            layout = _log_data_layout(channel.topic, log_variables)
            if layout is not None:
                return Reading("accel", partial(extractors.log_data, indices=layout[0], expected=layout[1]),
                               "header.stamp")
    elif channel.message_encoding == "json":
        if name == POSE_IN_FRAME:
            return Reading("pose", extractors.json_pose_in_frame, "timestamp")
        if name == FRAME_TRANSFORM:
            return Reading("pose", extractors.json_frame_transform, "timestamp")
        if name == ACCELERATION or (is_vector3_schema(name) and _looks_like_acc_topic(channel.topic)):
            return Reading("accel", extractors.json_acceleration, "timestamp")
    return None
