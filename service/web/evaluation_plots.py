"""The evaluation report's zoomable figures, read from the STORED per-step estimates (`FlightEstimates`,
kept per flight result): nothing is run again to draw them.

- `error_figure`: for one state group (p, v or a) of one flight, the running RMS of each method's error,
  estimate − reference per axis, and estimate vs reference per axis: where along the flight a method is
  better or worse.
- `paired_figure`: per flight, prior vs KNODE (UKF → KNODE-UKF, MHE → KNODE-MHE) as two dots in the
  methods' colours joined by a grey line (solid: the KNODE's error is lower, dashed: higher), overall and
  per group, in the table's units (MSE × 1e-3).
- `difference_figure`: KNODE − prior |error| over time, with the mocap gaps shaded when the report has them.
- `reference_clipping`: how much the Savitzky–Golay reference flattens the flight's speed peaks.
"""
from __future__ import annotations

import numpy as np

from learnest.estimators.estimates import FlightEstimates

from . import zoomable

# (key, state columns, unit, long name) of the 9-state flight systems x = [p, v, a]
GROUPS = {"p": (slice(0, 3), "m", "position"), "v": (slice(3, 6), "m/s", "velocity"),
          "a": (slice(6, 9), "m/s²", "acceleration")}
MSE_UNITS = {"overall": "mixed", "p": "m²", "v": "(m/s)²", "a": "(m/s²)²"}
PAIRS = (("ukf", "knode-ukf"), ("mhe", "knode-mhe"))   # (prior-only, KNODE) of the paper's comparison
RMS_WINDOW_S = 1.0
SCALE = 1e3   # the table shows MSE × 1e-3: values are multiplied by this to be read in those units
SHORT_SG_S = 0.21   # the SG window the reference is compared with: keeps 99 % of a 0.5-Hz, 96 % of a 1-Hz swing
PEAK_PERCENTILE = 99
MOVING_SHARE = 0.05   # axes whose peak speed is below this share of the fastest axis' are not compared


def running_rms(errors: np.ndarray, dt: float, window_s: float = RMS_WINDOW_S) -> np.ndarray:
    """RMS of the errors over a centred window (shorter at the ends), averaged over the columns.

    Parameters
    ----------
    errors : ndarray, shape (T, k)
        Estimate − reference, in the group's unit.
    dt : float
        Sample period, s.
    window_s : float
        Window length, s.

    Returns
    -------
    ndarray, shape (T,)
        In the errors' unit; its square averaged over the flight (with full windows) is the group's MSE.
    """
    squared = np.mean(np.asarray(errors, float) ** 2, axis=1)
    half = max(1, int(round(window_s / dt / 2)))
    cumulative = np.concatenate([[0.0], np.cumsum(squared)])
    index = np.arange(len(squared))
    lo, hi = np.maximum(index - half, 0), np.minimum(index + half + 1, len(squared))
    return np.sqrt((cumulative[hi] - cumulative[lo]) / (hi - lo))


def _ordered(methods: list[str]) -> list[str]:
    """Priors first (drawn below), then the KNODE variants."""
    return sorted(methods, key=lambda m: (m.startswith("knode"), m))


def _style(method: str) -> dict:
    knode = method.startswith("knode")
    return {"colour": zoomable.METHOD_COLOURS.get(method, "#7f7f7f"), "width": 1.2 if knode else 2.4}


def error_figure(estimates: FlightEstimates, group: str) -> dict:
    """Running RMS (1 s), error per axis and estimate vs reference per axis of one state group.

    Parameters
    ----------
    estimates : FlightEstimates
        The stored estimates of one flight.
    group : {"p", "v", "a"}

    Returns
    -------
    dict
        A `zoomable.figure` spec with 7 rows sharing the time axis.
    """
    columns, unit, name = GROUPS[group]
    axes = ("x", "y", "z")
    labels = ([f"running RMS ({unit})"] + [f"{group}{a} error ({unit})" for a in axes]
              + [f"{group}{a} ({unit})" for a in axes])
    layout = zoomable.stacked_layout(labels, title=f"{name} of {estimates.flight}: error = estimate − reference")
    dt = float(np.median(np.diff(estimates.t))) if len(estimates.t) > 1 else 1.0
    reference = np.asarray(estimates.reference)[:, columns]
    traces = []
    for method in _ordered(estimates.methods):
        style = _style(method)
        error = np.asarray(estimates.estimates[method])[:, columns] - reference
        traces.append(zoomable.line(running_rms(error, dt), method.upper(), style["colour"], row=1,
                                    width=style["width"], group=method))
        for k in range(3):
            traces.append(zoomable.line(error[:, k], method.upper(), style["colour"], row=2 + k,
                                        width=style["width"], legend=False, group=method))
            traces.append(zoomable.line(error[:, k] + reference[:, k], method.upper(), style["colour"],
                                        row=5 + k, width=style["width"], legend=False, group=method))
    for k in range(3):
        traces.append(zoomable.line(reference[:, k], "SG reference", zoomable.REFERENCE_COLOUR, row=5 + k,
                                    width=1.0, dash="dot", legend=k == 0, group="reference"))
    return zoomable.figure(estimates.t, traces, layout)


