"""`read_pair`: a Vicon export and the cfclient log of the same flight as one Flight on the Vicon clock;
`read_single`: a cfclient log that carries the pose the vehicle received (locSrv.*) as a Flight of its own."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ... import clock
from ...align import build_flight, position_resolution, samples_per_second
from ...flight import Flight, IngestError, sha256_file
from ...limits import QUATERNION_NORM_TOLERANCE
from .cfclient import ONBOARD_QUATERNION, POSE, read_cfclient_csv
from .vicon import read_vicon_csv

# Clock alignment is trusted when the specific forces correlate at least this well (clean flights with
# take-off: > 0.95), no other lag comes within this fraction of the peak (periodic motion), and the bootstrap
# pins the offset to one mocap sample (`clock.ClockAlignment.pins_one_sample`).
MIN_CLOCK_SCORE = 0.5
MAX_RUNNER_UP_RATIO = 0.9
CLOCK_METHODS = {
    "specific-force vector": "cross-correlation of the specific-force vector in the body frame (mocap R(q)ᵀ(p̈ + g) "
                             "vs accelerometer, the three axes summed)",
    "specific-force magnitude": "cross-correlation of |specific force| (mocap p̈ + g vs accelerometer)",
}


def read_single(path, rate_hz: float = 100.0, *, cut: bool | tuple = True) -> Flight:
    """A cfclient "Log to file" CSV with the received mocap pose (locSrv.*) and acc.* as a Flight.

    The pose is what the vehicle received from the motion capture (as in a uSD log): one clock, no
    alignment.  Repeated rows of the pose (the log block samples the last frame received) are dropped;
    rows before the first frame (all zero) too.  Attitude from locSrv.qx..qw, or from the onboard estimate
    stateEstimate.qx..qw when the locSrv quaternion is not logged or zero (position-only mocap).

    Raises
    ------
    IngestError
        Naming the file: no locSrv position, fewer than 2 frames, no usable attitude.
    """
    path = Path(path)
    log = read_cfclient_csv(path)
    pose = log.pose
    if not pose:
        raise IngestError(path, f"a cfclient log without the received mocap pose ({', '.join(POSE[:3])}) needs a "
                                f"Vicon export of the same flight given with it")
    t, values, onboard = pose["t"], pose["values"], pose["onboard_quat"]
    received = np.flatnonzero(np.any(values[:, :3] != 0, axis=1))   # locSrv reads zero until the first frame
    first = received[0] if received.size else len(t)
    t, values = t[first:], values[first:]
    onboard = None if onboard is None else onboard[first:]
    resolution = position_resolution(values[:, :3])
    alive = t if resolution > 0 else None   # see the uSD reader: a rounded pose repeats without a gap
    distinct = np.r_[True, np.any(np.diff(values, axis=0) != 0, axis=1)] if len(t) else np.zeros(0, bool)
    notes = [f"{path.name}: {w}" for w in log.warnings]
    unit = np.abs(np.linalg.norm(values[:, 3:], axis=1) - 1.0) < QUATERNION_NORM_TOLERANCE
    if unit.any():
        keep = distinct & unit
        quat, attitude_source = values[keep, 3:], "mocap (locSrv quaternion)"
    elif onboard is not None and np.any(np.abs(np.linalg.norm(onboard, axis=1) - 1.0) < QUATERNION_NORM_TOLERANCE):
        keep = distinct & (np.abs(np.linalg.norm(onboard, axis=1) - 1.0) < QUATERNION_NORM_TOLERANCE)
        quat, attitude_source = onboard[keep], "onboard estimate (stateEstimate.q*), locSrv quaternion is zero"
        notes.append("locSrv has no attitude (quaternion not logged or zero: position-only mocap); attitude taken "
                     "from the onboard estimate stateEstimate.qx/qy/qz/qw")
    else:
        raise IngestError(path, f"no attitude: locSrv.qx..qw is not logged or not a unit quaternion, and there is "
                                f"no onboard estimate ({', '.join(ONBOARD_QUATERNION)}) to use instead")
    if keep.sum() < 2:
        raise IngestError(path, f"fewer than 2 mocap frames (locSrv) in this cfclient log ({int(keep.sum())})")
    meta = {
        "adapter": "cfclient",
        "sources": [{"path": str(path), "sha256": sha256_file(path)}],
        "original_rates": {"acc": samples_per_second(log.t), "mocap": samples_per_second(t[keep])},
        "clock_offset_s": None,
        "attitude_source": attitude_source,
        "mocap_source": "locSrv: the pose the vehicle received from the motion capture (its clock, radio latency "
                        "included)",
        "cfclient": {"rows": log.rows, "rows_used": int(len(log.t)), "columns": log.columns,
                     "t_first_since_boot_s": float(log.t[0])},
        "warnings": notes,
    }
    return build_flight(path, t_mocap=t[keep], p=values[keep, :3], quat=quat, t_acc=log.t, acc_body_g=log.acc_g,
                        channels=log.channels, rate_hz=rate_hz, meta=meta, cut=cut, mocap_alive_t=alive)


def read_pair(vicon_path, cfclient_path, rate_hz: float = 100.0, *, clock_offset_s: float | None = None,
              max_lag_s: float = clock.DEFAULT_MAX_LAG_S, segment: str | None = None,
              cut: bool | tuple = True,
              accel_lowpass: clock.SensorLowPass | None = clock.CRAZYFLIE_ACCEL_LOWPASS) -> Flight:
    """A Vicon CSV export and the cfclient log of the same flight as one Flight on the Vicon clock.

    clock_offset_s: t_vicon = t_cfclient_s + clock_offset_s (t_cfclient_s = Timestamp / 1000).  None:
    estimated by cross-correlation (ingest.clock), searched within ±max_lag_s of aligning the starts, and
    corrected for the group delay of the accelerometer's own low-pass ``accel_lowpass`` (by default the
    Crazyflie firmware's, 2 poles at 30 Hz on 1 kHz samples, 7.5 ms; None for an unfiltered accelerometer).
    The accelerometer keeps that delay on the Vicon clock: it is the sensor's, not the clocks'.
    """
    vicon_path, cfclient_path = Path(vicon_path), Path(cfclient_path)
    track = read_vicon_csv(vicon_path, segment)
    log = read_cfclient_csv(cfclient_path)
    alignment = None
    if clock_offset_s is None:
        alignment = _estimate_offset(vicon_path, cfclient_path, track, log, max_lag_s, rate_hz, accel_lowpass)
        clock_offset_s = alignment.offset_s
    _require_overlap(vicon_path, cfclient_path, track.t, log.t + clock_offset_s, rate_hz)

    warnings = [f"{vicon_path.name}: {w}" for w in track.warnings]
    warnings += [f"{cfclient_path.name}: {w}" for w in log.warnings]
    clock_issue = _clock_issue(alignment, f"{vicon_path.name} + {cfclient_path.name}", 1.0 / track.rate_hz)
    meta = {
        "adapter": "vicon+cfclient",
        "sources": [{"path": str(vicon_path), "sha256": sha256_file(vicon_path)},
                    {"path": str(cfclient_path), "sha256": sha256_file(cfclient_path)}],
        "original_rates": {"mocap": track.rate_hz, "acc": samples_per_second(log.t)},
        "clock_offset_s": float(clock_offset_s),
        "clock_offset_score": None if alignment is None else alignment.score,
        "clock_offset_uncertainty_s": None if alignment is None else alignment.uncertainty_s,
        "clock_alignment": _clock_meta(alignment),
        "vicon": {"subject": track.subject, "segment": track.segment, "capture_rate_hz": track.rate_hz,
                  "frames": track.frames, "occluded_frames": track.occluded_frames,
                  "missing_frame_numbers": track.missing_frame_numbers, "units": track.units},
        "cfclient": {"rows": log.rows, "rows_used": int(len(log.t)), "columns": log.columns,
                     "t_first_since_boot_s": float(log.t[0])},
        "warnings": warnings + ([clock_issue] if clock_issue else []),
    }
    if clock_issue:
        meta["quality"] = {"ok": False, "issues": [clock_issue]}
    channels = {name: (t + clock_offset_s, values) for name, (t, values) in log.channels.items()}
    return build_flight(vicon_path, t_mocap=track.t, p=track.p, quat=track.quat, t_acc=log.t + clock_offset_s,
                        acc_body_g=log.acc_g, channels=channels, rate_hz=rate_hz, meta=meta, cut=cut)


def _estimate_offset(vicon_path, cfclient_path, track, log, max_lag_s, rate_hz,
                     accel_lowpass: clock.SensorLowPass | None) -> clock.ClockAlignment:
    try:
        return clock.align_mocap_and_accelerometer(track.t, track.p, log.t, log.acc_g, max_lag_s=max_lag_s,
                                                   rate_hz=rate_hz, accel_lowpass=accel_lowpass, quat=track.quat)
    except ValueError as err:  # blame the file whose signal failed; a failed search is the pair's
        if str(err).startswith("mocap"):
            raise IngestError(vicon_path, f"cannot align its clock with {cfclient_path.name}: {err}") from None
        raise IngestError(cfclient_path, f"cannot align its clock with {vicon_path.name}: {err}") from None


def _clock_meta(alignment: clock.ClockAlignment | None) -> dict:
    """``meta["clock_alignment"]``: how the offset was found and the alignment's diagnostics."""
    if alignment is None:
        return {"method": "given"}
    method = CLOCK_METHODS[alignment.signal] + (f" (the magnitude: {alignment.note})" if alignment.note else "")
    method += (", plus the accelerometer low-pass's group delay (sensor_delay_s); uncertainty_s: 1 sigma (half the "
               "central 68 %) over a block bootstrap of 2-s blocks")
    return {"method": method, **alignment.as_meta()}


