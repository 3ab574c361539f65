"""The canonical Flight every adapter produces and every later stage consumes.

Uniform time grid (100 Hz default), SI units, world frame z-up, time in seconds from the flight's start.
`a_meas` is the accelerometer's body-frame specific force rotated into the world by the mocap attitude,
with gravity removed (m/s²).  Quaternions are scalar-last [qx, qy, qz, qw].
"""
from __future__ import annotations

import hashlib
import io
import json
import math
import zipfile
from collections.abc import Iterator, Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, BinaryIO

import numpy as np

from learnest.errors import InvalidInput

if TYPE_CHECKING:
    import pandas as pd

REQUIRED = ("t", "p", "a_meas", "quat")
OPTIONAL = ("gyro", "motors", "vbat", "rotor_speed", "thrust_cmd", "thrust_si", "setpoint", "v_onboard",
            "p_onboard", "acc_body", "quat_onboard", "rpy_onboard", "acc_onboard", "torque_cmd", "attitude_cmd",
            "yaw_setpoint")
# units of every array a Flight may carry (DataFrame export, API, reports); a channel not listed has none.
# Adapters convert to these with the converters of ingest.units.  "motors" is the duty cycle the firmware
# logs (after its battery compensation); "thrust_cmd" the controller's collective command in firmware units.
UNITS = {"t": "s", "p": "m", "a_meas": "m/s^2", "quat": "1", "gyro": "rad/s", "motors": "PWM (0-65535)",
         "vbat": "V", "rotor_speed": "rad/s", "thrust_cmd": "firmware thrust units (0-65535)", "thrust_si": "N",
         "setpoint": "m", "v_onboard": "m/s", "p_onboard": "m", "acc_body": "m/s^2",
         # the onboard estimator's attitude (scalar-last quaternion; Lee controller's roll/pitch/yaw) and
         # acceleration (world frame, gravity removed), the controller's torque and attitude commands
         "quat_onboard": "1", "rpy_onboard": "rad", "acc_onboard": "m/s^2", "torque_cmd": "N m",
         "attitude_cmd": "deg", "yaw_setpoint": "deg"}
_AXES = {3: ("x", "y", "z"), 4: ("x", "y", "z", "w")}


class IngestError(InvalidInput):
    """A file that cannot become a Flight; the message names the file and the problem.

    Attributes
    ----------
    path : str
        The file at fault (or a stand-in such as ``"DataFrame"``).
    problem : str
        What is wrong with it; the message is ``f"{path}: {problem}"``.
    """

    def __init__(self, path: str | Path, problem: str) -> None:
        self.path, self.problem = str(path), problem
        super().__init__(f"{path}: {problem}")


