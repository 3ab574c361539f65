"""Which topic is the pose and which the acceleration: the candidates of a recording (a multi-body topic gives
one candidate per body, "/poses:cf1"), the automatic choice (motion capture before the vehicle's own
estimate; a vehicle named by one topic picks the other), and the errors that list every candidate with its
type and message count when the choice is the user's."""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from ...flight import IngestError
from .channels import SOURCE_RANK, Channel, Reading, pose_source
from .decoding import Decoded, DecoderFor, split_bodies
from .schemas import ACCELERATION, FRAME_TRANSFORM, IMU, LOG_DATA_GENERIC, POSE_IN_FRAME, ros_type

BODY_SEPARATOR = ":"      # "/poses:cf1" is body cf1 of topic /poses

ROLE_WORDS = {"pose": ("motion-capture pose", "pose_topic", "--pose-topic",
                       "geometry_msgs/PoseStamped, TransformStamped, PoseWithCovarianceStamped, nav_msgs/Odometry, "
                       "tf2_msgs/TFMessage (as TOPIC:CHILD_FRAME), motion_capture_tracking_interfaces/NamedPoseArray "
                       f"(as TOPIC:NAME) (ROS); {POSE_IN_FRAME}, {FRAME_TRANSFORM} (json)"),
              "accel": ("acceleration", "accel_topic", "--imu-topic",
                        f"{IMU}, {LOG_DATA_GENERIC} on an 'acc' topic or mapped in log_variables (ROS); "
                        f"{ACCELERATION}, *Vector3 on an 'acc' topic (json)")}


@dataclass
class Candidate:
    """A stream that could play a role: a topic, or one body of a multi-body topic.

    Attributes
    ----------
    label : str
        What the user names it by: the topic, or "topic:body".
    channels : list of Channel
        The channels of the topic.
    reading : Reading
        How its messages are read.
    count : int
        Messages of the topic (of a multi-body topic: messages that carry this body).
    body : str or None
        The body's name in a multi-body topic.
    decoded : Decoded or None
        The samples, already decoded for a multi-body topic (listing the bodies needs every message).
    """
    label: str
    channels: Sequence[Channel]
    reading: Reading
    count: int
    body: str | None = None
    decoded: Decoded | None = None

    @property
    def topic(self) -> str:
        """The topic the candidate comes from."""
        return self.channels[0].topic

    @property
    def type_name(self) -> str:
        """Its message type."""
        return self.channels[0].schema_name

    @property
    def source(self) -> tuple[str, str]:
        """(where the pose comes from, why we think so); for accelerations ("", "")."""
        return pose_source(self.topic, self.type_name) if self.reading.role == "pose" else ("", "")

    def describe(self) -> str:
        """One line for messages: label (type, encoding, message count[, pose source])."""
        source = f", {self.source[0]}" if self.reading.role == "pose" else ""
        return f"{self.label} ({self.type_name}, {self.channels[0].message_encoding}, {self.count} messages{source})"

    def words(self) -> set[str]:
        """Names in its label that may name a vehicle: the body, or the topic's path parts."""
        return {self.body} if self.body else {part for part in self.topic.split("/") if part}


def listing(items) -> str:
    """Channels or candidates, one description each, separated by "; "."""
    return "; ".join(item.describe() for item in items) or "none"


def candidates(path: Path, channels: Sequence[Channel], readings: dict[int, Reading],
               decoder_for: DecoderFor) -> list[Candidate]:
    """Every stream that could be the pose or the acceleration, in topic order (multi-body topics are decoded
    here, to know their bodies)."""
    by_topic: dict[str, list[Channel]] = defaultdict(list)
    for channel in channels:
        if channel.id in readings and channel.messages:
            by_topic[channel.topic].append(channel)
    found = []
    for topic, topic_channels in sorted(by_topic.items()):
        reading = readings[topic_channels[0].id]
        if not reading.multi:
            found.append(Candidate(topic, topic_channels, reading, sum(c.count for c in topic_channels)))
            continue
        for body, decoded in split_bodies(path, topic_channels, reading, decoder_for).items():
            found.append(Candidate(f"{topic}{BODY_SEPARATOR}{body}", topic_channels, reading, len(decoded.values),
                                   body=body, decoded=decoded))
    return found


