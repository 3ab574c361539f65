"""`read`: an MCAP recording as a Flight (see the package docstring for the supported topics).

The file is scanned (`container`), its channels classified (`channels`); then one pose and one
acceleration topic are chosen, their messages decoded and extracted, put on one clock, cleaned (time order,
repeats, non-finite values, non-unit quaternions, the acceleration's unit) and handed to
`ingest.align.build_flight`.
"""
from __future__ import annotations

import contextlib
import io
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from mcap_ros2.decoder import DecoderFactory

from ...align import build_flight, samples_per_second
from ...flight import Flight, IngestError, sha256_file
from ...frames import GRAVITY
from ...limits import MAX_DURATION_S, QUATERNION_NORM_TOLERANCE
from . import extractors
from .channels import ONBOARD, Channel, Reading, classify
from .container import MAGIC, McapChannel, scan
from .decoding import Decoded, DecoderFor, decode
from .inputs import imu_gyro_channel, input_channels, sidecar_log_variables
from .selection import ROLE_WORDS, Candidate, candidates, choose, listing

# A flight's median specific force is ≈ 1 g (hover or rest); outside these bounds the unit is wrong.
PLAUSIBLE_MEDIAN_ACC_G = (0.25, 4.0)


def sniff(path) -> bool:
    """True when the file starts with the MCAP magic bytes (content, not extension)."""
    try:
        with open(path, "rb") as handle:
            return handle.read(len(MAGIC)) == MAGIC
    except OSError:
        return False


# -- decoding ------------------------------------------------------------------------------------------------

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


def _has_all_stamps(decoded: Decoded) -> bool:
    return all(stamp is not None for stamp in decoded.stamps)


def _times(decoded: Decoded, use_stamps: bool) -> tuple[list[int], str]:
    """The messages' own stamps when asked for and every message has one, otherwise their log_time."""
    if use_stamps:
        stamps = [stamp for stamp in decoded.stamps if stamp is not None]
        if len(stamps) == len(decoded.stamps):
            return stamps, decoded.reading.stamp_name
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


def _no_usable_topics(path: Path, channels: Sequence[Channel], warnings: list[str],
                      readings: dict[int, Reading]) -> IngestError | None:
    if any(c.messages and c.id in readings for c in channels):
        return None
    notes = f" [{'; '.join(warnings)}]" if warnings else ""
    return IngestError(path, f"no usable topics (need a pose topic: {ROLE_WORDS['pose'][3]}; and an "
                             f"acceleration topic: {ROLE_WORDS['accel'][3]}); topics in the file: "
                             f"{listing(channels)}{notes}")


# -- public entry ------------------------------------------------------------------------------------------

def _stream(path: Path, decoded: Decoded, label: str, t_ns: list[int], origin_ns: int,
            notes: list[str]) -> tuple[np.ndarray, np.ndarray, dict]:
    """Seconds since origin_ns, cleaned values (pose as-is, acceleration in g), and the topic's report."""
    messages = (len(decoded.values) + sum(decoded.rejected.values()) if decoded.reading.multi
                else sum(c.count for c in decoded.channels))
    report: dict[str, Any] = {"messages": messages,
                              "rejected": dict(decoded.rejected)}
    t_s = np.array([(ns - origin_ns) / 1e9 for ns in t_ns], dtype=float)  # exact ints, then one rounding
    values = np.array(decoded.values, dtype=float)
    if decoded.reading.role == "pose":
        t_s, values = _clean(t_s, values, report, valid_row=_unit_quaternion(values))
    else:
        values = _to_g(label, values, decoded.units, notes)
        t_s, values = _clean(t_s, values, report)
    if len(t_s) < 2:
        dropped = {**report["rejected"], **{k: v for k, v in report.items() if k in DROP_REASONS and v}}
        raise IngestError(path, f"topic {label}: {len(t_s)} usable message(s) of {report['messages']} "
                                f"(dropped: {dropped or 'none'})")
    return t_s, values, report


