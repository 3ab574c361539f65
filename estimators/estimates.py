"""The per-step state estimates of an evaluated flight, kept so results can leave as data.

One `FlightEstimates` holds, on one flight's grid, what every method estimated, the Savitzky–Golay reference
it was scored against and the measurement it was given.  It travels as a compact ``.npz`` (`to_bytes`: the
service stores one blob per flight result) and becomes a tidy table (`to_frame`, `estimates_table`): one row
per (flight, method, sample), columns named with their units (``p_x_m``, ``v_x_m_s``, ``a_x_m_s2``).
"""
from __future__ import annotations

import io
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from learnest.errors import InvalidInput

if TYPE_CHECKING:
    import pandas as pd

# x = [p, v, a] of the flight systems ("quadrotor", "crazyflie"): names, unit suffixes and units
STATE_GROUPS = (("p", "m", "m"), ("v", "m_s", "m/s"), ("a", "m_s2", "m/s^2"))
AXES = ("x", "y", "z")
STATE_COLUMNS = tuple(f"{group}_{axis}_{suffix}" for group, suffix, _ in STATE_GROUPS for axis in AXES)
STATE_UNITS = {f"{group}_{axis}_{suffix}": unit for group, suffix, unit in STATE_GROUPS for axis in AXES}
# y = [p (mocap), a_meas (accelerometer in the world frame, gravity removed)]
MEASUREMENT_STATES = STATE_COLUMNS[0:3] + STATE_COLUMNS[6:9]
REFERENCE_PREFIX, ERROR_PREFIX, MEASUREMENT_PREFIX = "ref_", "err_", "meas_"


def table_units() -> dict[str, str]:
    """{column: unit} of every column of `estimates_table` (``flight``, ``method``: no unit)."""
    units = {"t_s": "s", "t_log_s": "s", "flight_id": "", "flight": "", "method": ""}
    for prefix in ("", REFERENCE_PREFIX, ERROR_PREFIX):
        units.update({prefix + name: unit for name, unit in STATE_UNITS.items()})
    units.update({MEASUREMENT_PREFIX + name: STATE_UNITS[name] for name in MEASUREMENT_STATES})
    return units


