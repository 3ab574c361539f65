"""Zoomable figures: plotly.js, served from the `plotly` package on this server (no CDN), drawn from figure
specifications built here as plain dicts in plotly's JSON schema (no plotly Python import on a request).

A page embeds a spec with `embed` (a ``<script type='application/json'>`` block, escaped for HTML) next to a
``<div>``; static/plots.js draws every such block.  Traces that carry no ``x`` take the spec's shared ``t``,
so a time axis is sent once per figure, not once per trace.  Rows of a figure share one x axis: zooming one
zooms all.

A screen shows at most a few thousand points across: a trace longer than MAX_POINTS is decimated to the
smallest and largest value of each of MAX_POINTS / 2 equal stretches (and the first value of any gap), so
its outline - peaks and spikes included - is what the full trace would draw, in bounded bytes; such a trace
carries its own ``x``.  A 226k-sample flight's page is then a few hundred kB, not 45 MB.
"""
from __future__ import annotations

import importlib.util
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from markupsafe import Markup

# one colour per method throughout the pages and the CLI's PNGs; the priors are drawn wider and first, so the
# KNODE line on top never hides them
from ..local.palette import METHOD_COLOURS, REFERENCE_COLOUR  # noqa: F401  (re-exported)

PLOTLY_JS_ROUTE = "/vendor/plotly.min.js"
SIGNIFICANT_DIGITS = 5          # of every number sent: far below what a screen shows, a third of the bytes
MAX_POINTS = 4000               # per trace: about two per pixel of a wide screen (min and max of each stretch)



def plotly_js_path() -> Path:
    """plotly.min.js inside the installed `plotly` package (found without importing it).

    Raises
    ------
    FileNotFoundError
        When the package, or the file in it, is not installed.
    """
    spec = importlib.util.find_spec("plotly")
    for folder in (spec.submodule_search_locations or []) if spec else []:
        path = Path(folder) / "package_data" / "plotly.min.js"
        if path.is_file():
            return path
    raise FileNotFoundError("plotly.min.js: the `plotly` package is not installed (pip install plotly)")


def series(values) -> list:
    """Numbers to `SIGNIFICANT_DIGITS` digits as a JSON-able list; NaN and inf become None (a gap)."""
    array = np.asarray(values, dtype=float).ravel()
    text = np.char.mod(f"%.{SIGNIFICANT_DIGITS}g", array)
    return [float(v) if np.isfinite(a) else None for v, a in zip(text, array, strict=True)]


