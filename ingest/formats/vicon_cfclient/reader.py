"""Vicon Nexus/Tracker CSV export + cfclient CSV log (two files, two clocks, one flight) -> Flight.

Vicon export (one or more sections separated by a blank line; the first *segment pose* section is read):
    Segments                                   section title
    100                                        capture rate, Hz
    ,,cf1:cf1,,,,,                             subject:segment name above its first column
    Frame,Sub Frame,RX,RY,RZ,TX,TY,TZ          global pose of each segment (more segments -> more columns)
    ,,rad,rad,rad,mm,mm,mm                     units (optional): rotation rad|deg, position mm|cm|m
    1,0,0.01,-0.02,1.57,12.3,-45.6,32.1        data; blank pose cells = the segment was occluded
RX/RY/RZ is the helical axis (rotation vector, body -> world), Nexus' default for segments.  Time on the
Vicon clock: (Frame - first frame)/rate (+ Sub Frame/(sub frames per frame · rate), normally 0).

cfclient log (cfclient/utils/logdatawriter.py: one file per log block, one row per log packet):
    Timestamp,acc.x,acc.y,acc.z[,gyro.x,...]   Timestamp: ms since the Crazyflie booted; acc: g, body frame

The clocks share nothing; `ingest.clock` estimates the offset (t_vicon = t_cfclient_s + clock_offset_s)
by cross-correlating the specific-force magnitude seen by both.  An ambiguous alignment (score below
MIN_CLOCK_SCORE or a side lobe nearly as high, e.g. a hover) is reported in meta["warnings"] and
meta["quality"].  Resampling, rotation into the world and the flying-window cut: `ingest.align.build_flight`.
"""
from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from ... import clock
from ...align import build_flight, samples_per_second
from ...flight import Flight, IngestError, existing_file, sha256_file
from ...limits import MAX_ROOM_M
from ..crazyflie_usd.reader import OPTIONAL_SOURCES  # the same firmware log variables, whichever tool logged them

POSE_COLUMNS = ("RX", "RY", "RZ", "TX", "TY", "TZ")
FRAME_COLUMNS = ("Frame", "Sub Frame")
EXPECTED_HEADER = ",".join(FRAME_COLUMNS + POSE_COLUMNS)
POSITION_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
ROTATION_UNITS = {"rad": 1.0, "deg": np.pi / 180.0}
ACC_COLUMNS = ("acc.x", "acc.y", "acc.z")

# Without a units line the magnitude decides: a capture volume is < 20 m across, so a median |p| up to
# 20 is metres; a flight in millimetres sits >= 0.2 m from the origin most of the time (it is airborne,
# z ~ 1000), so 200 or more is millimetres.  In between neither reading is plausible: refuse.
MIN_MEDIAN_MM = 200.0
# A helical rotation vector has norm <= π (some exporters use up to 2π); larger values are degrees.
MAX_ROTVEC_RAD = 2 * np.pi + 1e-6
MAX_CAPTURE_RATE_HZ = 10_000.0     # Vicon cameras top out at a few kHz
MAX_DURATION_S = 3600.0            # a Crazyflie battery lasts minutes; longer means corrupt time stamps
# cfclient logs acc.* in g; a median |acc| above 4 g is m/s² (≈ 9.8) or garbage (as in ingest.nanobench).
MAX_PLAUSIBLE_MEDIAN_ACC_G = 4.0
# Clock alignment is trusted when the specific-force magnitudes correlate at least this well (clean
# flights with take-off: > 0.95) and no other lag comes within this fraction of the peak (periodic motion).
MIN_CLOCK_SCORE = 0.5
MAX_RUNNER_UP_RATIO = 0.9
SNIFF_BYTES = 1 << 16
MAX_COLUMNS = 10_000               # a full-body Nexus export has a few hundred


