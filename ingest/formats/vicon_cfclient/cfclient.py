"""A cfclient CSV log (see the package docstring) -> accelerometer and optional channels on the
Crazyflie's clock (`CfclientLog`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ...flight import IngestError
from ...limits import MAX_DURATION_S
from ..crazyflie_variables import ACC, OPTIONAL_SOURCES
from .csv_text import SNIFF_BYTES, is_blank, parse_numbers, read_lines, split_cells, string_table

# The pose the vehicle received from the mocap (m, scalar-last quaternion), as the firmware logs it: with it a
# cfclient log is a flight of its own (no Vicon export needed).  Without a usable quaternion (position-only
# mocap) the onboard attitude estimate stateEstimate.q* is used.
POSE = ("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw")
ONBOARD_QUATERNION = ("stateEstimate.qx", "stateEstimate.qy", "stateEstimate.qz", "stateEstimate.qw")

# cfclient logs acc.* in g; a median |acc| above 4 g is m/s² (≈ 9.8) or garbage (as in the NanoBench reader).
MAX_PLAUSIBLE_MEDIAN_ACC_G = 4.0


@dataclass
class CfclientLog:
    """A cfclient CSV log on its own clock (seconds since the Crazyflie booted)."""
    t: np.ndarray              # (N,) s
    acc_g: np.ndarray          # (N, 3) g, body frame
    channels: dict             # canonical name -> (t, values in SI), see crazyflie_variables.OPTIONAL_SOURCES
    rows: int                  # data rows in the file
    columns: list
    warnings: list = field(default_factory=list)
    pose: dict = field(default_factory=dict)   # "t" (K,) s, "values" (K, 7) locSrv, "onboard_quat" (K, 4) or None


def has_pose(path) -> bool:
    """True when a cfclient log's header carries the received mocap position (locSrv.x/y/z)."""
    try:
        with open(path, "rb") as handle:
            first = handle.read(SNIFF_BYTES).decode("utf-8-sig", errors="replace").splitlines()[:1]
    except OSError:
        return False
    return bool(first) and set(POSE[:3]) <= set(split_cells(first[0]))


def sniff_cfclient(path) -> bool:
    """True when the first line is a cfclient log header: Timestamp, then group.name variables."""
    try:
        with open(path, "rb") as handle:
            first = handle.read(SNIFF_BYTES).decode("utf-8-sig", errors="replace").splitlines()[:1]
    except OSError:
        return False
    cells = split_cells(first[0]) if first else []
    variables = [cell for cell in cells[1:] if cell]
    return bool(cells) and cells[0] == "Timestamp" and bool(variables) and all("." in v for v in variables)


