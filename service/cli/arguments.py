"""The argument types and shared options of `learnest`'s subcommands: each refuses a bad value before
any import or ingest (one-line error, exit 2)."""
from __future__ import annotations

import argparse
import math
from pathlib import Path

from learnest.workflows.vocabulary import (
    EVALUATION_METHODS,
    GAP_EVERY_S,
    GAP_S,
    MIN_GAP_S,
    SG_WINDOW_RANGE,
    EvaluationSettings,
    InvalidInput,
    gap_plan_problem,
    parse_methods,
)


# -- argument types: refuse bad values before any import or ingest (one-line error, exit 2) -----------
def _positive_float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text!r}")
    return value


def _positive_int(text: str) -> int:
    return _whole_number(text, 1)


def _seconds(text: str) -> float:
    """A non-negative number of seconds (a gap length of 0 turns the gap yardstick off)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be a non-negative number of seconds, got {text!r}")
    return value


def _whole_number(text: str, least: int = 0) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"must be at least {least}, got {text!r}")
    return value


def _sg_window(text: str) -> int:
    """A Savitzky-Golay window in samples, within `SG_WINDOW_RANGE`."""
    value = _positive_int(text)
    low, high = SG_WINDOW_RANGE
    if not low <= value <= high:
        raise argparse.ArgumentTypeError(f"must be {low} to {high} samples, got {text!r}")
    return value


def _model_ref(text: str) -> str:
    """A registry reference, checked for its form only (whether it exists needs the registry)."""
    from ..local import parse_ref

    try:
        return str(parse_ref(text))
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _name(text: str) -> str:
    """A registered model or alias name (references.NAME), checked before any import of the service."""
    from ..local import check_name

    try:
        return check_name(text)
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _topic(text: str) -> str:
    """A ROS topic name, optionally with ":BODY" (one body of a TFMessage / NamedPoseArray topic)."""
    from ..local import check_topic

    try:
        return check_topic(text)
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _cut(text: str) -> str:
    """The take-off/landing cut, checked for its form before any work (`learnest.ingest.align.parse_cut`)."""
    from learnest.workflows.files import cut_text, parse_cut

    try:
        return cut_text(parse_cut(text))
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def _new_file(text: str) -> str:
    """An output path whose folder exists: a typo must not cost a whole evaluation."""
    folder = Path(text).expanduser().resolve().parent
    if not folder.is_dir():
        raise argparse.ArgumentTypeError(f"folder {folder} does not exist")
    if Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file name")
    return text


def _export_path(text: str) -> str:
    """An output file whose folder exists and whose suffix names an export format (.csv, .parquet, .mcap)."""
    from learnest.workflows.files import format_of

    try:
        format_of(text)
    except InvalidInput as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return _new_file(text)


def _export_format(path: str) -> str:
    from learnest.workflows.files import format_of

    return format_of(path)


def evaluation_settings(args: argparse.Namespace) -> EvaluationSettings:
    """The settings `learnest evaluate` is asked for (--methods, --horizon, --include-bad, --sg-window, --gap-s,
    --gap-every-s, --noise) as their type, built before any flight is read: InvalidInput naming the setting when
    one is out of bounds (`EvaluationSettings`)."""
    return EvaluationSettings(tuple(parse_methods(args.methods, EVALUATION_METHODS)), args.horizon, args.include_bad,
                              args.sg_window, args.gap_s, args.gap_every_s, args.noise)


def gap_options_problem(args: argparse.Namespace) -> str | None:
    """Why --gap-s and --gap-every-s (on the --rate grid, when the command has one) make no bounded gap plan,
    naming the option; None when they do or the command has none.  Checked right after parsing, before any
    import, ingest or stored row (`learnest.models.presets.gap_plan_problem`)."""
    if not hasattr(args, "gap_s") or not hasattr(args, "gap_every_s"):
        return None
    rate = getattr(args, "rate", None)
    problem = gap_plan_problem(args.gap_s, args.gap_every_s, dt=1.0 / rate if rate else None)
    return None if problem is None else f"argument --{problem[0].replace('_', '-')}: {problem[1]}"


def _add_gap_arguments(parser: argparse.ArgumentParser) -> None:
    """--gap-s and --gap-every-s: where the mocap-gap yardstick hides the mocap (estimators.yardsticks)."""
    parser.add_argument("--gap-s", type=_seconds, default=GAP_S, metavar="S",
                        help=f"mocap-gap yardstick: hide the mocap position from the estimators for S s per gap "
                             f"(default {GAP_S}; 0: no gaps; else at least {MIN_GAP_S:g} s and one sample)")
    parser.add_argument("--gap-every-s", type=_positive_float, default=GAP_EVERY_S, metavar="S",
                        help=f"one gap every S s after the first 5 s of the kept flight (default {GAP_EVERY_S})")


def _add_topic_arguments(parser: argparse.ArgumentParser) -> None:
    """--pose-topic / --imu-topic, for the commands that read MCAP recordings and ROS bags."""
    parser.add_argument("--pose-topic", type=_topic, metavar="TOPIC",
                        help="MCAP/ROS bag: the pose topic to read, e.g. /poses:cf1 (one body of a NamedPoseArray "
                             "or /tf topic) or /vicon/cf1/cf1 (default: the motion-capture topic, if only one)")
    parser.add_argument("--imu-topic", "--accel-topic", dest="imu_topic", type=_topic, metavar="TOPIC",
                        help="MCAP/ROS bag: the acceleration topic (sensor_msgs/Imu or LogDataGeneric), "
                             "e.g. /cf1/imu (default: the only one, or the pose's vehicle's)")


def _topics(args) -> dict:
    return {"pose_topic": getattr(args, "pose_topic", None), "imu_topic": getattr(args, "imu_topic", None)}


def _add_cut_argument(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--cut", type=_cut, default="auto", metavar="auto|none|START:STOP",
                        help="the stretch of each recording to keep: auto (default: the flying part, take-off and "
                             "landing cut; a log that starts in the air keeps its start), none (everything) or "
                             "START:STOP in seconds from the recording's start, e.g. 2.5:14 (either side may be empty)")


# `learnest serve --NAME` options that override LEARNEST_NAME (service.config): timeouts and limits
SERVE_LIMITS = {"header_timeout_s": (float, "a request's headers must arrive within this many seconds (10)"),
                "body_timeout_s": (float, "a request body gets this many seconds (30) ..."),
                "body_min_rate": (float, "... plus one per this many bytes received (10000); else 408"),
                "body_max_s": (float, "... and never more than this many seconds in all (900)"),
                "keep_alive_s": (float, "close an idle keep-alive connection after this many seconds (5)"),
                "send_timeout_s": (float, "drop a client that takes no byte of an answer for this many seconds (60)"),
                "limit_concurrency": (int, "connections + requests in progress beyond which the answer is 503 "
                                           "(200; 0 = no limit)"),
                "max_client_connections": (int, "connections from one client network (/24, /64) beyond which the "
                                                "answer is 503 (32; 0 = no limit)"),
                "decode_workers": (int, "uploads decoded at once (2)"),
                "decode_timeout_s": (float, "one upload's decode time limit, seconds (60)")}