@dataclass
class ViconTrack:
    """One segment's pose from a Vicon CSV: only the frames where it was seen."""
    t: np.ndarray              # (N,) s on the Vicon clock, 0 at the section's first frame
    p: np.ndarray              # (N, 3) m
    quat: np.ndarray           # (N, 4) scalar last, body -> world
    rate_hz: float             # capture rate from the file
    segment: str               # "subject:segment" as written
    frames: int                # data rows in the section
    occluded_frames: int       # rows with blank (or non-finite) pose cells
    missing_frame_numbers: int  # frame numbers skipped between the first and the last row
    units: dict                # {"position": "mm", "rotation": "rad", "from": "units line" | "magnitude"}
    warnings: list = field(default_factory=list)

    @property
    def subject(self) -> str:
        return self.segment.split(":", 1)[0]


@dataclass
class CfclientLog:
    """A cfclient CSV log on its own clock (seconds since the Crazyflie booted)."""
    t: np.ndarray              # (N,) s
    acc_g: np.ndarray          # (N, 3) g, body frame
    channels: dict             # canonical name -> (t, values in SI), see ingest.usd.OPTIONAL_SOURCES
    rows: int                  # data rows in the file
    columns: list
    warnings: list = field(default_factory=list)


# -- text helpers ---------------------------------------------------------------------------------------
def _read_lines(path: Path) -> tuple[list[str], bool]:
    """The file's lines (CRLF, CR or LF) and whether it ends with a line break."""
    existing_file(path, "CSV log")
    try:
        data = path.read_bytes()
    except OSError as err:
        raise IngestError(path, f"cannot read ({err.strerror or err})") from None
    # Names may be in a Windows code page; numbers are ASCII either way, so undecodable bytes just become �.
    text = data.decode("utf-8-sig", errors="replace").replace("\r\n", "\n").replace("\r", "\n")
    ends_with_newline = text.endswith("\n")
    lines = text.split("\n")[:-1] if ends_with_newline else text.split("\n")
    if all(_is_blank(line) for line in lines):
        raise IngestError(path, "empty file" + (" (only blank lines)" if data.strip() else ""))
    return lines, ends_with_newline


def _cells(line: str) -> list[str]:
    return [cell.strip().strip('"').strip() for cell in line.split(",")]


def _is_blank(line: str) -> bool:
    return not line.replace(",", "").strip()


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _string_table(lines: list[str], usecols: list[int]) -> pd.DataFrame:
    """Cells as stripped strings, one row per line (so row i is lines[i]); short rows padded with ""."""
    n_fields = max(max(line.count(",") for line in lines) + 1, max(usecols) + 1)
    if n_fields > MAX_COLUMNS:
        raise ValueError(f"{n_fields} columns in a row: not a log export")
    try:
        table = pd.read_csv(io.StringIO("\n".join(lines) + "\n"), header=None, names=range(n_fields),
                            usecols=usecols, dtype=str, na_filter=False, quoting=csv.QUOTE_NONE,
                            skip_blank_lines=False, engine="c")
    except (pd.errors.ParserError, pd.errors.EmptyDataError, ValueError, OverflowError) as err:
        raise ValueError(f"malformed CSV ({(str(err).strip().splitlines() or [type(err).__name__])[-1]})") from None
    if len(table) != len(lines):  # cannot happen with QUOTE_NONE and blank lines kept; guards line numbers
        raise ValueError(f"malformed CSV ({len(table)} rows parsed from {len(lines)} lines)")
    return table.fillna("").apply(lambda column: column.str.strip())


def _numbers(path: Path, cells: pd.Series, what: str, first_line: int) -> np.ndarray:
    """Floats from string cells; blank -> NaN; anything else that is not a number -> IngestError."""
    values = pd.to_numeric(cells.replace("", "nan"), errors="coerce").to_numpy(dtype=float)
    bad = np.flatnonzero(np.isnan(values) & (cells != "").to_numpy() & (cells.str.lower() != "nan").to_numpy())
    if bad.size:
        raise IngestError(path, f"line {first_line + bad[0]}: non-numeric value {cells.iloc[bad[0]]!r} in "
                                f"column {what} ({bad.size} such cell(s))")
    return values


