"""Decoding a chosen channel's messages into samples: (receive time, own stamp, values, unit) per message,
with the messages that are no usable sample counted by reason.  A channel whose messages carry several named
bodies (tf2_msgs/TFMessage, NamedPoseArray) is split into one sample stream per body."""
from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ...flight import IngestError
from .channels import Channel, Reading
from .extractors import Rejected

# (file, channel) -> a function from one payload to the decoded message; raises IngestError when the
# channel's definition cannot be used.  (The channel is the container's own kind: Any.)
DecoderFor = Callable[[Path, Any], Callable[[bytes], Any]]


@dataclass
class Decoded:
    """The samples of one stream (one topic, or one body of a multi-body topic).

    Attributes
    ----------
    channels : list of Channel
        Where the samples come from (one topic may have several channels).
    reading : Reading
        How they were read.
    log_times : list of int
        Receive time of each sample's message, ns.
    stamps : list of int or None
        The message's own stamp, ns (None when it has none).
    values : list of tuple
        Pose (x, y, z, qx, qy, qz, qw) or acceleration (x, y, z).
    units : list of str or None
        Acceleration unit of each sample ("g", "m/s^2" or None); None for poses.
    rejected : Counter
        Messages that gave no sample, by reason.
    """
    channels: Sequence[Channel]
    reading: Reading
    log_times: list[int] = field(default_factory=list)
    stamps: list[int | None] = field(default_factory=list)
    values: list[tuple] = field(default_factory=list)
    units: list[str | None] = field(default_factory=list)
    rejected: Counter = field(default_factory=Counter)

    def add(self, log_time: int, stamp: int | None, values: tuple, unit: str | None) -> None:
        """Append one sample."""
        self.log_times.append(log_time)
        self.stamps.append(stamp)
        self.values.append(values)
        self.units.append(unit)


def _decoded_messages(path: Path, channels: Sequence[Channel], decoder_for: DecoderFor, rejected: Counter):
    """(log_time, decoded message) of every message of the channels; undecodable ones are counted."""
    for channel in channels:
        decode = decoder_for(path, channel)
        for log_time, payload in channel.messages:
            try:
                yield log_time, decode(payload)
            except Exception as err:   # third-party decoder on bytes from the file: count, never crash
                rejected[f"undecodable ({type(err).__name__})"] += 1


def decode(path: Path, channels: Sequence[Channel], reading: Reading, decoder_for: DecoderFor) -> Decoded:
    """The samples of a single-body topic.

    Raises
    ------
    IngestError
        None of the messages is usable (the reasons are counted in the message).
    """
    decoded = Decoded(channels, reading)
    assert reading.extract is not None
    for log_time, message in _decoded_messages(path, channels, decoder_for, decoded.rejected):
        try:
            stamp, values, unit = reading.extract(message)
        except Rejected as reason:
            decoded.rejected[str(reason)] += 1
            continue
        except Exception as err:   # a decoded message without the fields its type promises
            decoded.rejected[f"undecodable ({type(err).__name__})"] += 1
            continue
        decoded.add(log_time, stamp, values, unit)
    require_samples(path, decoded)
    return decoded


def split_bodies(path: Path, channels: Sequence[Channel], reading: Reading,
                 decoder_for: DecoderFor) -> dict[str, Decoded]:
    """The samples of a multi-body topic, per body name (sorted); messages or entries that cannot be read are
    counted in every body's `rejected`."""
    assert reading.split is not None
    rejected: Counter = Counter()
    bodies: dict[str, Decoded] = defaultdict(lambda: Decoded(channels, reading, rejected=rejected))
    for log_time, message in _decoded_messages(path, channels, decoder_for, rejected):
        try:
            entries = reading.split(message)
        except Exception as err:   # a decoded message without the fields its type promises
            rejected[f"undecodable ({type(err).__name__})"] += 1
            continue
        for name, stamp, values in entries:
            bodies[name].add(log_time, stamp, values, None)
    return dict(sorted(bodies.items()))


def require_samples(path: Path, decoded: Decoded, label: str | None = None) -> None:
    """IngestError when a stream has no sample at all."""
    if not decoded.values:
        reasons = "; ".join(f"{n} {why}" for why, n in decoded.rejected.most_common()) or "no messages kept"
        total = sum(len(c.messages) for c in decoded.channels)
        raise IngestError(path, f"topic {label or decoded.channels[0].topic}: none of its {total} messages is "
                                f"usable ({reasons})")
