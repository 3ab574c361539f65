"""Writers of a Vicon segment export and a cfclient log block file (for the simulator and the tests)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from learnest.errors import InvalidInput

from ..crazyflie_variables import ACC
from .vicon import EXPECTED_HEADER


def write_vicon_csv(path, t, p_m, quat_xyzw, rate_hz, occluded_mask=None, subject="cf1", *, units="mm",
                    units_line: bool = True, newline: str = "\n", first_frame: int = 1,
                    marker_section: bool = False) -> None:
    """A Nexus-style segment export of one rigid body.

    t: frame times (s) on the capture grid t[0] + k/rate_hz (frame numbers first_frame + k; gaps allowed);
    p_m in metres, written in `units` (mm or m); quat_xyzw scalar last, written as a helical vector in rad;
    occluded_mask rows are written with blank pose cells.  marker_section appends a marker "Trajectories"
    section after a blank line, as Nexus does, which readers must skip.
    """
    from scipy.spatial.transform import Rotation  # scipy.spatial costs ~0.5 s to import: on first use

    t, p_m, quat = np.asarray(t, float), np.asarray(p_m, float), np.asarray(quat_xyzw, float)
    steps = (t - t[0]) * rate_hz
    frames = first_frame + np.round(steps).astype(np.int64)
    if np.any(np.abs(steps - np.round(steps)) > 1e-3) or np.any(np.diff(frames) <= 0):
        raise InvalidInput("t must be increasing times on the capture grid t[0] + k / rate_hz")
    occluded = np.zeros(len(t), bool) if occluded_mask is None else np.asarray(occluded_mask, bool)
    if units not in ("mm", "m"):
        raise InvalidInput(f"units must be 'mm' or 'm', not {units!r}")
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
        raise InvalidInput("time stamps must increase by at least 1 ms")
    acc = np.asarray(acc_body_g, dtype=float)
    columns = {name: acc[:, j] for j, name in enumerate(ACC)}
    columns.update({name: np.asarray(values, dtype=float).reshape(-1) for name, values in (extra or {}).items()})
    for name, values in columns.items():
        if len(values) != len(t_ms):
            raise InvalidInput(f"{name}: {len(values)} values for {len(t_ms)} time stamps")
    rows = ["Timestamp," + ",".join(columns)]
    rows += [f"{stamp}," + ",".join(repr(float(values[k])) for values in columns.values())
             for k, stamp in enumerate(t_ms)]
    Path(path).write_text("\n".join(rows) + "\n", encoding="utf-8")
