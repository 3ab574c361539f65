"""The Crazyflie's inputs in a recording: crazyswarm2 publishes custom firmware log blocks as
crazyflie_interfaces/LogDataGeneric topics (values only, in log-block order), so which topic carries which
firmware variable comes from the user's crazyswarm2 configuration (`crazyflies.yaml`, its
``firmware_logging.custom_topics``) or from ``log_variables`` {topic: [names]}.  Variables known to
`ingest.formats.crazyflie_variables` (motor.m1..m4, pm.vbat, pm.vbatMV, rpm.m1..m4, ctrlLee.thrustSI,
gyro.x/y/z, ...) become the same Flight channels, in the same units, as in a uSD or cfclient log.
"""
from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from functools import partial
from pathlib import Path

import numpy as np

from ...flight import IngestError
from ...sidecar import SidecarTooLarge, read_sidecar
from ..crazyflie_variables import OPTIONAL_SOURCES
from . import extractors
from .channels import Channel, Reading
from .decoding import DecoderFor, decode
from .schemas import LOG_DATA_GENERIC, ROS_ENCODINGS, ros_type

# Beside a recording: "<file stem>_crazyflies.yaml" (one per recording), else "crazyflies.yaml" (the folder's);
# ingest.sidecar.CRAZYSWARM_CONFIG recognises the same names.
CRAZYSWARM_CONFIG_NAMES = ("{stem}_crazyflies.yaml", "{stem}_crazyflies.yml", "crazyflies.yaml", "crazyflies.yml")
INPUT_VARIABLES = frozenset(name for _, names, _ in OPTIONAL_SOURCES for name in names)


def _custom_topics(scope: object) -> dict[str, list[str]]:
    """{topic name: vars} of one scope's ``firmware_logging.custom_topics`` (entries without a list of
    names are left out)."""
    logging = scope.get("firmware_logging") if isinstance(scope, dict) else None
    custom = logging.get("custom_topics") if isinstance(logging, dict) else None
    if not isinstance(custom, dict):
        return {}
    return {str(name): list(spec["vars"]) for name, spec in custom.items()
            if isinstance(spec, dict) and isinstance(spec.get("vars"), list)
            and all(isinstance(v, str) for v in spec["vars"])}


def crazyswarm_log_variables(config: object) -> dict[str, list[str]]:
    """The LogDataGeneric topics a crazyswarm2 ``crazyflies.yaml`` declares, with their variables.

    crazyswarm2's server publishes custom topic NAME of robot ROBOT as ``/ROBOT/NAME``; a robot's topics are
    those under ``all``, its ``robot_types`` entry and its own entry (the later scope wins for one NAME).

    Parameters
    ----------
    config : object
        The parsed YAML (anything else than a mapping gives no topics).

    Returns
    -------
    dict
        {"/ROBOT/NAME": ["group.name", ...]} in log-block order, e.g.
        {"/cf1/motors": ["motor.m1", "motor.m2", "motor.m3", "motor.m4"]}.
    """
    if not isinstance(config, dict):
        return {}
    robots, types = config.get("robots"), config.get("robot_types")
    robots = robots if isinstance(robots, dict) else {}
    types = types if isinstance(types, dict) else {}
    found = {}
    for robot, settings in robots.items():
        settings = settings if isinstance(settings, dict) else {}
        robot_type = settings.get("type")
        merged = {**_custom_topics(config.get("all")),
                  **_custom_topics(types.get(robot_type) if isinstance(robot_type, str) else None),
                  **_custom_topics(settings)}
        found.update({f"/{robot}/{name}": names for name, names in merged.items()})
    return found


def sidecar_log_variables(path: Path, notes: list[str]) -> tuple[dict[str, list[str]] | None, Path | None]:
    """The log variables of the crazyswarm2 configuration beside a recording, and the configuration's path.

    Looks for ``<stem>_crazyflies.yaml``, then ``crazyflies.yaml`` (or ``.yml``), in the recording's folder;
    (None, None) without one.  An unreadable configuration is a note (the recording is still a flight:
    (None, its path)); one past the sidecar caps is refused (`ingest.sidecar.SidecarTooLarge`).
    """
    for name in CRAZYSWARM_CONFIG_NAMES:
        config = path.with_name(name.format(stem=path.stem))
        if not config.is_file():
            continue
        try:
            record = read_sidecar(config)
        except SidecarTooLarge:
            raise
        except IngestError as err:
            notes.append(f"{config.name}: {err.problem}; its log variables are not used")
            return None, config
        found = crazyswarm_log_variables(record)
        notes.append(f"{config.name}: LogDataGeneric variables of {len(found)} topic(s) "
                     f"({', '.join(sorted(found)) or 'none declared'})")
        return found, config
    return None, None