def decimation(values, max_points: int = MAX_POINTS) -> np.ndarray | None:
    """Sorted indices of ``values`` that keep, of each of ``max_points // 2`` equal stretches, the smallest and
    largest value and the first NaN (a gap stays a gap), plus the first and last sample; None when the series
    has at most ``max_points`` values (nothing to drop)."""
    array = np.asarray(values, dtype=float).ravel()
    n = len(array)
    if n <= max_points:
        return None
    size = -(-n // (max_points // 2))
    rows = -(-n // size)
    padded = np.full(rows * size, np.nan)
    padded[:n] = array
    block = padded.reshape(rows, size)
    missing = np.isnan(block)
    starts = np.arange(rows) * size
    low = np.where(missing, np.inf, block).argmin(axis=1)
    high = np.where(missing, -np.inf, block).argmax(axis=1)
    picked = [starts + low, starts + high, [0, n - 1]]
    gaps = missing.copy()
    gaps[-1, n - starts[-1]:] = False          # the padding is no gap
    has_gap = gaps.any(axis=1)
    picked.append((starts + gaps.argmax(axis=1))[has_gap])
    index = np.unique(np.concatenate(picked))
    return index[index < n]


def line(y, name: str, colour: str, *, row: int = 1, width: float = 1.2, dash: str = "solid",
         group: str | None = None, legend: bool = True, x=None) -> dict:
    """A line trace on ``row`` (1 = top) of a stacked figure; without ``x`` it takes the figure's ``t``.  A
    trace longer than MAX_POINTS is decimated (`decimation`) when the figure is made (`figure`)."""
    values = np.asarray(y, dtype=float).ravel()
    trace = {"type": "scatter", "mode": "lines", "name": name, "y": values,
             "line": {"color": colour, "width": width, "dash": dash},
             "xaxis": "x", "yaxis": "y" if row == 1 else f"y{row}", "legendgroup": group or name,
             "showlegend": legend, "hovertemplate": "%{y:.4g}"}
    if x is not None:
        trace["x"] = np.asarray(x, dtype=float).ravel()
    return trace


def _finished(trace: dict, t: np.ndarray) -> dict:
    """A trace of `line` with its numbers as JSON lists, decimated when long (then with its own x)."""
    if not isinstance(trace.get("y"), np.ndarray):
        return trace
    y = trace["y"]
    x = trace.get("x", t)
    x = np.asarray(x, dtype=float) if not isinstance(x, np.ndarray) else x
    index = decimation(y)
    if index is not None:
        return {**trace, "x": series(x[index]), "y": series(y[index])}
    finished = {**trace, "y": series(y)}
    if "x" in trace:
        finished["x"] = series(x)
    return finished


def stacked_layout(ylabels: Sequence[str], xlabel: str = "t (s)", title: str | None = None,
                   row_height: int = 150) -> dict:
    """Layout of ``len(ylabels)`` rows sharing one x axis (top to bottom), each with its y label."""
    rows = len(ylabels)
    layout: dict = {"grid": {"rows": rows, "columns": 1, "pattern": "coupled", "roworder": "top to bottom"},
                    "height": 110 + row_height * rows, "margin": {"l": 70, "r": 20, "t": 75 if title else 40,
                                                                   "b": 45},
                    "hovermode": "x unified", "legend": {"orientation": "h", "y": 1.0, "yanchor": "bottom"},
                    "xaxis": {"title": {"text": xlabel}, "showgrid": True}, "shapes": [], "annotations": []}
    if title:
        layout["title"] = {"text": title, "font": {"size": 14}, "y": 0.995, "yanchor": "top",
                           "yref": "container"}
    for k, label in enumerate(ylabels, start=1):
        layout["yaxis" if k == 1 else f"yaxis{k}"] = {"title": {"text": label, "font": {"size": 11}},
                                                      "zeroline": True}
    return layout


def shade(layout: dict, start: float, stop: float, colour: str, label: str | None = None,
          label_y: float = 1.0) -> None:
    """A band over every row between x = ``start`` and ``stop``, with ``label`` at its left, its bottom at
    ``label_y`` (figure fraction: 1 is the top of the plotting area)."""
    layout["shapes"].append({"type": "rect", "xref": "x", "yref": "paper", "x0": float(start), "x1": float(stop),
                             "y0": 0, "y1": 1, "fillcolor": colour, "opacity": 0.25, "line": {"width": 0},
                             "layer": "below"})
    if label:
        layout["annotations"].append({"x": float(start), "xref": "x", "y": label_y, "yref": "paper", "text": label,
                                      "showarrow": False, "xanchor": "left", "yanchor": "bottom",
                                      "font": {"size": 10, "color": "#444"}})


def figure(t, traces: list[dict], layout: dict) -> dict:
    """A figure spec: the shared time axis ``t`` (s), the traces (long ones decimated, `decimation`) and the
    layout.  ``t`` is sent only when a trace uses it."""
    t = np.asarray(t, dtype=float).ravel()
    data = [_finished(trace, t) for trace in traces]
    shared = any("x" not in trace for trace in data)
    return {"t": series(t) if shared else [], "data": data, "layout": layout}


def embed(spec: dict) -> Markup:
    """The spec as JSON safe inside a ``<script type='application/json'>`` block (``<``, ``>``, ``&`` and
    ``'`` escaped, so no text in it can close the block)."""
    text = json.dumps(spec, separators=(",", ":"), allow_nan=False)
    for char, escaped in (("&", "\\u0026"), ("<", "\\u003c"), (">", "\\u003e"), ("'", "\\u0027")):
        text = text.replace(char, escaped)
    return Markup(text)