# -- Vicon CSV ------------------------------------------------------------------------------------------
def sniff_vicon(path) -> bool:
    """True when the content looks like a Vicon CSV export: title, capture rate, then a Frame,Sub Frame
    header within the first section's lines (any section type; read_vicon_csv needs segment poses)."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(SNIFF_BYTES).decode("utf-8-sig", errors="replace")
    except OSError:
        return False
    lines = head.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if len(lines) < 4 or _is_blank(lines[0]) or not _positive_number(_cells(lines[1])[0]):
        return False
    return any(_cells(line)[:2] == list(FRAME_COLUMNS) for line in lines[2:5])


def _positive_number(text: str) -> bool:
    return _is_number(text) and 0 < float(text) < float("inf")


@dataclass
class _Section:
    first_line: int            # 1-based line number of the title
    lines: list

    @property
    def header(self) -> list[str]:
        return _cells(self.lines[3]) if len(self.lines) > 3 else []

    def pose_columns(self) -> list[int]:
        """Column index of RX for every segment in the header."""
        header = [cell.upper() for cell in self.header]
        if [cell.lower() for cell in header[:2]] != [name.lower() for name in FRAME_COLUMNS]:
            return []
        return [i for i in range(2, len(header) - 5) if tuple(header[i:i + 6]) == POSE_COLUMNS]


def _sections(lines: list[str]) -> list[_Section]:
    sections, current, start = [], [], 0
    for number, line in enumerate(lines, start=1):
        if _is_blank(line):
            if current:
                sections.append(_Section(start, current))
            current = []
        else:
            start = number if not current else start
            current.append(line)
    if current:
        sections.append(_Section(start, current))
    return sections


def _pose_section(path: Path, lines: list[str]) -> _Section:
    sections = _sections(lines)
    for section in sections:
        if section.pose_columns():
            return section
    found = "; ".join(f"line {s.first_line + 3}: {','.join(s.header)[:80]!r} (section {_cells(s.lines[0])[0]!r})"
                      for s in sections[:3] if len(s.lines) > 3) or "no section with a header line"
    raise IngestError(path, f"not a Vicon segment export: expected a section of title, capture rate, segment "
                            f"names and the header {EXPECTED_HEADER!r} (helical rotation, translation); "
                            f"found {found}")


def _capture_rate(path: Path, section: _Section) -> float:
    text = _cells(section.lines[1])[0]
    if not _positive_number(text) or float(text) > MAX_CAPTURE_RATE_HZ:
        raise IngestError(path, f"line {section.first_line + 1}: expected the capture rate in Hz (e.g. 100) "
                                f"after the section title, found {section.lines[1].strip()[:40]!r}")
    return float(text)


def _segment_column(path: Path, section: _Section, segment: str | None) -> tuple[int, str, list[str]]:
    """(column of RX, its subject:segment name, all segment names) for the requested or first segment."""
    names_line = _cells(section.lines[2])
    columns = section.pose_columns()
    names = [names_line[i] if i < len(names_line) and names_line[i] else f"segment {k + 1}"
             for k, i in enumerate(columns)]
    if segment is None:
        return columns[0], names[0], names
    for column, name in zip(columns, names):
        if segment in (name, name.split(":", 1)[0]):
            return column, name, names
    raise IngestError(path, f"no segment {segment!r} in this export (segments: {', '.join(names)})")


def _units_line(section: _Section) -> list[str] | None:
    """The units line's cells, or None when the data follow the header directly."""
    if len(section.lines) < 5:
        return None
    cells = _cells(section.lines[4])
    return None if _is_number(cells[0]) else cells