def read_cfclient_csv(path) -> CfclientLog:
    """Parse a cfclient CSV log: Timestamp (ms since boot) and acc.x/y/z (g) required; the optional
    variables of ingest.formats.crazyflie_variables.OPTIONAL_SOURCES become channels (converted to SI)."""
    path = Path(path)
    lines, ends_with_newline = read_lines(path)
    header = split_cells(lines[0])
    missing = [name for name in ("Timestamp",) + ACC if name not in header]
    if missing:
        raise IngestError(path, f"not a cfclient log: the header must hold Timestamp,{','.join(ACC)} "
                                f"(missing {', '.join(missing)}; found {','.join(header)[:80]!r})")
    warnings: list[str] = []
    data_lines = lines[1:]
    if data_lines and not ends_with_newline:
        warnings.append("last line has no line end (file truncated?): dropped that row")
        data_lines = data_lines[:-1]
    present = np.array([not is_blank(line) for line in data_lines], dtype=bool)
    if not present.any():
        raise IngestError(path, "no data rows after the header")
    # Only the variables this adapter uses are parsed: other columns may hold anything.
    wanted = ("Timestamp",) + ACC + POSE + ONBOARD_QUATERNION + tuple(name for _, names, _ in OPTIONAL_SOURCES
                                                                    for name in names)
    column_of = {name: header.index(name) for name in dict.fromkeys(wanted) if name in header}
    try:
        table = string_table(data_lines, sorted(set(column_of.values())))
    except ValueError as err:
        raise IngestError(path, str(err)) from None
    numbers = {name: parse_numbers(path, table[i], name, first_line=2) for name, i in column_of.items()}
    t_ms, acc = numbers["Timestamp"], np.column_stack([numbers[name] for name in ACC])
    usable = _increasing_finite(t_ms, acc, present, warnings)
    if usable.sum() < 2:
        raise IngestError(path, f"too few rows with a time stamp and acc.x/y/z ({int(usable.sum())})")
    t = t_ms[usable] / 1000.0
    if t[-1] - t[0] > MAX_DURATION_S:
        raise IngestError(path, f"time stamps span {t[-1] - t[0]:.6g} s, more than {MAX_DURATION_S:.0f} s: "
                                f"Timestamp must be milliseconds")
    acc = acc[usable]
    with np.errstate(over="ignore"):   # an absurd 1e308 in one row is inf here, and the median ignores it
        median_acc = float(np.median(np.linalg.norm(acc, axis=1)))
    if median_acc > MAX_PLAUSIBLE_MEDIAN_ACC_G:
        raise IngestError(path, f"median |acc| = {median_acc:.4g} is not ≈ 1 g: acc.x/y/z must be in g")
    return CfclientLog(t=t, acc_g=acc, channels=_cfclient_channels(t_ms / 1000.0, numbers, usable),
                       rows=int(present.sum()), columns=[name for name in header if name], warnings=warnings,
                       pose=_pose(t_ms / 1000.0, numbers, usable))


def _pose(t: np.ndarray, numbers: dict, usable: np.ndarray) -> dict:
    """locSrv rows (position m, quaternion; zero quaternion cells when only x/y/z are logged) and the onboard
    quaternion on the same rows, or {} when the log has no locSrv position."""
    if not all(name in numbers for name in POSE[:3]):
        return {}
    columns = [numbers[name] if name in numbers else np.zeros(len(t)) for name in POSE]
    values = np.column_stack(columns)
    keep = usable & np.all(np.isfinite(values), axis=1)
    onboard = None
    if all(name in numbers for name in ONBOARD_QUATERNION):
        onboard = np.column_stack([numbers[name] for name in ONBOARD_QUATERNION])[keep]
    return {"t": t[keep], "values": values[keep], "onboard_quat": onboard}


def _increasing_finite(t_ms: np.ndarray, acc: np.ndarray, present: np.ndarray, warnings: list[str]) -> np.ndarray:
    """Non-blank rows with a finite time stamp and acceleration, later than every earlier row (cfclient
    stamps each packet with the Crazyflie's sample time; a repeat or step back is not a new sample)."""
    finite = present & np.isfinite(t_ms) & np.all(np.isfinite(acc), axis=1)
    if (present & ~finite).any():
        warnings.append(f"{int((present & ~finite).sum())} row(s) without a time stamp or acc.x/y/z dropped")
    running_max = np.maximum.accumulate(np.where(finite, t_ms, -np.inf))
    later = finite & (t_ms > np.r_[-np.inf, running_max[:-1]])
    if (finite & ~later).any():
        warnings.append(f"{int((finite & ~later).sum())} row(s) whose time stamp does not increase dropped")
    return later


def _cfclient_channels(t: np.ndarray, numbers: dict, usable: np.ndarray) -> dict:
    channels = {}
    for channel, names, to_si in OPTIONAL_SOURCES:
        if channel in channels or not all(name in numbers for name in names):
            continue
        values = to_si(np.column_stack([numbers[name] for name in names]))
        keep = usable & np.all(np.isfinite(values), axis=1)
        if keep.sum() >= 2:
            channels[channel] = (t[keep], values[keep])
    return channels