def _clock_issue(alignment: clock.ClockAlignment | None, pair: str, sample_s: float) -> str | None:
    """Why the estimated offset of the files ``pair`` should not be trusted, or None.  ``sample_s``: the mocap's
    sample interval, s."""
    if alignment is None:
        return None
    what = "specific force" if alignment.signal == "specific-force vector" else "|specific force|"
    if not alignment.score >= MIN_CLOCK_SCORE:
        return (f"clock offset ambiguous ({pair}): mocap and accelerometer {what} correlate only "
                f"{alignment.score:.2f} at the best lag (< {MIN_CLOCK_SCORE:g}) — too little excitation "
                f"(hover?) or the files are not of the same flight")
    if alignment.runner_up > MAX_RUNNER_UP_RATIO * alignment.score:
        return (f"clock offset ambiguous ({pair}): another lag correlates {alignment.runner_up:.2f} vs "
                f"{alignment.score:.2f} at the best (repetitive motion without take-off/landing?)")
    if not alignment.pins_one_sample(sample_s):
        return (f"clock offset not pinned to one mocap sample ({pair}): {1000 * alignment.offset_s:+.1f} ± "
                f"{1000 * alignment.uncertainty_s:.1f} ms (1 sigma, block bootstrap) for a "
                f"{1000 * sample_s:.0f}-ms sample — the motion times the clocks too loosely")
    return None


def _require_overlap(vicon_path: Path, cfclient_path: Path, t_mocap, t_acc, rate_hz: float) -> None:
    if min(t_mocap[-1], t_acc[-1]) - max(t_mocap[0], t_acc[0]) < 2.0 / rate_hz:
        raise IngestError(cfclient_path, f"no overlap with {vicon_path.name} after clock alignment: mocap covers "
                                         f"{t_mocap[0]:.2f}..{t_mocap[-1]:.2f} s, this log "
                                         f"{t_acc[0]:.2f}..{t_acc[-1]:.2f} s on the Vicon clock")

