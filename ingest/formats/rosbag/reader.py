"""`read`: a ROS bag (ROS 1 .bag or ROS 2 sqlite3 .db3) as a Flight, through the MCAP reader's topic choice
and message-to-array path (see the package docstring)."""
from __future__ import annotations

from pathlib import Path

from ...flight import Flight, existing_file
from ..mcap.reader import read_channels
from .container import kind, open_bag


def sniff(path) -> bool:
    """True for a ROS 1 bag ("#ROSBAG V2.0") or an SQLite file (a ROS 2 .db3), from the first bytes."""
    return kind(Path(path)) is not None


def read(path, pose_topic: str | None = None, accel_topic: str | None = None, rate_hz: float = 100.0, *,
         log_variables: dict[str, list[str]] | None = None, cut: bool | tuple = True) -> Flight:
    """A ROS bag as a Flight.

    Parameters
    ----------
    path : str or Path
        A ROS 1 .bag or a ROS 2 sqlite3 storage file (.db3); the format is told from the content.
    pose_topic, accel_topic : str, optional
        The topics to read when the automatic choice is ambiguous; one body of a tf2_msgs/TFMessage or
        NamedPoseArray topic is "topic:name", e.g. "/poses:cf1".
    rate_hz : float
        Grid rate of the Flight, Hz.
    log_variables : dict, optional
        LogDataGeneric topic -> names of its values (see formats.mcap.reader.read).
    cut : bool or (start_s, stop_s)
        The stretch to keep, as `ingest.align.build_flight` takes it.

    Returns
    -------
    Flight
        meta["adapter"] "rosbag-ros1" or "rosbag-ros2"; meta["topics"] the chosen topics and the pose's
        source; meta["warnings"] when the pose is the vehicle's onboard estimate.

    Raises
    ------
    IngestError
        Naming the file: not a bag, damaged, no usable or ambiguous topics (every candidate listed).
    """
    path = existing_file(path, "ROS bag")
    with open_bag(path) as (channels, decoder_for):
        return read_channels(path, channels, [], decoder_for, container="rosbag", pose_topic=pose_topic,
                             accel_topic=accel_topic, rate_hz=rate_hz, log_variables=log_variables,
                             cut=cut)
