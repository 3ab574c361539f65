"""A NanoBench CSV writer (for the simulator and the tests): the columns and the printing of the recorder,
so that `reader.read` accepts what it writes."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

from learnest.errors import InvalidInput

from ...flight import json_compatible
from .reader import ACC_COLUMNS, MOCAP_COLUMNS, OPTIONAL_STREAMS, metadata_path

# Optional streams in the column order of the NanoBench files.
WRITE_ORDER = ("gyro", "motors", "p_onboard", "v_onboard", "setpoint", "vbat")


def write(path, t, p, quat_xyzw, acc_body_g, *, gyro=None, motors=None, p_onboard=None, v_onboard=None,
          setpoint=None, vbat=None, metadata: dict | None = None, decimals: int = 9) -> None:
    """A NanoBench CSV that `reader.read` accepts: one row per time stamp t (s; NanoBench uses Unix time), the
    REQUIRED_COLUMNS (p in m, quaternion scalar last, acc in g, body frame), then every optional stream
    given (columns of OPTIONAL_STREAMS, in NanoBench's order, SI units as `read` expects), printed with
    `decimals` decimals like the recorder.  `metadata` is written beside it as <stem>_metadata.yaml."""
    t = np.asarray(t, dtype=float).reshape(-1)
    if len(t) < 2 or not np.all(np.diff(t) > 0):
        raise InvalidInput("t must hold at least 2 strictly increasing time stamps")
    streams = {"mocap": (MOCAP_COLUMNS, np.column_stack([p, quat_xyzw])), "acc": (ACC_COLUMNS, acc_body_g)}
    given = {"gyro": gyro, "motors": motors, "p_onboard": p_onboard, "v_onboard": v_onboard,
             "setpoint": setpoint, "vbat": vbat}
    streams.update({name: (OPTIONAL_STREAMS[name], given[name]) for name in WRITE_ORDER if given[name] is not None})
    header, blocks = ["t"], [t[:, None]]
    for name, (columns, values) in streams.items():
        values = np.asarray(values, dtype=float)
        values = values[:, None] if values.ndim == 1 else values     # a single column (vbat) may be 1-D
        if values.shape != (len(t), len(columns)):
            raise InvalidInput(f"{name}: expected {len(t)} rows of {len(columns)} values, got shape {values.shape}")
        header += list(columns)
        blocks.append(values)
    path = Path(path)
    with open(path, "w", encoding="utf-8", newline="\n") as handle:
        np.savetxt(handle, np.hstack(blocks), fmt=f"%.{decimals}f", delimiter=",", header=",".join(header),
                   comments="")
    if metadata is not None:
        metadata_path(path).write_text(yaml.safe_dump(json_compatible(metadata), sort_keys=True), encoding="utf-8")