def _unit_of(path: Path, section: _Section, cells: list[str], columns: range, known: dict, kind: str):
    found = {cells[i].lower() if i < len(cells) else "" for i in columns}
    if found == {""}:
        return None   # a units line without units for this segment: decide by magnitude
    if len(found) != 1 or not found <= set(known):
        raise IngestError(path, f"line {section.first_line + 4}: {kind} units {sorted(found)} not understood "
                                f"(expected one of {', '.join(known)})")
    return found.pop()


def read_vicon_csv(path, segment: str | None = None) -> ViconTrack:
    """Parse a Vicon Nexus/Tracker CSV export: the first segment-pose section, the requested (default:
    first) segment.  Occluded frames are left out (they are gaps, not data) and counted."""
    path = Path(path)
    lines, ends_with_newline = _read_lines(path)
    section = _pose_section(path, lines)
    warnings: list[str] = []
    rate = _capture_rate(path, section)
    column, name, names = _segment_column(path, section, segment)
    if len(names) > 1:
        warnings.append(f"export holds {len(names)} segments ({', '.join(names)}); read {name!r}")
    units = _units_line(section)
    data_offset = 5 if units is not None else 4
    data_lines = section.lines[data_offset:]
    first_data_line = section.first_line + data_offset
    if data_lines and not ends_with_newline and first_data_line + len(data_lines) - 1 == len(lines):
        # A file cut off mid-write: its last row may hold a cut number.
        warnings.append("last line has no line end (file truncated?): dropped that row")
        data_lines = data_lines[:-1]
    if not data_lines:
        raise IngestError(path, f"no data rows after the header (line {section.first_line + 3})")
    try:
        table = _string_table(data_lines, [0, 1] + list(range(column, column + 6)))
    except ValueError as err:
        raise IngestError(path, str(err)) from None

    t, frames = _frame_times(path, table, rate, first_data_line, warnings)
    pose = np.column_stack([_numbers(path, table[column + j], POSE_COLUMNS[j], first_data_line)
                            for j in range(6)])
    seen = np.all(np.isfinite(pose), axis=1)
    partly = int(np.sum(~seen & np.any(np.isfinite(pose), axis=1)))
    if partly:
        warnings.append(f"{partly} row(s) with only some pose cells filled: treated as occluded")
    if seen.sum() < 2:
        what = f"all {len(seen)} frames" if not seen.any() else f"{int((~seen).sum())} of {len(seen)} frames"
        raise IngestError(path, f"{what} occluded: segment {name!r} has {int(seen.sum())} frame(s) with a pose")

    rotvec, position, unit_info = _to_si(path, section, units, column, pose[seen], warnings)
    quat = Rotation.from_rotvec(rotvec).as_quat()   # scalar last
    return ViconTrack(t=t[seen], p=position, quat=quat, rate_hz=rate, segment=name, frames=len(seen),
                      occluded_frames=int((~seen).sum()),
                      missing_frame_numbers=int(frames[-1] - frames[0] + 1 - len(frames)),
                      units=unit_info, warnings=warnings)