@dataclass
class FlightEstimates:
    """Every method's state estimates on one flight, with the reference and the measurement.

    Parameters
    ----------
    flight : str
        The flight's name.
    t : ndarray, shape (T,)
        Time, s from the flight's start (the Flight's grid).
    reference : ndarray, shape (T, 9)
        Savitzky–Golay reference states [p (m), v (m/s), a (m/s²)] the MSE is computed against.
    measurement : ndarray, shape (T, 6)
        What the estimators were given: y = [p (m), a_meas (m/s², world frame, gravity removed)].
    quat : ndarray, shape (T, 4)
        Mocap attitude, scalar-last [qx, qy, qz, qw] (the estimators take the attitude from mocap).
    estimates : dict of str to ndarray, shape (T, 9)
        x̂ = [p, v, a] per method, in the units of ``reference``.
    log_start_ns : int
        Time of t = 0 on the log's own clock, ns (an MCAP recording's log time; the seconds since the
        logger started for CSV and uSD logs), so exports line up with the raw log.
    flight_id, sha256 : int or str, optional
        The stored flight's id and content sha256 (service only).
    """

    flight: str
    t: np.ndarray
    reference: np.ndarray
    measurement: np.ndarray
    quat: np.ndarray
    estimates: dict[str, np.ndarray] = field(default_factory=dict)
    log_start_ns: int = 0
    flight_id: int | None = None
    sha256: str | None = None

    def __post_init__(self) -> None:
        T = len(self.t)
        shapes = {"reference": (T, 9), "measurement": (T, 6), "quat": (T, 4),
                  **{f"estimates[{m!r}]": (T, 9) for m in self.estimates}}
        arrays = {"reference": self.reference, "measurement": self.measurement, "quat": self.quat,
                  **{f"estimates[{m!r}]": v for m, v in self.estimates.items()}}
        for name, shape in shapes.items():
            if np.shape(arrays[name]) != shape:
                raise InvalidInput(f"{self.flight}: {name} has shape {np.shape(arrays[name])}, expected {shape}")

    @property
    def methods(self) -> list[str]:
        """The methods, in the order they were run."""
        return list(self.estimates)

    def log_times_ns(self) -> np.ndarray:
        """Each sample's time on the log's clock, ns (int64): ``log_start_ns + round(t * 1e9)``."""
        return self.log_start_ns + np.round(np.asarray(self.t, float) * 1e9).astype(np.int64)

    # -- storage: one compressed .npz, arrays exact -----------------------------------------------------
    def to_bytes(self) -> bytes:
        """A compressed ``.npz``: the arrays exact (float64), the methods' order and names as JSON."""
        header = {"flight": self.flight, "methods": self.methods, "log_start_ns": int(self.log_start_ns)}
        arrays = {"header": np.frombuffer(json.dumps(header).encode(), dtype=np.uint8), "t": self.t,
                  "reference": self.reference, "measurement": self.measurement, "quat": self.quat}
        arrays.update({f"estimate_{i}": self.estimates[m] for i, m in enumerate(self.methods)})
        buffer = io.BytesIO()
        np.savez_compressed(buffer, allow_pickle=False, **arrays)
        return buffer.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes) -> FlightEstimates:
        """Inverse of `to_bytes`; InvalidInput when the bytes are not stored estimates."""
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                header = json.loads(npz["header"].tobytes().decode())
                estimates = {m: npz[f"estimate_{i}"] for i, m in enumerate(header["methods"])}
                return cls(header["flight"], npz["t"], npz["reference"], npz["measurement"], npz["quat"],
                           estimates, int(header["log_start_ns"]))
        except (OSError, ValueError, KeyError) as err:
            raise InvalidInput(f"stored estimates are unreadable ({type(err).__name__}: {err})") from None

    # -- the tidy table ------------------------------------------------------------------------------------
    def to_frame(self) -> pd.DataFrame:
        """One row per (method, sample): estimate, reference, error (estimate − reference), measurement.

        Returns
        -------
        pandas.DataFrame, shape (len(methods) * T, 5 + 9 + 9 + 9 + 6)
            Columns ``t_s``, ``t_log_s`` (on the log's clock), ``flight_id``, ``flight``, ``method``, the
            estimate ``p_x_m .. a_z_m_s2``, ``ref_*``, ``err_*`` and ``meas_*`` (p and a); ``attrs["units"]``.
        """
        import pandas as pd

        T, methods = len(self.t), self.methods
        frames = []
        t_log = self.log_times_ns() / 1e9
        for method in methods:
            estimate = np.asarray(self.estimates[method], float)
            columns: dict[str, object] = {"t_s": self.t, "t_log_s": t_log,
                                          "flight_id": pd.array([self.flight_id] * T, dtype="Int64"),
                                          "flight": [self.flight] * T, "method": [method] * T}
            columns.update(_named(STATE_COLUMNS, estimate))
            columns.update(_named(STATE_COLUMNS, self.reference, REFERENCE_PREFIX))
            columns.update(_named(STATE_COLUMNS, estimate - self.reference, ERROR_PREFIX))
            columns.update(_named(MEASUREMENT_STATES, self.measurement, MEASUREMENT_PREFIX))
            frames.append(pd.DataFrame(columns))
        frame = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=list(table_units()))
        frame.attrs["units"] = table_units()
        return frame


def _named(names: Sequence[str], values: np.ndarray, prefix: str = "") -> dict[str, np.ndarray]:
    values = np.asarray(values, float)
    return {prefix + name: values[:, i] for i, name in enumerate(names)}


def estimates_table(flights: Sequence[FlightEstimates]) -> pd.DataFrame:
    """The tidy table of several flights (`FlightEstimates.to_frame`, concatenated in order).

    Raises
    ------
    InvalidInput
        If ``flights`` is empty.
    """
    import pandas as pd

    if not flights:
        raise InvalidInput("no estimates to export (no flight was scored)")
    frame = pd.concat([f.to_frame() for f in flights], ignore_index=True)
    frame.attrs["units"] = table_units()
    return frame
