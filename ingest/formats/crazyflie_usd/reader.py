"""`read`: a uSD log as a Flight.  Picks the accelerometer, the mocap pose (locSrv) and the optional
channels from the decoded event streams, drops what is not data (the card's start-up pause, locSrv's
zeros before the first frame, sample-and-hold repeats) and hands them to `ingest.align.build_flight`."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...align import build_flight, position_resolution, resample_quaternions, samples_per_second
from ...flight import Flight, IngestError, sha256_file
from ...limits import MAX_DURATION_S, QUATERNION_NORM_TOLERANCE
from ...sidecar import info_sidecar, vehicle_info
from ..crazyflie_variables import ACC, OPTIONAL_SOURCES
from .decoder import UsdLog, decode, parse_header
from .layout import FIXED_FREQUENCY

SNIFF_BYTES = 1 << 20          # headers are a few kB; a MiB is plenty
POSE = ("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw")
ONBOARD_RPY = ("ctrlLee.rpyx", "ctrlLee.rpyy", "ctrlLee.rpyz")                      # rad, onboard estimate
EDGE_GAP_S = 0.5               # a pause this long in the accelerometer stream splits the recording ...
EDGE_FRAGMENT_S = 1.0          # ... and a piece shorter than this before the first/after the last split is dropped


def sniff(path) -> bool:
    """True when the file's content starts with a parsable uSD header (magic 0xBC, version 1 or 2)."""
    try:
        with open(path, "rb") as handle:
            parse_header(handle.read(SNIFF_BYTES), path)
    except (OSError, IngestError):
        return False
    return True


# -- event streams -> Flight ---------------------------------------------------------------------------------

@dataclass
class _Stream:
    """Some variables of one event stream as float columns."""
    event: str
    t: np.ndarray           # (N,) s
    values: np.ndarray      # (N, k)

    def select(self, mask) -> _Stream:
        return _Stream(self.event, self.t[mask], self.values[mask])

    def within(self, window: tuple[float, float]) -> _Stream:
        return self.select((self.t >= window[0]) & (self.t <= window[1]))


def _find_stream(log: UsdLog, names, prefer_own_event=False) -> _Stream | None:
    """The variables from the first event stream that has them all (for locSrv, a dedicated event stream
    carries the true mocap timestamps, so it beats the sample-and-hold copy in the fixed stream)."""
    candidates = [event for event, columns in log.events.items() if all(name in columns for name in names)]
    if not candidates:
        return None
    candidates.sort(key=lambda event: (len(log.events[event]["t"]) == 0,
                                       prefer_own_event and event == FIXED_FREQUENCY))
    columns = log.events[candidates[0]]
    values = np.column_stack([columns[name].astype(np.float64) for name in names])
    return _usable(_Stream(candidates[0], columns["t"], values))


def _require_stream(log: UsdLog, names, what: str, prefer_own_event=False) -> _Stream:
    stream = _find_stream(log, names, prefer_own_event)
    if stream is None:
        logged = set().union(*(columns.keys() for columns in log.events.values()))
        missing = [name for name in names if name not in logged]
        why = f"missing {', '.join(missing)}" if missing else "they are split across event streams"
        raise IngestError(log.path, f"no {what} in this uSD log: needs {', '.join(names)} "
                                    f"in one event stream ({why})")
    return stream


def _usable(stream: _Stream) -> _Stream:
    """Rows with finite values and a timestamp later than every earlier one (interpolation needs both)."""
    finite = np.all(np.isfinite(stream.values), axis=1)
    later = stream.t > np.maximum.accumulate(np.r_[-np.inf, stream.t[:-1]])
    return stream.select(finite & later)


