"""NanoBench CSV (Vicon + Crazyflie onboard logs on one 10 ms host grid) -> canonical Flight (`read`).

The recorder resampled every onboard stream onto the Vicon time stamps by *linear interpolation*: radio
dropouts show up as rows lying exactly on a straight line between their neighbours, and a stream that
stopped early is extrapolated linearly to the end of the file (B2_circle_medium_rep3: the IMU stops at
31 s and is extended to 20 g).  Such rows are not measurements; they are dropped per stream here and
`build_flight` interpolates the honest samples again (losslessly inside a gap, and without inventing a
tail).  Units and the cut into the flying part are handled by `ingest.align.build_flight`.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ... import units
from ...align import FLYING_HEIGHT_M, build_flight, samples_per_second, stream_timing
from ...flight import Flight, IngestError, existing_file, json_compatible, sha256_file
from ...frames import GRAVITY
from ...limits import MAX_ROOM_M, QUATERNION_NORM_TOLERANCE
from ...sidecar import SidecarTooLarge, read_sidecar

MOCAP_COLUMNS = ("px", "py", "pz", "qx", "qy", "qz", "qw")
ACC_COLUMNS = ("imu_acc_x", "imu_acc_y", "imu_acc_z")
REQUIRED_COLUMNS = ("t",) + MOCAP_COLUMNS + ACC_COLUMNS

# Optional canonical channels and the NanoBench columns that carry them.
OPTIONAL_STREAMS = {
    "gyro": ("imu_gyro_x", "imu_gyro_y", "imu_gyro_z"),
    "motors": ("motor_motor_m1", "motor_motor_m2", "motor_motor_m3", "motor_motor_m4"),
    "vbat": ("pwr_pm_vbat",),
    "thrust_cmd": ("pid_controller_cmd_thrust",),   # firmware units 0..65535 (before battery compensation)
    "setpoint": ("sp_ctrltarget_x", "sp_ctrltarget_y", "sp_ctrltarget_z"),
    "p_onboard": ("est_stateEstimate_x", "est_stateEstimate_y", "est_stateEstimate_z"),
    "v_onboard": ("est_stateEstimate_vx", "est_stateEstimate_vy", "est_stateEstimate_vz"),
    "acc_onboard": ("est_stateEstimate_ax", "est_stateEstimate_ay", "est_stateEstimate_az"),   # g -> m/s²
    "quat_onboard": ("att_stateEstimate_qx", "att_stateEstimate_qy", "att_stateEstimate_qz", "att_stateEstimate_qw"),
    "attitude_cmd": ("pid_controller_roll", "pid_controller_pitch", "pid_controller_yaw"),      # deg
    "yaw_setpoint": ("sp_ctrltarget_yaw",),                                                    # deg
}
# Columns kept in their own unit but logged in another: converted after cleaning (ingest.units).
CONVERTED_STREAMS = {"acc_onboard": units.standard_gravities}
# Columns not kept: derived from the Vicon pose by the recorder (roll/pitch/yaw, vx..vz, wx..wz_vicon: the
# Flight has the pose itself), or the onboard estimate's roll/pitch/yaw (its quaternion is kept).

# Sensor streams whose noise makes an exact repeat of a whole row impossible: a repeat is a stale value
# held by the logger.  (Motors, setpoints, battery can legitimately stay constant, e.g. 0 on the ground.)
NOISY_STREAMS = ("mocap", "acc", "gyro")

# The CSV prints 9 decimals, so a row the recorder interpolated lies on the line through its neighbours to
# ~1e-9; measured sensor rows in NanoBench deviate from it by >= 1e-7.  (Relative part: large PWM values.)
FILLED_ABS_TOL = 1e-8
FILLED_REL_TOL = 1e-12

# A Vicon volume is a room (< 20 m across); a median |p| beyond that means the file is in millimetres.
# No quadrotor sustains > 4 g of specific force for most of a flight; a median |acc| above that is m/s²
# (≈ 9.8) rather than g (≈ 1).
MAX_PLAUSIBLE_MEDIAN_ACC_G = 4.0
# Mocap attitude must be a unit quaternion; exporters write zeros when the object is lost.

# A recording whose time span needs more than 20 grid points per row is > 95 % interpolation (or its t
# is not in seconds, e.g. milliseconds); refusing it also bounds the memory of the resampled grid.
MAX_GRID_POINTS_PER_ROW = 20

HEADER_SNIFF_BYTES = 1 << 16


# -- sniffing -------------------------------------------------------------------------------------------
def _header_columns(path) -> list[str]:
    with open(path, "rb") as handle:
        first = handle.read(HEADER_SNIFF_BYTES).split(b"\n", 1)[0]
    return [name.strip() for name in first.decode("utf-8-sig", errors="replace").strip().split(",")]


def missing_columns(path) -> list[str] | None:
    """For a file `sniff` refused: the NanoBench columns its header lacks, when it has most of them (a
    NanoBench CSV with a column missing, not another format); else None."""
    try:
        columns = set(_header_columns(path))
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    missing = [name for name in REQUIRED_COLUMNS if name not in columns]
    return missing if 0 < len(missing) <= len(REQUIRED_COLUMNS) // 2 else None


def sniff(path) -> bool:
    """True when the file's header line carries the NanoBench columns (content, not extension)."""
    try:
        return set(REQUIRED_COLUMNS) <= set(_header_columns(path))
    except OSError:
        return False


