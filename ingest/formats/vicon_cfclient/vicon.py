"""A Vicon Nexus/Tracker CSV export (see the package docstring) -> one segment's pose (`ViconTrack`)."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from ...flight import IngestError
from ...limits import MAX_DURATION_S, MAX_ROOM_M
from .csv_text import SNIFF_BYTES, is_blank, is_number, parse_numbers, read_lines, split_cells, string_table

POSE_COLUMNS = ("RX", "RY", "RZ", "TX", "TY", "TZ")
FRAME_COLUMNS = ("Frame", "Sub Frame")
EXPECTED_HEADER = ",".join(FRAME_COLUMNS + POSE_COLUMNS)
POSITION_UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
ROTATION_UNITS = {"rad": 1.0, "deg": np.pi / 180.0}

# Without a units line the magnitude decides: a capture volume is < 20 m across, so a median |p| up to
# 20 is metres; a flight in millimetres sits >= 0.2 m from the origin most of the time (it is airborne,
# z ~ 1000), so 200 or more is millimetres.  In between neither reading is plausible: refuse.
MIN_MEDIAN_MM = 200.0
# A helical rotation vector has norm <= π (some exporters use up to 2π); larger values are degrees.
MAX_ROTVEC_RAD = 2 * np.pi + 1e-6
MAX_CAPTURE_RATE_HZ = 10_000.0     # Vicon cameras top out at a few kHz


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
        """The subject part of `segment` ("subject:segment" -> "subject"; the whole name without a colon)."""
        return self.segment.split(":", 1)[0]


def sniff_vicon(path) -> bool:
    """True when the content looks like a Vicon CSV export: title, capture rate, then a Frame,Sub Frame
    header within the first section's lines (any section type; read_vicon_csv needs segment poses)."""
    try:
        with open(path, "rb") as handle:
            head = handle.read(SNIFF_BYTES).decode("utf-8-sig", errors="replace")
    except OSError:
        return False
    lines = head.replace("\r\n", "\n").replace("\r", "\n").split("\n")
    if len(lines) < 4 or is_blank(lines[0]) or not _positive_number(split_cells(lines[1])[0]):
        return False
    return any(split_cells(line)[:2] == list(FRAME_COLUMNS) for line in lines[2:5])


def _positive_number(text: str) -> bool:
    return is_number(text) and 0 < float(text) < float("inf")


@dataclass
class _Section:
    first_line: int            # 1-based line number of the title
    lines: list

    @property
    def header(self) -> list[str]:
        return split_cells(self.lines[3]) if len(self.lines) > 3 else []

    def pose_columns(self) -> list[int]:
        """Column index of RX for every segment in the header."""
        header = [cell.upper() for cell in self.header]
        if [cell.lower() for cell in header[:2]] != [name.lower() for name in FRAME_COLUMNS]:
            return []
        return [i for i in range(2, len(header) - 5) if tuple(header[i:i + 6]) == POSE_COLUMNS]


def _sections(lines: list[str]) -> list[_Section]:
    sections: list[_Section] = []
    current: list[str] = []
    start = 0
    for number, line in enumerate(lines, start=1):
        if is_blank(line):
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
    found = "; ".join(f"line {s.first_line + 3}: {','.join(s.header)[:80]!r} "
                      f"(section {split_cells(s.lines[0])[0]!r})"
                      for s in sections[:3] if len(s.lines) > 3) or "no section with a header line"
    raise IngestError(path, f"not a Vicon segment export: expected a section of title, capture rate, segment "
                            f"names and the header {EXPECTED_HEADER!r} (helical rotation, translation); "
                            f"found {found}")


def _capture_rate(path: Path, section: _Section) -> float:
    text = split_cells(section.lines[1])[0]
    if not _positive_number(text) or float(text) > MAX_CAPTURE_RATE_HZ:
        raise IngestError(path, f"line {section.first_line + 1}: expected the capture rate in Hz (e.g. 100) "
                                f"after the section title, found {section.lines[1].strip()[:40]!r}")
    return float(text)


def _segment_column(path: Path, section: _Section, segment: str | None) -> tuple[int, str, list[str]]:
    """(column of RX, its subject:segment name, all segment names) for the requested or first segment."""
    names_line = split_cells(section.lines[2])
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
    cells = split_cells(section.lines[4])
    return None if is_number(cells[0]) else cells


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
    from scipy.spatial.transform import Rotation  # scipy.spatial costs ~0.5 s to import: on first use

    path = Path(path)
    lines, ends_with_newline = read_lines(path)
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
        table = string_table(data_lines, [0, 1] + list(range(column, column + 6)))
    except ValueError as err:
        raise IngestError(path, str(err)) from None

    t, frames = _frame_times(path, table, rate, first_data_line, warnings)
    pose = np.column_stack([parse_numbers(path, table[column + j], POSE_COLUMNS[j], first_data_line)
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
    frames = parse_numbers(path, table[0], "Frame", first_line)
    missing = np.flatnonzero(~np.isfinite(frames))
    if missing.size:
        raise IngestError(path, f"line {first_line + missing[0]}: no frame number")
    not_integer = np.flatnonzero((frames != np.round(frames)) | (np.abs(frames) >= 2 ** 53))
    if not_integer.size:
        i = int(not_integer[0])
        raise IngestError(path, f"line {first_line + i}: frame number {table[0].iloc[i]!r} is not an integer")
    sub_frames = np.nan_to_num(parse_numbers(path, table[1], "Sub Frame", first_line), nan=0.0)
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
        raise IngestError(path, f"frames span {t[-1] - t[0]:.6g} s at {rate:g} Hz, more than "
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