def _main_window(t: np.ndarray, notes: list[str]) -> tuple[float, float]:
    """Time span of the recording without short pieces split off by a long pause at its start or end.

    The real logs begin with a few records, then ~1.5 s of nothing (the card starting up) while the vehicle
    keeps flying; interpolating across that pause would invent data.  Pauses inside stay (build_flight
    counts them in meta["gaps"]).
    """
    if len(t) < 2:
        return -np.inf, np.inf
    breaks = np.flatnonzero(np.diff(t) > EDGE_GAP_S)
    starts, stops = np.r_[0, breaks + 1], np.r_[breaks, len(t) - 1]
    first, last = 0, len(starts) - 1
    while first < last and t[stops[first]] - t[starts[first]] < EDGE_FRAGMENT_S:
        first += 1
    while last > first and t[stops[last]] - t[starts[last]] < EDGE_FRAGMENT_S:
        last -= 1
    if first > 0:
        notes.append(f"skipped the first {starts[first]} accelerometer records: they precede a "
                     f"{t[starts[first]] - t[stops[first - 1]]:.2f} s pause in the recording")
    if last < len(starts) - 1:
        notes.append(f"skipped the last {len(t) - 1 - stops[last]} accelerometer records: they follow a "
                     f"{t[starts[last + 1]] - t[stops[last]]:.2f} s pause in the recording")
    return float(t[starts[first]]), float(t[stops[last]])


def _distinct_frames(pose: _Stream) -> _Stream:
    """The fixed stream repeats the last mocap pose until the next arrives; keep each frame's first sample
    so that resampling interpolates between true frames instead of following a staircase."""
    if len(pose.t) == 0:
        return pose
    return pose.select(np.r_[True, np.any(np.diff(pose.values, axis=0) != 0, axis=1)])


def _after_first_frame(pose: _Stream) -> _Stream:
    """locSrv reads all zero until the first mocap frame arrives; those zeros are no pose."""
    received = np.flatnonzero(np.any(pose.values != 0, axis=1))
    return pose.select(slice(received[0] if received.size else len(pose.t), None))


def rpy_to_quat(rpy) -> np.ndarray:
    """(N, 3) roll, pitch, yaw in rad (Z-Y-X, the firmware's quat2rpy) -> (N, 4) scalar-last quaternions."""
    from scipy.spatial.transform import Rotation  # scipy.spatial costs ~0.5 s to import: on first use

    return Rotation.from_euler("ZYX", np.asarray(rpy, dtype=float).reshape(-1, 3)[:, ::-1]).as_quat()


def _attitude(log: UsdLog, pose: _Stream, window, notes: list[str]) -> tuple[_Stream, np.ndarray, str]:
    """(pose frames kept, their quaternions, where the attitude came from).

    Position-only mocap (Crazyswarm2 sending extpos, as in the real logs) leaves locSrv's quaternion at
    zero; then the onboard attitude estimate (ctrlLee.rpy*) is interpolated to the mocap frames.
    """
    unit = np.abs(np.linalg.norm(pose.values[:, 3:], axis=1) - 1.0) < QUATERNION_NORM_TOLERANCE
    if unit.any():
        if not unit.all():
            notes.append(f"dropped {int((~unit).sum())} mocap frames whose locSrv quaternion is not unit length")
        kept = pose.select(unit)
        return kept, kept.values[:, 3:], "mocap (locSrv quaternion)"
    onboard = _find_stream(log, ONBOARD_RPY)
    onboard = onboard.within(window) if onboard is not None else None
    if onboard is None or len(onboard.t) < 2:
        raise IngestError(log.path, "locSrv quaternion is zero or invalid in every frame (position-only "
                                    "mocap?) and there is no onboard attitude (ctrlLee.rpyx/y/z) to use instead")
    notes.append("locSrv has no attitude (quaternion all zero: position-only mocap); attitude taken from "
                 "the onboard estimate ctrlLee.rpyx/y/z, interpolated to the mocap frames")
    quat = resample_quaternions(onboard.t, rpy_to_quat(onboard.values), pose.t)
    return pose, quat, "onboard estimate (ctrlLee.rpy), locSrv quaternion is zero"