def read(path, pose_topic: str | None = None, accel_topic: str | None = None, rate_hz: float = 100.0, *,
         log_variables: dict[str, list[str]] | None = None, cut: bool | tuple = True) -> Flight:
    """An MCAP recording as a Flight (see the module docstring for the supported topics).

    pose_topic / accel_topic choose the topics when the automatic choice is ambiguous (a body of a multi-body
    topic is "topic:name", e.g. "/poses:cf1").  log_variables maps LogDataGeneric topics to the names of their
    values, e.g. {"/cf1/imu": ["gyro.x", "gyro.y", "gyro.z", "acc.x", "acc.y", "acc.z"]}.  ``cut`` as
    `ingest.align.build_flight` takes it.
    """
    path = Path(path)
    content = scan(path)
    return read_channels(path, content.channels, content.warnings, _payload_decoder, container="mcap",
                         pose_topic=pose_topic, accel_topic=accel_topic, rate_hz=rate_hz, log_variables=log_variables,
                         cut=cut)


ADAPTER_NAMES = {frozenset({"cdr"}): "ros2", frozenset({"ros1"}): "ros1", frozenset({"json"}): "json"}


def read_channels(path: Path, channels: Sequence[Channel], warnings: list[str], decoder_for: DecoderFor, *,
                  container: str, pose_topic: str | None = None, accel_topic: str | None = None,
                  rate_hz: float = 100.0, log_variables: dict[str, list[str]] | None = None,
                  cut: bool | tuple = True) -> Flight:
    """The Flight of a recording's channels, whatever container they come from (MCAP here, ROS bags in
    formats.rosbag): topic choice, decoding, one clock, cleaning, the Flight.

    Parameters
    ----------
    path : Path
        The file, for messages and meta.
    channels : sequence of Channel
        Every channel of the file; messages are kept for pose/acceleration candidates.
    warnings : list of str
        What the container met on the way (damage), carried into meta[container]["warnings"].
    decoder_for : DecoderFor
        The container's payload decoder for a channel.
    container : str
        "mcap" or "rosbag": the meta key and the adapter name's prefix.
    pose_topic, accel_topic, rate_hz, log_variables
        As in `read`.  Without log_variables, those of a crazyswarm2 ``crazyflies.yaml`` beside the file
        (`inputs.sidecar_log_variables`); known Crazyflie variables among them become optional channels
        (motors, vbat, ...: `inputs.input_channels`).

    Returns
    -------
    Flight
        With meta["topics"] (the chosen topics and where the pose comes from), meta["warnings"] (an onboard
        estimate taken as the truth) and meta[container] (the details; "inputs": which topic and variables
        gave each input channel).
    """
    notes = list(warnings)
    config = None
    if log_variables is None:   # crazyswarm2's crazyflies.yaml beside the recording names its LogDataGeneric values
        log_variables, config = sidecar_log_variables(path, notes)
    readings = {c.id: r for c in channels if (r := classify(c, log_variables)) is not None}
    if (error := _no_usable_topics(path, channels, notes, readings)) is not None:
        raise error
    found = candidates(path, channels, readings, decoder_for)
    accel_words = {part for part in (accel_topic or "").split("/") if part}
    pose_choice, pose_note = choose(path, channels, found, "pose", pose_topic, accel_words)
    accel_choice, accel_note = choose(path, channels, found, "accel", accel_topic, pose_choice.words())
    notes += [note for note in (pose_note, accel_note) if note]
    pose = pose_choice.decoded or decode(path, pose_choice.channels, pose_choice.reading, decoder_for)
    accel = decode(path, accel_choice.channels, accel_choice.reading, decoder_for)

    # One clock: message stamps only when both topics have them throughout.
    use_stamps = _has_all_stamps(pose) and _has_all_stamps(accel)
    if _has_all_stamps(pose) != _has_all_stamps(accel):
        notes.append("only one of the two topics has time stamps in every message: both use the receive time "
                     "(log_time)")
    (t_pose_ns, pose_source), (t_acc_ns, acc_source) = _times(pose, use_stamps), _times(accel, use_stamps)
    origin_ns = min(min(t_pose_ns), min(t_acc_ns))
    t_pose, mocap, pose_report = _stream(path, pose, pose_choice.label, t_pose_ns, origin_ns, notes)
    t_acc, acc_g, acc_report = _stream(path, accel, accel_choice.label, t_acc_ns, origin_ns, notes)
    _check_acc_magnitude(path, accel_choice.label, acc_g)
    inputs, inputs_meta = input_channels(path, channels, log_variables, decoder_for, use_stamps=use_stamps,
                                         origin_ns=origin_ns, notes=notes)
    if "gyro" not in inputs and accel_choice.reading.extract is extractors.imu:
        # a LogDataGeneric gyro the user named wins; else the Imu's own angular velocity, when it has one
        gyro = imu_gyro_channel(path, accel_choice.channels, decoder_for, use_stamps=use_stamps,
                                origin_ns=origin_ns, notes=notes)
        if gyro is not None:
            inputs["gyro"], inputs_meta["gyro"] = gyro
    overlap = min(t_pose[-1], t_acc[-1]) - max(t_pose[0], t_acc[0])
    if overlap > MAX_DURATION_S:
        raise IngestError(path, f"pose and acceleration overlap for {overlap:.6g} s, more than "
                                f"{MAX_DURATION_S:.0f} s: corrupt time stamps?")

    meta = _recording_meta(path, config, container, pose_choice, accel_choice, found, (t_pose, t_acc),
                           {"pose": pose_source, "accel": acc_source}, origin_ns,
                           {"pose": pose_report, "accel": acc_report}, inputs_meta, notes)
    return build_flight(path, t_mocap=t_pose, p=mocap[:, :3], quat=mocap[:, 3:7], t_acc=t_acc, channels=inputs,
                        acc_body_g=acc_g, rate_hz=rate_hz, meta=meta, cut=cut)