def paired_figure(report: dict) -> dict | None:
    """Per scored flight, each (prior, KNODE) pair of `PAIRS` as two dots joined by a line, overall and per
    group, in MSE × 1e-3 (the table's unit); the median as a wide bar.  None without a scored pair."""
    scored = [f for f in report.get("flights", []) if not f.get("excluded") and f.get("mse")]
    pairs = [p for p in PAIRS if any(p[0] in f["mse"] and p[1] in f["mse"] for f in scored)]
    if not pairs:
        return None
    panels = ("overall", "p", "v", "a")
    traces = []
    layout: dict = {"grid": {"rows": 1, "columns": len(panels), "pattern": "independent"}, "height": 380,
                    "margin": {"l": 60, "r": 20, "t": 50, "b": 60}, "showlegend": False, "hovermode": "closest",
                    "annotations": []}
    for c, panel in enumerate(panels, start=1):
        xaxis, yaxis = ("x", "y") if c == 1 else (f"x{c}", f"y{c}")
        ticks, labels = [], []
        for i, (prior, knode) in enumerate(pairs):
            ticks += [2 * i, 2 * i + 1]
            labels += [prior.upper(), knode.upper()]
            values = [(f["flight"], _mse(f, prior, panel), _mse(f, knode, panel)) for f in scored
                      if prior in f["mse"] and knode in f["mse"]]
            for flight, before, after in values:
                better = after < before
                traces.append({"type": "scatter", "mode": "lines+markers", "x": [2 * i, 2 * i + 1],
                               "y": [before * SCALE, after * SCALE], "xaxis": xaxis, "yaxis": yaxis,
                               "name": flight,
                               "line": {"color": "#888", "width": 1, "dash": "solid" if better else "dash"},
                               "marker": {"color": [zoomable.METHOD_COLOURS.get(prior, "#777"),
                                                    zoomable.METHOD_COLOURS.get(knode, "#777")], "size": 7},
                               "text": [flight, flight],
                               "hovertemplate": "%{text}<br>%{y:.4g} × 1e-3<extra></extra>"})
            for k, method in ((0, prior), (1, knode)):
                median = float(np.median([v[1 + k] for v in values])) * SCALE
                traces.append({"type": "scatter", "mode": "lines", "x": [2 * i + k - 0.3, 2 * i + k + 0.3],
                               "y": [median, median], "xaxis": xaxis, "yaxis": yaxis, "name": "median",
                               "line": {"color": zoomable.METHOD_COLOURS.get(method, "#777"), "width": 4},
                               "hovertemplate": f"median {method.upper()}: %{{y:.4g}} × 1e-3<extra></extra>"})
        unit = MSE_UNITS[panel]
        layout["xaxis" if c == 1 else f"xaxis{c}"] = {"tickvals": ticks, "ticktext": labels,
                                                      "range": [-0.5, 2 * len(pairs) - 0.5]}
        layout["yaxis" if c == 1 else f"yaxis{c}"] = {
            "title": {"text": f"MSE × 1e-3 ({unit})" if panel != "overall" else "MSE over [p, v, a] × 1e-3"},
            "rangemode": "tozero"}
        layout["annotations"].append({"text": f"<b>{panel}</b>" if panel == "overall" else f"<b>{GROUPS[panel][2]}</b>",
                                      "xref": f"{xaxis} domain", "yref": "paper", "x": 0.5, "y": 1.02,
                                      "showarrow": False, "yanchor": "bottom"})
    return {"t": [], "data": traces, "layout": layout}


def _mse(entry: dict, method: str, panel: str) -> float:
    return entry["mse"][method] if panel == "overall" else entry["groups"][method][panel]