def _frame_times(path: Path, table: pd.DataFrame, rate: float, first_line: int, warnings: list[str]):
    """(time of each row in s, frame numbers); frames must be integers and strictly increasing."""
    frames = _numbers(path, table[0], "Frame", first_line)
    missing = np.flatnonzero(~np.isfinite(frames))
    if missing.size:
        raise IngestError(path, f"line {first_line + missing[0]}: no frame number")
    not_integer = np.flatnonzero((frames != np.round(frames)) | (np.abs(frames) >= 2 ** 53))
    if not_integer.size:
        i = int(not_integer[0])
        raise IngestError(path, f"line {first_line + i}: frame number {table[0].iloc[i]!r} is not an integer")
    sub_frames = np.nan_to_num(_numbers(path, table[1], "Sub Frame", first_line), nan=0.0)
    per_frame = 1.0
    if np.any(sub_frames != 0):
        per_frame = float(np.max(sub_frames)) + 1.0
        if not (np.all(sub_frames >= 0) and np.all(sub_frames == np.round(sub_frames)) and per_frame <= 1000):
            raise IngestError(path, "Sub Frame values must be small non-negative integers")
        warnings.append(f"non-zero sub frames: assumed {per_frame:g} sub frames per frame")
    t = (frames - frames[0]) / rate + sub_frames / (per_frame * rate)
    backwards = np.flatnonzero(np.diff(t) <= 0)
    if backwards.size:
        i = int(backwards[0]) + 1
        raise IngestError(path, f"line {first_line + i}: frame {table[0].iloc[i]} does not follow frame "
                                f"{table[0].iloc[i - 1]} (frames must increase)")
    if t[-1] - t[0] > MAX_DURATION_S:
        raise IngestError(path, f"frames span {t[-1] - t[0]:.0f} s at {rate:g} Hz, more than "
                                f"{MAX_DURATION_S:.0f} s: wrong capture rate or frame numbers?")
    return t, frames


def _to_si(path: Path, section: _Section, units: list[str] | None, column: int, pose: np.ndarray,
           warnings: list[str]) -> tuple[np.ndarray, np.ndarray, dict]:
    """(rotation vectors in rad, positions in m, the units and how they were decided)."""
    rotation_unit = position_unit = None
    if units is not None:
        rotation_unit = _unit_of(path, section, units, range(column, column + 3), ROTATION_UNITS, "rotation")
        position_unit = _unit_of(path, section, units, range(column + 3, column + 6), POSITION_UNITS, "position")
    with np.errstate(over="ignore"):   # absurd magnitudes become inf and are refused below
        median_p = float(np.median(np.linalg.norm(pose[:, 3:], axis=1)))
        rotvec_norm = np.linalg.norm(pose[:, :3], axis=1)
    decided = "units line"
    if position_unit is None:
        position_unit, decided = _position_unit_by_magnitude(path, median_p), "magnitude"
        warnings.append(f"no position units in the file: assumed {position_unit} (median |p| = {median_p:.4g})")
    if rotation_unit is None:
        rotation_unit = "deg" if np.max(rotvec_norm) > MAX_ROTVEC_RAD else "rad"
        warnings.append(f"no rotation units in the file: assumed {rotation_unit} "
                        f"(largest rotation vector norm {np.max(rotvec_norm):.4g})")
    rotvec = pose[:, :3] * ROTATION_UNITS[rotation_unit]
    position = pose[:, 3:] * POSITION_UNITS[position_unit]
    with np.errstate(over="ignore"):
        largest = float(np.max(np.linalg.norm(rotvec, axis=1)))
    if largest > MAX_ROTVEC_RAD:
        raise IngestError(path, f"rotation vector of norm {largest:.4g} rad is no helical rotation (expected "
                                f"<= π; rotation units {rotation_unit!r} wrong?)")
    if median_p * POSITION_UNITS[position_unit] > MAX_ROOM_M:
        raise IngestError(path, f"median |p| = {median_p * POSITION_UNITS[position_unit]:.4g} m after reading "
                                f"positions as {position_unit}: not a capture volume (< {MAX_ROOM_M:g} m)")
    return rotvec, position, {"position": position_unit, "rotation": rotation_unit, "from": decided}


def _position_unit_by_magnitude(path: Path, median_p: float) -> str:
    if median_p <= MAX_ROOM_M:
        return "m"
    if MIN_MEDIAN_MM <= median_p <= MAX_ROOM_M * 1000:
        return "mm"
    raise IngestError(path, f"positions without a units line and median |p| = {median_p:.4g}: neither metres "
                            f"(<= {MAX_ROOM_M:g}) nor millimetres of a flight (>= {MIN_MEDIAN_MM:g}); export "
                            f"with the units line (e.g. ',,rad,rad,rad,mm,mm,mm')")