def _on_clock(decoded, use_stamps: bool, origin_ns: int) -> tuple[np.ndarray, str]:
    """Seconds since origin_ns: the header stamps when the pose and acceleration use theirs and this topic
    has one in every message, else the receive times."""
    if use_stamps and all(stamp is not None for stamp in decoded.stamps):
        return np.array([(ns - origin_ns) / 1e9 for ns in decoded.stamps]), decoded.reading.stamp_name
    return np.array([(ns - origin_ns) / 1e9 for ns in decoded.log_times]), "log_time"


def _clean(t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Time-sorted finite rows with distinct times (the first of a repeat kept)."""
    keep = np.all(np.isfinite(values), axis=1)
    t, values = t[keep], values[keep]
    order = np.argsort(t, kind="stable")
    t, values = t[order], values[order]
    first = np.r_[True, np.diff(t) > 0]
    return t[first], values[first]


def input_channels(path: Path, channels: Sequence[Channel], log_variables: dict[str, list[str]] | None,
                   decoder_for: DecoderFor, *, use_stamps: bool, origin_ns: int,
                   notes: list[str]) -> tuple[dict, dict]:
    """The optional Flight channels (motors, vbat, rotor_speed, thrust_si, gyro, ...) of the LogDataGeneric
    topics that ``log_variables`` names.

    Parameters
    ----------
    path : Path
        The file, for messages.
    channels : sequence of Channel
        Every channel of the recording.
    log_variables : dict or None
        LogDataGeneric topic -> its variable names in log-block order.
    decoder_for : DecoderFor
        The container's payload decoder.
    use_stamps : bool
        Whether the pose and acceleration are on their header stamps (else on the receive times).
    origin_ns : int
        Time zero of the pose and acceleration streams, ns on the same clock.
    notes : list of str
        Gets one line per topic that could not be used.

    Returns
    -------
    (channels, meta)
        channels: {name: (t (K,) s since origin_ns, values (K, k) in the channel's unit)}, for
        `ingest.align.build_flight`; the first source of crazyflie_variables.OPTIONAL_SOURCES present wins,
        converted with its unit converter.  meta: {name: {"topic", "variables", "time_source", "samples"}}.
    """
    by_topic: dict[str, list[Channel]] = defaultdict(list)
    for channel in channels:
        if (log_variables and channel.topic in log_variables and channel.messages
                and channel.message_encoding in ROS_ENCODINGS and ros_type(channel.schema_name) == LOG_DATA_GENERIC
                and INPUT_VARIABLES & set(log_variables[channel.topic])):
            by_topic[channel.topic].append(channel)
    streams = {}
    for topic, topic_channels in sorted(by_topic.items()):
        names = list(log_variables[topic]) if log_variables else []
        reading = Reading("inputs", partial(extractors.log_values, expected=len(names)), "header.stamp")
        try:
            decoded = decode(path, topic_channels, reading, decoder_for)
        except IngestError as err:
            notes.append(f"{err.problem}; its inputs are left out")
            continue
        t, time_source = _on_clock(decoded, use_stamps, origin_ns)
        streams[topic] = (names, t, np.array(decoded.values, dtype=float), time_source)
    found: dict = {}
    meta: dict = {}
    for output, variables, to_unit in OPTIONAL_SOURCES:
        for topic, (names, t, values, time_source) in streams.items():
            if output in found or not set(variables) <= set(names):
                continue
            converted = to_unit(values[:, [names.index(name) for name in variables]]).reshape(len(t), -1)
            t_kept, kept = _clean(t, converted)
            if len(t_kept) >= 2:
                found[output] = (t_kept, kept)
                meta[output] = {"topic": topic, "variables": list(variables), "time_source": time_source,
                                 "samples": len(t_kept)}
    return found, meta


def imu_gyro_channel(path: Path, accel_channels: Sequence[Channel], decoder_for: DecoderFor, *, use_stamps: bool,
                     origin_ns: int, notes: list[str]) -> tuple[tuple[np.ndarray, np.ndarray], dict] | None:
    """The gyro (rad/s, body frame) of the sensor_msgs/Imu topic chosen for the acceleration.

    Returns
    -------
    ((t (K,) s since origin_ns, values (K, 3) rad/s), meta) or None
        None when the messages say they carry no angular velocity (covariance -1, silently: the driver
        declares it) or carry zeros throughout (a driver that leaves the field unset: noted in ``notes``).
    """
    topic = accel_channels[0].topic
    try:
        decoded = decode(path, accel_channels, Reading("inputs", extractors.imu_gyro, "header.stamp"), decoder_for)
    except IngestError:
        return None
    t, time_source = _on_clock(decoded, use_stamps, origin_ns)
    t, values = _clean(t, np.array(decoded.values, dtype=float).reshape(len(t), 3))
    if len(t) < 2:
        notes.append(f"{topic}: fewer than 2 usable angular velocities (non-finite or repeated times): no gyro")
        return None
    if not np.any(values):
        notes.append(f"{topic}: angular_velocity is zero in every Imu message (not logged): no gyro")
        return None
    return (t, values), {"topic": topic, "variables": ["angular_velocity.x", "angular_velocity.y",
                                                       "angular_velocity.z"], "time_source": time_source,
                         "samples": len(t)}
