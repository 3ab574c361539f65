"""Which channel is what: a channel's message encoding, schema and topic decide whether it is read as a
pose, as an acceleration, or not at all, with which extractor, and where its pose comes from (motion
capture, the vehicle's own estimate, or unknown).

A channel is anything with the attributes of `Channel`: an MCAP channel (container.McapChannel) or a
connection of a ROS bag (formats.rosbag)."""
from __future__ import annotations

import re
from dataclasses import dataclass
from functools import partial
from typing import Protocol

from ..crazyflie_variables import ACC
from . import extractors
from .extractors import Extractor, MultiExtractor
from .schemas import (
    ACCELERATION,
    FRAME_TRANSFORM,
    IMU,
    LOG_DATA_GENERIC,
    NAMED_POSE_ARRAY,
    ODOMETRY,
    POSE_IN_FRAME,
    POSE_STAMPED,
    POSE_WITH_COVARIANCE_STAMPED,
    ROS_ENCODINGS,
    TF_MESSAGE,
    TRANSFORM_STAMPED,
    is_vector3_schema,
    ros_type,
)


class Channel(Protocol):
    """What the reader needs of a channel, whatever container it comes from."""

    id: int
    topic: str
    message_encoding: str                 # "cdr", "ros1" or "json"
    count: int                            # messages in the file
    messages: list[tuple[int, bytes]]     # (receive time ns, payload), kept for candidate channels only

    @property
    def schema_name(self) -> str:
        """The message type ("pkg/msg/Type" or a JSON schema name), "" when unknown."""

    def describe(self) -> str:
        """One line for messages: topic (type, encoding, message count)."""


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
    extract: Extractor | None
    stamp_name: str       # what the message's own time stamp is called, for meta
    split: MultiExtractor | None = None   # instead of extract: a message with the poses of several bodies

    @property
    def multi(self) -> bool:
        """Whether a message carries several named bodies (each body is a candidate "topic:name")."""
        return self.split is not None


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


ROS_POSE_EXTRACTORS = {POSE_STAMPED: extractors.pose_stamped, TRANSFORM_STAMPED: extractors.transform_stamped,
                       POSE_WITH_COVARIANCE_STAMPED: extractors.pose_with_covariance_stamped,
                       ODOMETRY: extractors.odometry}
ROS_MULTI_POSE_EXTRACTORS = {TF_MESSAGE: extractors.tf_message, NAMED_POSE_ARRAY: extractors.named_pose_array}
# /tf_static holds fixed transforms (mounts, frames), never a trajectory
STATIC_TOPICS = ("/tf_static",)


def classify(channel: Channel, log_variables: dict | None = None) -> Reading | None:
    """How to read a channel as pose or acceleration, or None when it is neither."""
    name = channel.schema_name
    if channel.message_encoding in ROS_ENCODINGS and name:
        message_type = ros_type(name)
        if message_type in ROS_POSE_EXTRACTORS:
            return Reading("pose", ROS_POSE_EXTRACTORS[message_type], "header.stamp")
        if message_type in ROS_MULTI_POSE_EXTRACTORS and channel.topic not in STATIC_TOPICS:
            return Reading("pose", None, "header.stamp", split=ROS_MULTI_POSE_EXTRACTORS[message_type])
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


# -- where a pose comes from ------------------------------------------------------------------------------

MOTION_CAPTURE, ONBOARD, UNKNOWN = "motion capture", "onboard estimate", "unknown"
# Preference when several pose topics could be read: motion capture first, the vehicle's own estimate last.
SOURCE_RANK = {MOTION_CAPTURE: 0, UNKNOWN: 1, ONBOARD: 2}
MOCAP_WORDS = ("vicon", "mocap", "optitrack", "qualisys", "natnet", "motion_capture", "vrpn")
# crazyswarm2's crazyflie_server publishes each Crazyflie's own state estimate as /<name>/pose
CRAZYSWARM_ONBOARD_POSE = re.compile(r"/[^/]+/pose")


def pose_source(topic: str, type_name: str) -> tuple[str, str]:
    """(MOTION_CAPTURE, ONBOARD or UNKNOWN, why) for a pose topic, from its name and message type."""
    message_type = ros_type(type_name)
    if message_type == NAMED_POSE_ARRAY:
        return MOTION_CAPTURE, "motion_capture_tracking's NamedPoseArray"
    words = [word for word in MOCAP_WORDS if word in topic.lower()]
    if words:
        return MOTION_CAPTURE, f"topic name contains {words[0]!r}"
    if message_type == POSE_STAMPED and CRAZYSWARM_ONBOARD_POSE.fullmatch(topic):
        return ONBOARD, "crazyswarm2 publishes each Crazyflie's own state estimate on /<name>/pose"
    if message_type == ODOMETRY:
        return ONBOARD, "nav_msgs/Odometry is normally a state estimator's output"
    if message_type == TF_MESSAGE:
        return UNKNOWN, "/tf may carry motion capture or the onboard estimate (crazyswarm2 broadcasts both)"
    return UNKNOWN, "neither a motion-capture name nor a known onboard-estimate topic"