@dataclass
class Flight:
    """One flight on a uniform time grid, in SI units, world frame z-up.

    Parameters
    ----------
    t : ndarray, shape (T,)
        Time, s from the flight's start, uniform.
    p : ndarray, shape (T, 3)
        Mocap position, m, world frame z-up.
    a_meas : ndarray, shape (T, 3)
        Accelerometer specific force rotated into the world by the mocap attitude, gravity removed, m/s².
    quat : ndarray, shape (T, 4)
        Mocap attitude, body to world, scalar-last [qx, qy, qz, qw].
    channels : dict of str to ndarray
        Optional arrays with T rows each (names and units in ``OPTIONAL`` and ``UNITS``: ``gyro`` rad/s,
        ``motors`` PWM, ``vbat`` V, ...).
    meta : dict
        Sources (path, sha256), adapter, original rates, clock offset, ``quality`` {"ok", "issues"}, ``name``.

    Raises
    ------
    InvalidInput
        If an array or channel does not have as many rows as ``t``.

    Examples
    --------
    >>> import learnest as le
    >>> flight = le.read_flights(["sample_logs/circle_rep1.csv"])[0]
    >>> y = flight.measurements()      # (T, 6): p (m), a_meas (m/s²)
    >>> df = flight.to_dataframe()     # and back: le.Flight.from_dataframe(df)
    """

    t: np.ndarray                 # (T,) s from the flight's start, uniform
    p: np.ndarray                 # (T, 3) m, mocap position, world z-up
    a_meas: np.ndarray            # (T, 3) m/s², world frame, gravity removed
    quat: np.ndarray              # (T, 4) mocap attitude, scalar last
    channels: dict = field(default_factory=dict)   # optional arrays, each with T rows (see OPTIONAL)
    meta: dict = field(default_factory=dict)       # sources, adapter, rates, clock offset, quality ...

    def __post_init__(self):
        T = len(self.t)
        for name in ("p", "a_meas", "quat"):
            arr = getattr(self, name)
            if len(arr) != T:
                raise InvalidInput(f"Flight.{name} has {len(arr)} rows but t has {T}")
        for name, arr in self.channels.items():
            if len(arr) != T:
                raise InvalidInput(f"Flight channel {name!r} has {len(arr)} rows but t has {T}")

    @property
    def rate_hz(self) -> float:
        """Sample rate, Hz (``1 / dt``)."""
        return 1.0 / self.dt

    @property
    def dt(self) -> float:
        """Sample period, s: the median step of ``t`` (NaN with fewer than two samples)."""
        return float(np.median(np.diff(self.t))) if len(self.t) > 1 else float("nan")

    @property
    def duration_s(self) -> float:
        """``t[-1] - t[0]``, s (0 for an empty flight)."""
        return float(self.t[-1] - self.t[0]) if len(self.t) else 0.0

    @property
    def name(self) -> str:
        """``meta["name"]``, else the stem of the first source file, else ``"flight"``."""
        return self.meta.get("name") or Path(self.meta.get("sources", [{"path": "flight"}])[0]["path"]).stem

    @property
    def quality(self) -> dict:
        """``meta["quality"]``: ``{"ok": bool, "issues": [str, ...]}`` (ok when never assessed)."""
        return self.meta.get("quality", {"ok": True, "issues": []})

    def measurements(self) -> np.ndarray:
        """y = [p (m), a_meas (m/s²)], shape (T, 6): the quadrotor's measurement vector (Sec. V-C)."""
        return np.column_stack([self.p, self.a_meas])

    def slice(self, start: int, stop: int) -> Flight:
        """Rows [start, stop) as a new Flight, time restarted at zero; ``meta`` is copied (shallowly), without
        ``motor_power_before``: a history of the samples before the record holds for its own first sample only
        (`learnest.models.inputs.slice_keeping_heat` makes a slice's)."""
        t = self.t[start:stop]
        meta = {k: v for k, v in self.meta.items() if k != "motor_power_before"}
        return Flight(t - t[0], self.p[start:stop], self.a_meas[start:stop], self.quat[start:stop],
                      {k: v[start:stop] for k, v in self.channels.items()}, meta)

    def __repr__(self) -> str:
        state = "ok" if self.quality.get("ok", True) else "FAILED quality"
        channels = ", ".join(sorted(self.channels)) or "none"
        return (f"Flight({self.name!r}, {self.duration_s:.1f} s, {len(self.t)} samples at {self.rate_hz:.0f} Hz, "
                f"adapter={self.meta.get('adapter')!r}, channels: {channels}, quality {state})")

    # -- pandas ------------------------------------------------------------------------------------
    def to_dataframe(self) -> pd.DataFrame:
        """The flight as a pandas DataFrame, one row per sample.

        Columns are ``t`` (s) and one column per array axis: ``p_x, p_y, p_z`` (m), ``a_meas_x..z``
        (m/s², world, gravity removed), ``quat_x..w`` and each channel (``gyro_x..z``, ``vbat``,
        ``quat_onboard_x..w``, ...;
        a channel of other width k gives ``name_0..name_{k-1}``: ``motors_0..3`` are m1..m4).
        ``df.attrs`` holds ``units``
        ({column: unit}) and ``meta`` (the flight's metadata), so `from_dataframe` restores the flight.

        Returns
        -------
        pandas.DataFrame, shape (T, 1 + 10 + channel columns)
        """
        import pandas as pd

        columns, units = {"t": self.t}, {"t": UNITS["t"]}
        arrays = {"p": self.p, "a_meas": self.a_meas, "quat": self.quat, **self.channels}
        for name, values in arrays.items():
            for column, series in _split_columns(name, np.asarray(values)).items():
                columns[column] = series
                units[column] = UNITS.get(name, "")
        frame = pd.DataFrame(columns)
        frame.attrs.update(units=units, meta=json.loads(json.dumps(self.meta)),
                           channels={k: (np.asarray(v).shape[1] if np.ndim(v) == 2 else 0)
                                     for k, v in self.channels.items()})
        return frame

    @classmethod
    def from_dataframe(cls, frame: pd.DataFrame, meta: dict | None = None) -> Flight:
        """Rebuild a Flight from `to_dataframe`'s layout (or any frame with those column names).

        Parameters
        ----------
        frame : pandas.DataFrame
            Needs ``t`` (s, uniform), ``p_x..z`` (m), ``a_meas_x..z`` (m/s²) and ``quat_x..w``; other
            column groups ``name_x..``/``name_0..`` or single columns become channels.
        meta : dict, optional
            Metadata; default ``frame.attrs["meta"]``.

        Returns
        -------
        Flight

        Raises
        ------
        IngestError
            If a required column is missing.
        """
        names = list(frame.columns)
        missing = [c for c in ("t", "p_x", "p_y", "p_z", "a_meas_x", "a_meas_y", "a_meas_z",
                               "quat_x", "quat_y", "quat_z", "quat_w") if c not in names]
        if missing:
            raise IngestError("DataFrame", f"missing column(s) {', '.join(missing)}")
        grouped: dict[str, list[str]] = {}
        for column in names:
            if column == "t":
                continue
            base, _, suffix = column.rpartition("_")
            if base and (suffix in ("x", "y", "z", "w") or suffix.isdigit()):
                grouped.setdefault(base, []).append(column)
            else:
                grouped.setdefault(column, []).append(column)
        widths = frame.attrs.get("channels", {})
        arrays = {}
        for name, group in grouped.items():
            values = frame[group].to_numpy(dtype=float)
            arrays[name] = values[:, 0] if len(group) == 1 and widths.get(name, 0) == 0 else values
        core = {k: arrays.pop(k) for k in ("p", "a_meas", "quat")}
        return cls(frame["t"].to_numpy(dtype=float), core["p"], core["a_meas"], core["quat"], arrays,
                   dict(meta if meta is not None else frame.attrs.get("meta", {})))

    # -- persistence: one .npz, arrays exact, metadata as JSON inside --------------------------------
    def to_bytes(self) -> bytes:
        """The flight as a compressed ``.npz``: arrays exact, channels as ``channel__<name>``, meta as JSON."""
        buffer = io.BytesIO()
        # meta first: the member order of the archive (and so the blob's sha) is unchanged
        arrays = {"meta": np.frombuffer(json.dumps(self.meta).encode(), dtype=np.uint8),
                  "t": self.t, "p": self.p, "a_meas": self.a_meas, "quat": self.quat}
        arrays.update({f"channel__{k}": v for k, v in self.channels.items()})
        # allow_pickle=True is numpy's default, given so the stubs do not match **arrays against it
        np.savez_compressed(buffer, allow_pickle=True, **arrays)
        return buffer.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> Flight:
        """Inverse of `to_bytes`."""
        with np.load(io.BytesIO(data), allow_pickle=False) as npz:
            meta = json.loads(npz["meta"].tobytes().decode())
            channels = {k[len("channel__"):]: npz[k] for k in npz.files if k.startswith("channel__")}
            return cls(npz["t"], npz["p"], npz["a_meas"], npz["quat"], channels, meta)

    def save(self, path: str | Path) -> None:
        """Write `to_bytes` to ``path`` atomically (through ``path.tmp`` and a rename)."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(self.to_bytes())
        tmp.replace(path)  # atomic: never a half-written flight on disk

    @classmethod
    def load(cls, path: str | Path) -> Flight:
        """Read a flight written by `save`.

        Raises
        ------
        IngestError
            If the file cannot be read or is not a saved flight.
        """
        try:
            return cls.from_bytes(Path(path).read_bytes())
        except (OSError, ValueError, KeyError) as err:
            raise IngestError(path, f"not a saved learnest flight ({err})") from None



def stored_array_blocks(path: str | Path | BinaryIO, names: Sequence[str], rows: int) -> Iterator[list[np.ndarray]]:
    """Blocks of at most ``rows`` rows of the arrays ``names`` (e.g. "t", "p") of a flight written by
    `Flight.to_bytes` (its path or an open binary file), read from the archive as they are needed: the memory
    of one block, whatever the flight's length (`Flight.from_bytes` holds every array at once).

    Raises
    ------
    ValueError
        If an array is not a plain C-ordered numeric one, or the arrays' lengths differ.
    """
    with zipfile.ZipFile(path) as archive, ExitStack() as stack:
        readers = []
        for name in names:
            handle = stack.enter_context(archive.open(f"{name}.npy"))
            version = np.lib.format.read_magic(handle)
            header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, fortran_order, dtype = header(handle)
            if fortran_order or dtype.hasobject or not shape:
                raise ValueError(f"{name}: not a C-ordered numeric array")
            row_items = int(np.prod(shape[1:], dtype=np.int64))
            readers.append((handle, shape, dtype, row_items * dtype.itemsize))
        length = readers[0][1][0] if readers else 0
        if any(shape[0] != length for _, shape, _, _ in readers):
            raise ValueError(f"arrays {', '.join(names)} differ in length")
        for start in range(0, length, rows):
            count = min(rows, length - start)
            yield [np.frombuffer(handle.read(count * row_bytes), dtype=dtype).reshape(count, *shape[1:])
                   for handle, shape, dtype, row_bytes in readers]


def _split_columns(name: str, values: np.ndarray) -> dict:
    if values.ndim == 1:
        return {name: values}
    # x, y, z for vectors and the quaternion's x, y, z, w; any other width (4 motors, 4 rotor speeds) 0..k-1
    width = values.shape[1]
    quaternion = width == 4 and name.startswith("quat")
    axes = _AXES[width] if width == 3 or quaternion else tuple(str(i) for i in range(width))
    return {f"{name}_{axis}": values[:, i] for i, axis in enumerate(axes)}


def json_compatible(value: Any) -> Any:
    """``value`` with only JSON types: numpy arrays and scalars become lists and numbers, NaN and ±inf
    become None (PostgreSQL's json type rejects them; json.dumps would write them), tuples become lists,
    keys become strings, and anything else (a YAML date, ...) its string.  One definition for flight
    metadata, stored reports and job results."""
    if isinstance(value, dict):
        return {str(k): json_compatible(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_compatible(v) for v in value]
    if hasattr(value, "tolist"):  # numpy array or scalar
        return json_compatible(value.tolist())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if value is None or isinstance(value, (bool, int, str)):
        return value
    return str(value)


def existing_file(path: str | Path, kind: str) -> Path:
    """``path`` as a Path if it is a non-empty regular file; otherwise the IngestError every reader gives.

    Parameters
    ----------
    path : str or Path
    kind : str
        What the file should have been ("NanoBench CSV", "MCAP recording", ...), for the message.

    Raises
    ------
    IngestError
        If ``path`` is a directory, does not exist or is empty.
    """
    path = Path(path)
    if path.is_dir():
        raise IngestError(path, f"is a directory, not a {kind}")
    if not path.is_file():
        raise IngestError(path, "no such file")
    if path.stat().st_size == 0:
        raise IngestError(path, f"empty file, not a {kind}")
    return path


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 digest of a file's bytes, read in 1 MiB chunks."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for chunk in iter(lambda: handle.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()
