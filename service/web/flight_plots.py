"""The flight page's zoomable channels: position, accelerometer, gyro, velocity, attitude, motors and battery
(those the flight carries), on the log's own time axis, with what the normalized flight left out shaded:

- the take-off and landing the flying-window cut removed (``meta["flying_window"]``);
- a stream which ended before the recording did (``meta["streams"]``: where each stream's measured rows
  end; a NanoBench accelerometer cut off in mid-air ends the grid, so its gap lies after the data);
- stretches inside the kept flight where a stream was interpolated across missing samples (`MIN_GAP_S` or
  longer), found as the quality checks find them (collinear resampled values).
"""
from __future__ import annotations

import numpy as np

from learnest.ingest.align import LANDING_SETTLE_S
from learnest.ingest.baseline import sg_references
from learnest.ingest.flight import Flight
from learnest.ingest.quality import COLLINEAR_RTOL, MAX_GAP_S

from . import zoomable

MIN_GAP_S = 0.1          # interpolated stretches at least this long are shaded (20-ms radio gaps are not)
VELOCITY_SG_S = 0.21     # the velocity row: a short SG derivative of the mocap position (follows fast motion)
STOPPED_TOGETHER_S = 0.5   # streams whose rows end this close together are shaded as one band
CUT_COLOUR, MISSING_COLOUR, GAP_COLOUR = "#999999", "#d62728", "#ff7f0e"
AXIS_COLOURS = ("#1f77b4", "#2ca02c", "#9467bd", "#8c564b")


def euler_deg(quat: np.ndarray) -> np.ndarray:
    """Roll, pitch, yaw (ZYX convention, degrees; yaw unwrapped) of scalar-last quaternions, shape (T, 3)."""
    x, y, z, w = np.asarray(quat, float).T
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.unwrap(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
    return np.degrees(np.column_stack([roll, pitch, yaw]))


def interpolated_runs(values: np.ndarray, dt: float, min_s: float = MIN_GAP_S) -> list[tuple[int, int]]:
    """[start, stop) sample ranges of at least ``min_s`` over which a resampled stream is a straight line
    (build_flight interpolates across missing samples; measured data is never collinear to 1e-9)."""
    values = np.asarray(values, dtype=float).reshape(len(values), -1)
    if len(values) < 3:
        return []
    midpoint = 0.5 * (values[:-2] + values[2:])
    tolerance = COLLINEAR_RTOL * np.maximum(1.0, np.abs(values[1:-1]))
    on_line = np.all(np.abs(values[1:-1] - midpoint) <= tolerance, axis=1)
    edges = np.diff(np.r_[0, on_line.astype(int), 0])
    runs = zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True)
    # an interior run [a, b) of on-line samples spans the samples a .. b + 1 of the series (its two ends measured)
    return [(int(a), int(b) + 2) for a, b in runs if (b - a + 1) * dt >= min_s]


def stream_ends(flight: Flight) -> dict[str, float]:
    """{stream: where its measured rows end, s on the page's axis (the grid's start = 0)} from the adapter's
    ``meta["streams"]`` (NanoBench records them); empty when it recorded none."""
    streams = flight.meta.get("streams") or {}
    spans = {name: s for name, s in streams.items() if isinstance(s, dict) and s.get("t_last_s") is not None}
    if not spans:
        return {}
    # the grid starts where both mocap and accelerometer have begun
    origin = max(float(spans.get(name, {}).get("t_first_s") or 0.0) for name in ("mocap", "acc"))
    return {name: float(s["t_last_s"]) - origin for name, s in spans.items()}