def _recording_meta(path: Path, config: Path | None, container: str, pose_choice: Candidate, accel_choice: Candidate,
                    found: list[Candidate], times: tuple, time_source: dict, origin_ns: int, streams: dict,
                    inputs_meta: dict, notes: list[str]) -> dict:
    """`read_channels`' Flight meta: adapter, source files with sha256, rates of the pose and acceleration
    ``times`` (s), the topics and where the pose comes from, warnings, and the container's details."""
    t_pose, t_acc = times
    encodings = frozenset({pose_choice.channels[0].message_encoding, accel_choice.channels[0].message_encoding})
    source, why = pose_choice.source
    meta = {
        "adapter": f"{container}-{ADAPTER_NAMES.get(encodings, 'ros2+json')}",
        "sources": [{"path": str(p), "sha256": sha256_file(p)} for p in (path, config) if p is not None],
        "original_rates": {"mocap": samples_per_second(t_pose), "acc": samples_per_second(t_acc)},
        "clock_offset_s": None,     # one recorder clock for every topic in a bag
        "topics": {"pose": pose_choice.label, "pose_type": pose_choice.type_name, "pose_source": source,
                   "pose_source_reason": why, "accel": accel_choice.label, "accel_type": accel_choice.type_name},
        "warnings": ([_onboard_warning(pose_choice.label, why)] if source == ONBOARD else [])
                    + _vehicle_mismatch(pose_choice, accel_choice, found),
        container: {"pose_topic": pose_choice.label, "accel_topic": accel_choice.label,
                    "pose_type": pose_choice.type_name, "accel_type": accel_choice.type_name,
                    "time_source": time_source, "time_origin_ns": origin_ns,
                    "streams": streams, "inputs": inputs_meta,
                    "warnings": notes},
    }
    if pose_choice.body:
        meta["vehicle"] = pose_choice.body
    return meta


def _vehicle_mismatch(pose: Candidate, accel: Candidate, found: list[Candidate]) -> list[str]:
    """A warning when the acceleration topic is named after another body of the pose's multi-body topic."""
    others = {c.body for c in found if c.body and c.topic == pose.topic and c.body != pose.body}
    named = accel.words() & others
    if pose.body is None or pose.body in accel.words() or not named:
        return []
    return [f"the acceleration topic {accel.label} seems to belong to {sorted(named)[0]}, the pose {pose.label} "
            f"to {pose.body}: choose the IMU topic of {pose.body}"]


def _onboard_warning(label: str, why: str) -> str:
    return (f"the pose topic {label} is the vehicle's onboard estimate, not motion capture ({why}): errors "
            f"measured against it are errors against the Crazyflie's own estimator, not against the truth")