# -- parsing --------------------------------------------------------------------------------------------
def _check_file(path: Path) -> list[str]:
    """Fail early on files that cannot be NanoBench; return the header's columns."""
    existing_file(path, "NanoBench CSV")
    try:
        columns = _header_columns(path)
    except OSError as err:
        raise IngestError(path, f"cannot read ({err})") from None
    missing = [name for name in REQUIRED_COLUMNS if name not in columns]
    if missing:
        raise IngestError(path, f"not a NanoBench CSV: missing column(s) {', '.join(missing)}")
    return columns


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as handle:
        handle.seek(-1, 2)
        return handle.read(1) in (b"\n", b"\r")


def _read_table(path: Path, usecols: list[str]) -> pd.DataFrame:
    try:
        table = pd.read_csv(path, usecols=usecols, engine="c", index_col=False, skipinitialspace=True,
                            skip_blank_lines=True, encoding="utf-8")
    except UnicodeDecodeError:
        raise IngestError(path, "not a text file (invalid UTF-8)") from None
    except (pd.errors.ParserError, pd.errors.EmptyDataError, ValueError, OverflowError) as err:
        detail = str(err).strip().splitlines() or [type(err).__name__]
        raise IngestError(path, f"malformed CSV ({detail[-1]})") from None
    if table.empty:
        raise IngestError(path, "too few data rows (0)")
    for column in usecols:
        _require_numeric(path, table, column)
    return table.astype(float)


def _require_numeric(path: Path, table: pd.DataFrame, column: str) -> None:
    values = table[column]
    if pd.api.types.is_bool_dtype(values) or not pd.api.types.is_numeric_dtype(values):
        coerced = pd.to_numeric(values, errors="coerce")
        bad = np.flatnonzero(coerced.isna().to_numpy() & values.notna().to_numpy())
        if bad.size == 0:  # e.g. a column of True/False
            bad = np.array([0])
        raise IngestError(path, f"non-numeric value {values.iloc[bad[0]]!r} in column {column!r} "
                                f"(data row {bad[0] + 1})")


def _drop_truncated_last_row(path: Path, table: pd.DataFrame, warnings: list[str]) -> pd.DataFrame:
    # A file cut off mid-write does not end with a line break; its last row may hold a cut number.
    if len(table) and not _ends_with_newline(path):
        warnings.append("last line has no line end (file truncated?): dropped that row")
        return table.iloc[:-1]
    return table


def _time_column(path: Path, table: pd.DataFrame, rate_hz: float, warnings: list[str]) -> pd.DataFrame:
    finite = np.isfinite(table["t"].to_numpy())
    if not finite.all():
        warnings.append(f"{int((~finite).sum())} row(s) without a time stamp dropped")
        table = table[finite]
    if len(table) < 2:
        raise IngestError(path, f"too few data rows ({len(table)})")
    t = table["t"].to_numpy()
    backwards = np.flatnonzero(np.diff(t) <= 0)
    if backwards.size:
        i = int(backwards[0])
        raise IngestError(path, f"time is not strictly increasing: t={float(t[i + 1]):.15g} s follows "
                                f"t={float(t[i]):.15g} s (data row {i + 2}; {backwards.size} such place(s))")
    grid_points = (t[-1] - t[0]) * rate_hz
    if not grid_points <= MAX_GRID_POINTS_PER_ROW * len(t):
        raise IngestError(path, f"time stamps span {t[-1] - t[0]:.6g} s for only {len(t)} rows "
                                f"(median step {np.median(np.diff(t)):.3g} s): t must be seconds, without "
                                f"breaks in the recording")
    return table