def flight_figure(flight: Flight) -> dict:
    """The zoomable channels of a stored flight, its cut parts and gaps shaded (see the module's text).

    Returns
    -------
    dict
        A `zoomable.figure` spec, one row per channel group; time in s since the log's start (the grid's
        start) when the flight records its flying window, else since the kept flight's start.
    """
    window = flight.meta.get("flying_window") or {}
    offset = float(window.get("start_s") or 0.0)
    t = np.asarray(flight.t) + offset
    dt = flight.dt
    rows: list[tuple[str, list[tuple[str, np.ndarray, str]]]] = []

    def add(label: str, columns: np.ndarray, names: tuple[str, ...], dash: str = "solid") -> None:
        columns = np.asarray(columns, float).reshape(len(t), -1)
        rows.append((label, [(n, columns[:, k], dash) for k, n in enumerate(names)]))

    add("position (m)", flight.p, ("x", "y", "z"))
    if "acc_body" in flight.channels:
        add("accelerometer (m/s²)", flight.channels["acc_body"], ("x", "y", "z"))
    else:
        add("a_meas, world (m/s²)", flight.a_meas, ("x", "y", "z"))
    if "gyro" in flight.channels:
        add("gyro (rad/s)", flight.channels["gyro"], ("x", "y", "z"))
    window_n = max(5, int(round(VELOCITY_SG_S / dt)) | 1)
    if window_n <= len(t):
        add("velocity (m/s)", sg_references(flight.p, dt, window_n)["v"], ("x", "y", "z"))
        if "v_onboard" in flight.channels:
            rows[-1][1].extend((f"{n} onboard", flight.channels["v_onboard"][:, k], "dot")
                               for k, n in enumerate("xyz"))
    add("attitude (deg)", euler_deg(flight.quat), ("roll", "pitch", "yaw"))
    if "motors" in flight.channels:
        add("motors (PWM)", flight.channels["motors"], ("m1", "m2", "m3", "m4"))
    if "vbat" in flight.channels:
        add("battery (V)", flight.channels["vbat"], ("vbat",))

    traces = []
    for r, (_label, lines) in enumerate(rows, start=1):
        for k, (name, values, dash) in enumerate(lines):
            traces.append(zoomable.line(values, name, AXIS_COLOURS[k % len(AXIS_COLOURS)], row=r, width=1.0,
                                        dash=dash, group=f"{r}-{name}", legend=False))
    layout = zoomable.stacked_layout([label for label, _ in rows], row_height=130,
                                     xlabel="t (s) since the log's start" if window else "t (s)")
    notes = _shade_what_is_missing(layout, flight, t, offset, window)
    if notes:
        layout["title"] = {"text": "; ".join(notes), "font": {"size": 12, "color": "#a00"}, "y": 0.995,
                           "yanchor": "top", "yref": "container"}
        layout["margin"]["t"] = 75
    return zoomable.figure(t, traces, layout)


def _shade_what_is_missing(layout: dict, flight: Flight, t: np.ndarray, offset: float, window: dict) -> list[str]:
    """Shade the cut take-off and landing, streams which ended early and gaps inside the flight; returns
    the notes for gaps longer than the quality checks allow."""
    ends = stream_ends(flight)
    end = max([*ends.values(), float(t[-1])]) if ends else float(t[-1]) + (LANDING_SETTLE_S if window else 0.0)
    if window:
        if offset > 0:
            zoomable.shade(layout, 0.0, offset, CUT_COLOUR, "take-off (cut)")
        if end > t[-1]:
            zoomable.shade(layout, float(t[-1]), end, CUT_COLOUR, "landing (cut)")
    layout["xaxis"]["range"] = [0.0 if window else float(t[0]), end]
    notes = []
    gaps = flight.meta.get("gaps") or {}
    early = sorted((stopped, stream) for stream, stopped in ends.items() if stopped < end - 5 * flight.dt)
    while early:   # streams of one radio link stop together: one band names them all
        together = [(s, name) for s, name in early if s < early[0][0] + STOPPED_TOGETHER_S]
        early = early[len(together):]
        names = sorted((name for _, name in together), key=lambda n: (n not in ("mocap", "acc"), n))
        listed = ", ".join(names) if len(names) <= 3 else f"{', '.join(names[:2])} and {len(names) - 2} other streams"
        zoomable.shade(layout, together[0][0], end, MISSING_COLOUR, f"no {listed} samples after {together[0][0]:.1f} s",
                       label_y=0.985 - 0.02 * len(layout["annotations"]))
    streams = {"mocap": flight.p, "acc": flight.channels.get("acc_body", flight.a_meas)}
    for stream, values in streams.items():
        for a, b in interpolated_runs(values, flight.dt):
            zoomable.shade(layout, float(t[a]), float(t[b - 1]), GAP_COLOUR,
                           f"{stream} gap {(b - a - 1) * flight.dt:.2f} s", label_y=0.96)
        longest = float(gaps.get(f"{stream}_longest_gap_airborne_s") or 0.0)
        if longest > MAX_GAP_S:
            notes.append(f"{stream}: {longest:.2f} s without samples while airborne")
    return notes