def _how_to_choose(role: str) -> str:
    _, argument, option, _ = ROLE_WORDS[role]
    field = "imu_topic" if role == "accel" else "pose_topic"
    return f"choose one with {argument}=... (CLI: {option} TOPIC; upload: form field {field})"


def _requested(path: Path, channels: Sequence[Channel], found: list[Candidate], role: str,
               requested: str) -> Candidate:
    what, _, _, supported = ROLE_WORDS[role]
    for candidate in found:
        if candidate.label == requested and candidate.reading.role == role:
            return candidate
    topic = requested.rsplit(BODY_SEPARATOR, 1)[0] if BODY_SEPARATOR in requested else requested
    bodies = [c for c in found if c.body is not None and c.topic in (requested, topic) and c.reading.role == role]
    if bodies and requested == bodies[0].topic and len(bodies) == 1:
        return bodies[0]
    if bodies:
        raise IngestError(path, f"topic {bodies[0].topic} carries {len(bodies)} bodies, {requested!r} is none of them: "
                            f"{listing(bodies)}; name one as TOPIC{BODY_SEPARATOR}NAME")
    named = [c for c in channels if c.topic in (requested, topic)]
    if not named:
        raise IngestError(path, f"no topic {requested!r} in this file; topics: {listing(channels)}")
    hint = (f"; for a LogDataGeneric topic pass log_variables={{{requested!r}: [variable names in log "
            f"order, including acc.x, acc.y, acc.z]}}"
            if any(ros_type(c.schema_name) == LOG_DATA_GENERIC for c in named) else "")
    raise IngestError(path, f"topic {requested} ({named[0].schema_name}) cannot be read as {what} "
                            f"(supported: {supported}){hint}")


def choose(path: Path, channels: Sequence[Channel], found: list[Candidate], role: str, requested: str | None,
           vehicle_words: set[str] | frozenset[str] = frozenset()) -> tuple[Candidate, str | None]:
    """The candidate that plays `role`, and a note saying why when others were passed over.

    Parameters
    ----------
    path : Path
        The file, for messages.
    channels : sequence of Channel
        Every channel of the file (listed when a requested topic is missing).
    found : list of Candidate
        What `candidates` gave.
    role : {"pose", "accel"}
    requested : str or None
        The topic (or "topic:body") the user named.
    vehicle_words : set of str
        Names of the vehicle the other topic belongs to: among equally good candidates, the one whose name
        contains one of them is taken.

    Raises
    ------
    IngestError
        The requested topic is missing or unreadable, or the choice is ambiguous (every candidate listed).
    """
    if requested is not None:
        return _requested(path, channels, found, role, requested), None
    what, _, _, supported = ROLE_WORDS[role]
    mine = [c for c in found if c.reading.role == role]
    if not mine:
        raise IngestError(path, f"no usable {what} topic (supported: {supported}); topics in the file: "
                                f"{listing(channels)}")
    rank = {c.label: SOURCE_RANK[c.source[0]] if role == "pose" else 0 for c in mine}
    best = [c for c in mine if rank[c.label] == min(rank.values())]
    note = None
    if len(best) > 1 and vehicle_words:
        same_vehicle = [c for c in best if c.words() & vehicle_words]
        if len(same_vehicle) == 1:
            best, note = same_vehicle, f"{same_vehicle[0].label}: the only {what} topic of vehicle " \
                                       f"{'/'.join(sorted(same_vehicle[0].words() & vehicle_words))}"
    if len(best) > 1:
        raise IngestError(path, f"{len(mine)} candidate {what} topics: {listing(mine)}; {_how_to_choose(role)}")
    if len(mine) > 1 and note is None:
        others = ", ".join(f"{c.label} ({c.source[0]})" for c in mine if c is not best[0])
        note = f"{best[0].label} ({best[0].source[0]}) preferred over {others}"
    return best[0], note