# -- per-stream cleaning: missing, interpolated, extrapolated and stale rows are gaps -------------------
def _on_line_through_neighbours(t: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Rows 1..n-2 that equal the linear interpolation (in time) of the rows either side."""
    flags = np.zeros(len(t), dtype=bool)
    if len(t) < 3:
        return flags
    with np.errstate(invalid="ignore", over="ignore"):  # absurd magnitudes simply do not match
        weight = ((t[1:-1] - t[:-2]) / (t[2:] - t[:-2]))[:, None]
        predicted = values[:-2] + (values[2:] - values[:-2]) * weight
        tolerance = FILLED_ABS_TOL + FILLED_REL_TOL * np.abs(values[1:-1])
        flags[1:-1] = np.all(np.abs(values[1:-1] - predicted) <= tolerance, axis=1)
    return flags


def _extrapolated_ends(flags: np.ndarray, values: np.ndarray) -> np.ndarray:
    """A sloped straight run reaching the first/last row is extrapolation beyond the stream's real
    samples: drop it including the end row.  A flat run there (motors at 0 on the ground) is kept."""
    ends = np.zeros_like(flags)
    n = len(flags)
    if n >= 3 and flags[-2]:
        start = n - 2
        while start > 0 and flags[start - 1]:
            start -= 1
        if np.ptp(values[start - 1:], axis=0).max() > 0:
            ends[start:] = True
    if n >= 3 and flags[1]:
        stop = 1
        while stop < n - 1 and flags[stop + 1]:
            stop += 1
        if np.ptp(values[:stop + 2], axis=0).max() > 0:
            ends[:stop + 1] = True
    return ends


def _stale_repeats(values: np.ndarray) -> np.ndarray:
    repeats = np.zeros(len(values), dtype=bool)
    repeats[1:] = np.all(values[1:] == values[:-1], axis=1)
    return repeats


def clean_stream(name: str, t: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
    """The rows of one stream that are measurements, and counts of what was dropped and why."""
    finite = np.all(np.isfinite(values), axis=1)
    if name == "mocap":  # a lost Vicon object is often written as a zero / non-unit quaternion
        with np.errstate(invalid="ignore", over="ignore"):
            finite &= np.abs(np.linalg.norm(values[:, 3:7], axis=1) - 1.0) <= QUATERNION_NORM_TOLERANCE
    t, values = t[finite], values[finite]
    stale = _stale_repeats(values) if name in NOISY_STREAMS else np.zeros(len(t), dtype=bool)
    t_live, v_live = t[~stale], values[~stale]
    filled = _on_line_through_neighbours(t_live, v_live)
    extrapolated = _extrapolated_ends(filled, v_live)
    keep = ~(filled | extrapolated)
    report = {"rows_missing": int((~finite).sum()), "rows_stale": int(stale.sum()),
              "rows_interpolated": int((filled & ~extrapolated).sum()),
              "rows_extrapolated": int(extrapolated.sum()), "rows_kept": int(keep.sum())}
    return t_live[keep], v_live[keep], report


# -- unit sanity ----------------------------------------------------------------------------------------
def _check_units(path: Path, p: np.ndarray, acc_g: np.ndarray) -> None:
    median_p = float(np.median(np.linalg.norm(p, axis=1))) if len(p) else 0.0
    if median_p > MAX_ROOM_M:
        raise IngestError(path, f"positions look like millimetres (median |p| = {median_p:.4g}, a "
                                f"motion-capture room is < {MAX_ROOM_M:g} m); convert to metres")
    median_acc = float(np.median(np.linalg.norm(acc_g, axis=1))) if len(acc_g) else 1.0
    if median_acc > MAX_PLAUSIBLE_MEDIAN_ACC_G:
        hint = " — looks like m/s² instead of g" if abs(median_acc - GRAVITY) < 0.5 * GRAVITY else ""
        raise IngestError(path, f"accelerometer median |acc| = {median_acc:.4g} is not ≈ 1 g{hint}; "
                                f"imu_acc_* must be in g")


# -- metadata -------------------------------------------------------------------------------------------
def metadata_path(path: Path) -> Path:
    """Where a NanoBench CSV's metadata sidecar is: <stem>_metadata.yaml next to it."""
    return path.with_name(f"{path.stem}_metadata.yaml")


def _read_metadata(path: Path, warnings: list[str]) -> dict | None:
    yaml_path = metadata_path(path)
    if not yaml_path.is_file():
        return None
    try:
        metadata = read_sidecar(yaml_path)
    except SidecarTooLarge:
        raise  # an expansion bomb is refused with the flight, never stored
    except IngestError as err:
        warnings.append(f"{yaml_path.name} {err.problem}: ignored")
        return None
    if not isinstance(metadata, dict):
        warnings.append(f"{yaml_path.name} is not a mapping: ignored")
        return None
    return metadata


# -- public entry ---------------------------------------------------------------------------------------
def read(path, rate_hz: float = 100.0, cut: bool | tuple = True) -> Flight:
    """Parse a NanoBench CSV into a Flight (mocap + accelerometer required, other streams optional)."""
    path = Path(path)
    columns = _check_file(path)
    present = {name: cols for name, cols in OPTIONAL_STREAMS.items() if set(cols) <= set(columns)}
    usecols = list(dict.fromkeys(REQUIRED_COLUMNS + tuple(c for cols in present.values() for c in cols)))
    warnings: list[str] = []

    table = _read_table(path, usecols)
    table = _drop_truncated_last_row(path, table, warnings)
    table = _time_column(path, table, rate_hz, warnings)
    t = table["t"].to_numpy()

    streams = {"mocap": MOCAP_COLUMNS, "acc": ACC_COLUMNS, **present}
    cleaned, reports = {}, {}
    for name, cols in streams.items():
        t_s, v_s, reports[name] = clean_stream(name, t, table[list(cols)].to_numpy())
        if len(t_s) >= 2:
            cleaned[name] = (t_s, CONVERTED_STREAMS[name](v_s) if name in CONVERTED_STREAMS else v_s)
        elif name in ("mocap", "acc"):
            raise IngestError(path, f"{name} stream has {len(t_s)} usable row(s) of {len(t)}")
        else:
            warnings.append(f"{name}: fewer than 2 usable rows, channel left out")

    (t_mocap, mocap), (t_acc, acc) = cleaned.pop("mocap"), cleaned.pop("acc")
    _check_units(path, mocap[:, :3], acc)

    metadata = _read_metadata(path, warnings)
    _truncation(path, len(t), metadata, warnings)
    times = {"mocap": t_mocap, "acc": t_acc, **{name: ts for name, (ts, _) in cleaned.items()}}
    meta = {
        "adapter": "nanobench",
        "sources": _sources(path, metadata),
        "original_rates": {name: _stream_rate(name, ts, metadata, warnings) for name, ts in times.items()},
        "clock_offset_s": None,
        "vehicle": _vehicle(metadata, warnings),
        "nanobench": json_compatible(metadata),
        "streams": {name: {**reports[name], **_span(times.get(name), t[0])} for name in reports},
        "timing": {name: stream_timing(ts) for name, ts in times.items()},
        "warnings": warnings,
    }
    flight = build_flight(path, t_mocap=t_mocap, p=mocap[:, :3], quat=mocap[:, 3:7], t_acc=t_acc,
                          acc_body_g=acc, channels=cleaned, rate_hz=rate_hz, meta=meta, cut=cut)
    flight.meta["gaps"].update(_airborne_gaps(t_mocap, mocap[:, 2], {"mocap": t_mocap, "acc": t_acc}))
    return flight


def _vehicle(metadata: dict | None, warnings: list[str]) -> str | int | None:
    """The metadata's crazyflie_id when it is a name or number; YAML may also give a date, bytes, a list...,
    which the stored (JSON) meta cannot hold and no vehicle is named by: ignored with a warning."""
    vehicle = (metadata or {}).get("crazyflie_id")
    if vehicle is None or (isinstance(vehicle, (str, int)) and not isinstance(vehicle, bool)):
        return vehicle
    warnings.append(f"metadata crazyflie_id = {str(vehicle)[:40]!r} is not a vehicle name: ignored")
    return None


def _sources(path: Path, metadata: dict | None) -> list[dict]:
    sources = [{"path": str(path), "sha256": sha256_file(path)}]
    if metadata is not None:
        sources.append({"path": str(metadata_path(path)), "sha256": sha256_file(metadata_path(path))})
    return sources


# NanoBench metadata counts the rows each onboard log block really delivered (before resampling).
METADATA_ROW_COUNT_KEYS = {"mocap": "vicon", "acc": "imu", "gyro": "imu", "motors": "motor", "vbat": "power",
                           "thrust_cmd": "pid_output",
                           "setpoint": "setpoint", "p_onboard": "estimator", "v_onboard": "estimator"}


MAX_METADATA_ROWS = 1e12   # past any recorder's row count; larger (or a 400-digit int) is not one


def _stream_rate(name: str, t: np.ndarray, metadata: dict | None, warnings: list[str]) -> float | None:
    """The stream's sample rate (Hz) from the time stamps of its measured rows (`ingest.align.samples_per_second`:
    one over the mean of the ordinary steps, gaps left out).  The metadata's row count is not a rate: the radio
    drops packets (a 100 Hz IMU delivering 77 % of its samples is 100 Hz with gaps), and a file cut short holds
    fewer rows than it counts.  A row count that is not a plausible number is ignored with a warning."""
    _row_count(name, metadata, warnings)
    return samples_per_second(t)


def _row_count(name: str, metadata: dict | None, warnings: list[str]) -> int | None:
    """The metadata's row count of a stream when it is a plain number of a plausible size (YAML also gives
    bools, 400-digit ints, inf, NaN: ignored with a warning)."""
    counts = (metadata or {}).get("row_counts")
    count = counts.get(METADATA_ROW_COUNT_KEYS.get(name)) if isinstance(counts, dict) else None
    if isinstance(count, (int, float)) and not isinstance(count, bool) and 1 < count < MAX_METADATA_ROWS:
        return int(count)
    if count is not None:
        problem = (f"metadata row_counts.{METADATA_ROW_COUNT_KEYS.get(name)} = {str(count)[:40]!r} is not a "
                   f"row count: ignored")
        if problem not in warnings:
            warnings.append(problem)
    return None


def _truncation(path: Path, rows: int, metadata: dict | None, warnings: list[str]) -> None:
    """The recorder writes one CSV row per Vicon frame, and its metadata counts them: a file with fewer rows
    than that was cut short (an interrupted copy or download)."""
    counted = _row_count("mocap", metadata, [])
    if counted is not None and rows < counted:
        warnings.append(f"truncated: the file holds {rows} rows, its metadata counts {counted} Vicon frames "
                        f"({counted - rows} missing at the end)")


def _span(ts, t_file_start: float) -> dict:
    """Where a stream's measured rows start and end (s from the file's first row): a stream that ends
    early (radio lost) shortens the usable flight."""
    if ts is None or len(ts) == 0:
        return {"t_first_s": None, "t_last_s": None}
    return {"t_first_s": float(ts[0] - t_file_start), "t_last_s": float(ts[-1] - t_file_start)}


def _airborne_gaps(t_mocap, z, times: dict) -> dict:
    """Longest time without a measured sample while the vehicle is airborne (mocap z above its resting
    height, as in ingest.align), per stream.  A stream which ends while the vehicle still flies counts
    its whole missing tail as one gap; build_flight cannot see that, it simply ends the grid."""
    rest = np.median(z[t_mocap <= t_mocap[0] + 0.5])
    airborne = np.flatnonzero(z > rest + FLYING_HEIGHT_M)
    start, stop = (t_mocap[airborne[0]], t_mocap[airborne[-1]]) if airborne.size else (t_mocap[0], t_mocap[-1])
    gaps = {}
    for name, ts in times.items():
        inside = ts[(ts > start) & (ts < stop)]
        gaps[f"{name}_longest_gap_airborne_s"] = float(np.max(np.diff(np.r_[start, inside, stop])))
    return gaps