# -- cfclient CSV ---------------------------------------------------------------------------------------
def sniff_cfclient(path) -> bool:
    """True when the first line is a cfclient log header: Timestamp, then group.name variables."""
    try:
        with open(path, "rb") as handle:
            first = handle.read(SNIFF_BYTES).decode("utf-8-sig", errors="replace").splitlines()[:1]
    except OSError:
        return False
    cells = _cells(first[0]) if first else []
    variables = [cell for cell in cells[1:] if cell]
    return bool(cells) and cells[0] == "Timestamp" and bool(variables) and all("." in v for v in variables)


def read_cfclient_csv(path) -> CfclientLog:
    """Parse a cfclient CSV log: Timestamp (ms since boot) and acc.x/y/z (g) required; the optional
    variables of ingest.usd.OPTIONAL_SOURCES become channels (converted to SI)."""
    path = Path(path)
    lines, ends_with_newline = _read_lines(path)
    header = _cells(lines[0])
    missing = [name for name in ("Timestamp",) + ACC_COLUMNS if name not in header]
    if missing:
        raise IngestError(path, f"not a cfclient log: the header must hold Timestamp,{','.join(ACC_COLUMNS)} "
                                f"(missing {', '.join(missing)}; found {','.join(header)[:80]!r})")
    warnings: list[str] = []
    data_lines = lines[1:]
    if data_lines and not ends_with_newline:
        warnings.append("last line has no line end (file truncated?): dropped that row")
        data_lines = data_lines[:-1]
    present = np.array([not _is_blank(line) for line in data_lines], dtype=bool)
    if not present.any():
        raise IngestError(path, "no data rows after the header")
    # Only the variables this adapter uses are parsed: other columns may hold anything.
    wanted = ("Timestamp",) + ACC_COLUMNS + tuple(name for _, names, _ in OPTIONAL_SOURCES for name in names)
    column_of = {name: header.index(name) for name in dict.fromkeys(wanted) if name in header}
    try:
        table = _string_table(data_lines, sorted(set(column_of.values())))
    except ValueError as err:
        raise IngestError(path, str(err)) from None
    numbers = {name: _numbers(path, table[i], name, first_line=2) for name, i in column_of.items()}
    t_ms, acc = numbers["Timestamp"], np.column_stack([numbers[name] for name in ACC_COLUMNS])
    usable = _increasing_finite(t_ms, acc, present, warnings)
    if usable.sum() < 2:
        raise IngestError(path, f"too few rows with a time stamp and acc.x/y/z ({int(usable.sum())})")
    t = t_ms[usable] / 1000.0
    if t[-1] - t[0] > MAX_DURATION_S:
        raise IngestError(path, f"time stamps span {t[-1] - t[0]:.0f} s, more than {MAX_DURATION_S:.0f} s: "
                                f"Timestamp must be milliseconds")
    acc = acc[usable]
    with np.errstate(over="ignore"):   # an absurd 1e308 in one row is inf here, and the median ignores it
        median_acc = float(np.median(np.linalg.norm(acc, axis=1)))
    if median_acc > MAX_PLAUSIBLE_MEDIAN_ACC_G:
        raise IngestError(path, f"median |acc| = {median_acc:.4g} is not ≈ 1 g: acc.x/y/z must be in g")
    return CfclientLog(t=t, acc_g=acc, channels=_cfclient_channels(t_ms / 1000.0, numbers, usable),
                       rows=int(present.sum()), columns=[name for name in header if name], warnings=warnings)


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