def reference_clipping(estimates: FlightEstimates, window_used: int) -> dict | None:
    """How much the reference's SG window flattens this flight's fastest motion.

    The mocap position (the measurement kept with the estimates) is differentiated again with a short
    window (`SHORT_SG_S`), and the peak velocity of each axis compared with the reference's.

    Returns
    -------
    dict or None
        ``window_s`` (the reference's window, s), ``short_s`` (the short one, s), and for the axis whose peak
        the reference lowers most: ``axis``, ``peak_reference`` and ``peak_short`` (m/s, the
        `PEAK_PERCENTILE` th percentile of |v|) and ``clipped_pct`` (how much lower the reference's peak
        is, %); None for a flight shorter than the short window.
    """
    from learnest.ingest.baseline import sg_references

    t = np.asarray(estimates.t)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.0
    short = max(5, int(round(SHORT_SG_S / dt)) | 1) if dt > 0 else 0
    if not short or short > len(t):
        return None
    position = np.asarray(estimates.measurement)[:, :3]
    # the 99th percentile: the peak, without the odd spike a short window lets through
    fast = np.percentile(np.abs(sg_references(position, dt, short)["v"]), PEAK_PERCENTILE, axis=0)
    smooth = np.percentile(np.abs(np.asarray(estimates.reference)[:, 3:6]), PEAK_PERCENTILE, axis=0)
    moving = fast > max(MOVING_SHARE * float(fast.max()), 1e-9)   # an axis barely moving has no peak to clip
    clipped = np.where(moving, 1.0 - smooth / np.where(moving, fast, 1.0), -np.inf)
    k = int(np.argmax(clipped))
    if not moving[k]:
        return None
    return {"window_s": window_used * dt, "short_s": short * dt, "axis": "xyz"[k],
            "peak_reference": float(smooth[k]), "peak_short": float(fast[k]), "clipped_pct": 100.0 * clipped[k]}


GAP_START_S = 5.0   # the first mocap gap starts this long after the kept flight's start, unless the report says


def gap_windows(entry: dict | None, t: np.ndarray) -> list[tuple[float, float]]:
    """The mocap gaps of one flight's report entry, [(start, stop)] in s on ``t``'s axis: its
    ``yardsticks.mocap_gaps.windows_s`` when given, else ``gaps`` windows of ``gap_s`` every ``every_s``
    from ``start_s`` (default `GAP_START_S`) after the first sample.  [] without gap information."""
    gaps = ((entry or {}).get("yardsticks") or {}).get("mocap_gaps") or {}
    if gaps.get("windows_s"):
        return [(float(a), float(b)) for a, b in gaps["windows_s"]]
    try:
        length, every, count = float(gaps["gap_s"]), float(gaps["every_s"]), int(gaps["gaps"])
    except (KeyError, TypeError, ValueError):
        return []
    if not len(t) or length <= 0 or every <= 0:
        return []
    first = float(t[0]) + float(gaps.get("start_s", GAP_START_S))
    return [(first + k * every, first + k * every + length) for k in range(count)]


def difference_figure(estimates: FlightEstimates, group: str, gaps: list[tuple[float, float]]) -> dict | None:
    """Where along the flight the KNODE helps: per (prior, KNODE) pair that ran, the KNODE's |error| minus
    its prior's (norm over the group's three axes, in the group's unit; below 0 the KNODE is closer), its
    running mean over `RMS_WINDOW_S`, with the mocap gaps shaded.  None when no pair ran."""
    columns, unit, name = GROUPS[group]
    pairs = [(p, k) for p, k in PAIRS if p in estimates.methods and k in estimates.methods]
    if not pairs:
        return None
    reference = np.asarray(estimates.reference)[:, columns]
    dt = float(np.median(np.diff(estimates.t))) if len(estimates.t) > 1 else 1.0
    half = max(1, int(round(RMS_WINDOW_S / dt / 2)))
    layout = zoomable.stacked_layout([f"|error| KNODE − prior ({unit})"], row_height=260,
                                     title=f"{name} of {estimates.flight}: KNODE − prior error (below 0: the KNODE "
                                           f"is closer{'; shaded: mocap hidden' if gaps else ''})")
    for k, (start, stop) in enumerate(gaps):
        zoomable.shade(layout, start, stop, "#888888", "gap" if k == 0 else None)
    traces = []
    for prior, knode in pairs:
        error = {m: np.linalg.norm(np.asarray(estimates.estimates[m])[:, columns] - reference, axis=1)
                 for m in (prior, knode)}
        difference = error[knode] - error[prior]
        kernel = np.ones(2 * half + 1) / (2 * half + 1)
        smooth = np.convolve(difference, kernel, mode="same")
        label = f"{knode.upper()} − {prior.upper()}"
        traces.append(zoomable.line(difference, label, zoomable.METHOD_COLOURS.get(knode, "#777"), width=0.6,
                                    group=knode))
        traces.append(zoomable.line(smooth, f"{label}, {RMS_WINDOW_S:g}-s mean", zoomable.METHOD_COLOURS.get(
            knode, "#777"), width=2.2, group=knode))
    return zoomable.figure(estimates.t, traces, layout)