def _optional_channels(log: UsdLog, window) -> dict:
    channels = {}
    for channel, names, to_si in OPTIONAL_SOURCES:
        stream = None if channel in channels else _find_stream(log, names)
        if stream is not None:
            stream = stream.within(window)
            values = to_si(stream.values)
            values = values.reshape(len(stream.t), -1)
            finite = np.all(np.isfinite(values), axis=1)
            if finite.sum() >= 2:
                channels[channel] = (stream.t[finite], values[finite])
    return channels


def read(path, rate_hz: float = 100.0, cut: bool | tuple = True) -> Flight:
    """A uSD log as a Flight.

    Accelerometer from acc.x/y/z (g, body frame).  Mocap pose from locSrv.* (its own event stream if there
    is one, otherwise the fixed-frequency stream with repeated samples removed).  Attitude from the locSrv
    quaternion, or from the onboard estimate when the quaternion is all zero (position-only mocap; noted in
    meta["usd"]["warnings"] and meta["attitude_source"]).  Optional channels: p_onboard, v_onboard (from
    stateEstimateZ.*, mm -> m), gyro (deg/s -> rad/s), setpoint (ctrltargetZ.*, mm -> m), motors, vbat.
    A crazyswarm2 ``infoNNN.yaml`` next to ``logNNN`` gives meta["mass_kg"], meta["controller"] and the
    whole record (meta["vehicle_info"]).  ``cut`` as `ingest.align.build_flight` takes it.
    """
    log = decode(path)
    notes = list(log.warnings)
    acc = _require_stream(log, ACC, "accelerometer")
    pose = _require_stream(log, POSE, "motion-capture pose", prefer_own_event=True)
    if len(acc.t) < 2:   # e.g. a log that ends after its header: there is no time span to speak of
        raise IngestError(path, f"no samples: the log holds {len(acc.t)} accelerometer record(s) (a header "
                                "without data?)")
    window = _main_window(acc.t, notes)
    if window[1] - window[0] > MAX_DURATION_S:
        raise IngestError(path, f"timestamps span {window[1] - window[0]:.6g} s, more than {MAX_DURATION_S:.0f} s: "
                                f"corrupt timestamps?")
    acc, pose = acc.within(window), pose.within(window)
    pose = _after_first_frame(pose)
    alive = None
    if pose.event == FIXED_FREQUENCY:
        # a repeat of a pose rounded to 1 mm is most often a new frame at the same place: with such a
        # pose, gaps are told from every record (a held pose while the vehicle moves on is "frozen" in
        # ingest.quality); with a finer pose a repeat is a held value, and its stretch a gap
        alive = pose.t if position_resolution(pose.values[:, :3]) > 0 else None
        pose = _distinct_frames(pose)
    if len(pose.t) < 2:
        raise IngestError(path, f"fewer than 2 mocap frames (locSrv) in this uSD log ({len(pose.t)})")
    pose, quat, attitude_source = _attitude(log, pose, window, notes)

    sources = [{"path": str(path), "sha256": sha256_file(path)}]
    info_path = info_sidecar(path)
    info = {}
    if info_path is not None:
        variables = set().union(*(columns.keys() for columns in log.events.values()))
        info = vehicle_info(info_path, variables, notes)
        if info:
            sources.append({"path": str(info_path), "sha256": sha256_file(info_path)})
    meta = {
        "adapter": "usd",
        "sources": sources,
        "original_rates": {"acc": samples_per_second(acc.t), "mocap": samples_per_second(pose.t)},
        "clock_offset_s": None,
        "attitude_source": attitude_source,
        "usd": {"version": log.version, "crc_ok": log.crc_ok, "warnings": notes,
                "records": {event: int(len(columns["t"])) for event, columns in log.events.items()}},
    }
    if info:   # crazyswarm2's infoNNN.yaml: the vehicle's mass and controller
        meta.update(mass_kg=info["mass_kg"], controller=info["controller"], vehicle_info=info["info"])
    return build_flight(path, t_mocap=pose.t, p=pose.values[:, :3], quat=quat, t_acc=acc.t,
                        acc_body_g=acc.values, channels=_optional_channels(log, window), rate_hz=rate_hz,
                        meta=meta, cut=cut, mocap_alive_t=alive)