# -- the pair -------------------------------------------------------------------------------------------
def read_pair(vicon_path, cfclient_path, rate_hz: float = 100.0, *, clock_offset_s: float | None = None,
              max_lag_s: float = clock.DEFAULT_MAX_LAG_S, segment: str | None = None, cut: bool = True) -> Flight:
    """A Vicon CSV export and the cfclient log of the same flight as one Flight on the Vicon clock.

    clock_offset_s: t_vicon = t_cfclient_s + clock_offset_s (t_cfclient_s = Timestamp / 1000).  None:
    estimated by cross-correlation (ingest.clock), searched within ±max_lag_s of aligning the starts.
    """
    vicon_path, cfclient_path = Path(vicon_path), Path(cfclient_path)
    track = read_vicon_csv(vicon_path, segment)
    log = read_cfclient_csv(cfclient_path)
    alignment = None
    if clock_offset_s is None:
        alignment = _estimate_offset(vicon_path, cfclient_path, track, log, max_lag_s, rate_hz)
        clock_offset_s = alignment.offset_s
    _require_overlap(vicon_path, cfclient_path, track.t, log.t + clock_offset_s, rate_hz)

    warnings = [f"{vicon_path.name}: {w}" for w in track.warnings]
    warnings += [f"{cfclient_path.name}: {w}" for w in log.warnings]
    clock_issue = _clock_issue(alignment)
    meta = {
        "adapter": "vicon+cfclient",
        "sources": [{"path": str(vicon_path), "sha256": sha256_file(vicon_path)},
                    {"path": str(cfclient_path), "sha256": sha256_file(cfclient_path)}],
        "original_rates": {"mocap": track.rate_hz, "acc": samples_per_second(log.t)},
        "clock_offset_s": float(clock_offset_s),
        "clock_offset_score": None if alignment is None else alignment.score,
        "clock_alignment": {"method": "given" if alignment is None else
                            "cross-correlation of |specific force| (mocap p̈ + g vs accelerometer)",
                            **({} if alignment is None else alignment.as_meta())},
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


def _estimate_offset(vicon_path, cfclient_path, track, log, max_lag_s, rate_hz) -> clock.ClockAlignment:
    try:
        return clock.align_mocap_and_accelerometer(track.t, track.p, log.t, log.acc_g, max_lag_s=max_lag_s,
                                                   rate_hz=rate_hz)
    except ValueError as err:  # blame the file whose signal failed; a failed search is the pair's
        if str(err).startswith("mocap"):
            raise IngestError(vicon_path, f"cannot align its clock with {cfclient_path.name}: {err}") from None
        raise IngestError(cfclient_path, f"cannot align its clock with {vicon_path.name}: {err}") from None


def _clock_issue(alignment: clock.ClockAlignment | None) -> str | None:
    """Why the estimated offset should not be trusted, or None."""
    if alignment is None:
        return None
    if not alignment.score >= MIN_CLOCK_SCORE:
        return (f"clock offset ambiguous: mocap and accelerometer |specific force| correlate only "
                f"{alignment.score:.2f} at the best lag (< {MIN_CLOCK_SCORE:g}) — too little excitation "
                f"(hover?) or the files are not of the same flight")
    if alignment.runner_up > MAX_RUNNER_UP_RATIO * alignment.score:
        return (f"clock offset ambiguous: another lag correlates {alignment.runner_up:.2f} vs "
                f"{alignment.score:.2f} at the best (repetitive motion without take-off/landing?)")
    return None


def _require_overlap(vicon_path: Path, cfclient_path: Path, t_mocap, t_acc, rate_hz: float) -> None:
    if min(t_mocap[-1], t_acc[-1]) - max(t_mocap[0], t_acc[0]) < 2.0 / rate_hz:
        raise IngestError(cfclient_path, f"no overlap with {vicon_path.name} after clock alignment: mocap covers "
                                         f"{t_mocap[0]:.2f}..{t_mocap[-1]:.2f} s, this log "
                                         f"{t_acc[0]:.2f}..{t_acc[-1]:.2f} s on the Vicon clock")




# -- writers (simulator and tests) ----------------------------------------------------------------------
def write_vicon_csv(path, t, p_m, quat_xyzw, rate_hz, occluded_mask=None, subject="cf1", *, units="mm",
                    units_line: bool = True, newline: str = "\n", first_frame: int = 1,
                    marker_section: bool = False) -> None:
    """A Nexus-style segment export of one rigid body.

    t: frame times (s) on the capture grid t[0] + k/rate_hz (frame numbers first_frame + k; gaps allowed);
    p_m in metres, written in `units` (mm or m); quat_xyzw scalar last, written as a helical vector in rad;
    occluded_mask rows are written with blank pose cells.  marker_section appends a marker "Trajectories"
    section after a blank line, as Nexus does, which readers must skip.
    """
    t, p_m, quat = np.asarray(t, float), np.asarray(p_m, float), np.asarray(quat_xyzw, float)
    steps = (t - t[0]) * rate_hz
    frames = first_frame + np.round(steps).astype(np.int64)
    if np.any(np.abs(steps - np.round(steps)) > 1e-3) or np.any(np.diff(frames) <= 0):
        raise ValueError("t must be increasing times on the capture grid t[0] + k / rate_hz")
    occluded = np.zeros(len(t), bool) if occluded_mask is None else np.asarray(occluded_mask, bool)
    if units not in ("mm", "m"):
        raise ValueError(f"units must be 'mm' or 'm', not {units!r}")
    scale, digits = (1000.0, 6) if units == "mm" else (1.0, 9)   # both: 1 nm resolution
    rotvec = Rotation.from_quat(quat).as_rotvec()
    name = f"{subject}:{subject}"
    lines = ["Segments", f"{rate_hz:g}", f",,{name},,,,,", EXPECTED_HEADER]
    if units_line:
        lines.append(f",,rad,rad,rad,{units},{units},{units}")
    for k, frame in enumerate(frames):
        if occluded[k]:
            lines.append(f"{frame},0,,,,,,")
        else:
            r, x = rotvec[k], p_m[k] * scale
            lines.append(f"{frame},0,{r[0]:.10f},{r[1]:.10f},{r[2]:.10f},"
                         f"{x[0]:.{digits}f},{x[1]:.{digits}f},{x[2]:.{digits}f}")
    if marker_section:
        lines += ["", "Trajectories", f"{rate_hz:g}", f",,{subject}:m1,,", "Frame,Sub Frame,X,Y,Z", ",,mm,mm,mm"]
        lines += [f"{frame},0,{x[0]:.3f},{x[1]:.3f},{x[2] + 15.0:.3f}" for frame, x in zip(frames, p_m * 1000.0)]
    with open(path, "w", newline="", encoding="utf-8") as handle:
        handle.write(newline.join(lines) + newline)


def write_cfclient_csv(path, t_boot_s, acc_body_g, extra=None) -> None:
    """A cfclient log block file: Timestamp (integer ms since boot, as cfclient writes it), acc.x/y/z in g,
    then the `extra` variables {"group.name": (N,) values} in their firmware units."""
    t_ms = np.round(np.asarray(t_boot_s, dtype=float) * 1000.0).astype(np.int64)
    if np.any(np.diff(t_ms) <= 0):
        raise ValueError("time stamps must increase by at least 1 ms")
    acc = np.asarray(acc_body_g, dtype=float)
    columns = {name: acc[:, j] for j, name in enumerate(ACC_COLUMNS)}
    columns.update({name: np.asarray(values, dtype=float).reshape(-1) for name, values in (extra or {}).items()})
    for name, values in columns.items():
        if len(values) != len(t_ms):
            raise ValueError(f"{name}: {len(values)} values for {len(t_ms)} time stamps")
    rows = ["Timestamp," + ",".join(columns)]
    rows += [f"{stamp}," + ",".join(repr(float(values[k])) for values in columns.values())
             for k, stamp in enumerate(t_ms)]
    Path(path).write_text("\n".join(rows) + "\n", encoding="utf-8")
