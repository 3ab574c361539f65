"""Figures: matplotlib's object API (`Figure`), never pyplot.

pyplot keeps one global "current figure" per process, which the server's request threads would share; a
`Figure` made here belongs to the call that made it, so no lock is needed and nothing has to be closed.
Each builder returns the Figure; `png_data_uri` embeds it in a page, `save_figure` writes it to a file (the
CLI's --plot).  Here, below the web pages and the CLI, so both draw the same figures: it draws stored model
versions (`training_losses`), which the workflows know nothing of, and loads no FastAPI or Jinja.
"""
from __future__ import annotations

import base64
import io
import os
from typing import IO, TYPE_CHECKING, cast

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

from learnest.ingest.flight import Flight as CanonicalFlight

from ..storage.tables import ModelVersion
from .palette import AFTER_COLOUR, BEFORE_COLOUR, REFERENCE_COLOUR, colour

BOX_ORDER = ("mhe", "knode-mhe", "ukf", "knode-ukf")   # the order of the paper's Fig. 3
VELOCITY_METHODS = ("ukf", "knode-ukf")                # the velocity plot's estimators: quick to run on a request


def _figure(**options) -> Figure:
    from matplotlib.figure import Figure  # imported when a figure is drawn: starting the app stays fast

    return Figure(**options)


# -- output ------------------------------------------------------------------------------------------------
def save_figure(fig: Figure, target: str | os.PathLike | IO[bytes], dpi: int = 100) -> None:
    """Write the figure to a path (its extension picks the format, .png, .svg, .pdf ...) or, as PNG, to a
    binary file object."""
    fig.savefig(target, dpi=dpi, format="png" if hasattr(target, "write") else None)


def png_data_uri(fig: Figure, dpi: int = 100) -> str:
    """The figure as a ``data:image/png;base64,...`` URI for an ``<img src>`` (a page needs no second request)."""
    buffer = io.BytesIO()
    save_figure(fig, buffer, dpi)
    return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode()


# -- figures of stored things ---------------------------------------------------------------------------------
def trajectory(flight: CanonicalFlight, name: str) -> Figure:
    """Top view (x-y, equal axes) and height over time of a flight's mocap position."""
    fig = _figure(figsize=(10, 4), layout="constrained")
    top, height = fig.subplots(1, 2, width_ratios=[1, 1.6])
    top.plot(flight.p[:, 0], flight.p[:, 1], lw=1)
    top.set(xlabel="x (m)", ylabel="y (m)", title=f"{name}: top view", aspect="equal")
    height.plot(flight.t, flight.p[:, 2], lw=1)
    height.set(xlabel="t (s)", ylabel="z (m)", title="height")
    for ax in (top, height):
        ax.grid(alpha=0.3)
    return fig


def training_losses(versions: list[ModelVersion]) -> Figure:
    """Training loss per epoch of each version (log scale); a None loss (a diverged epoch) is a gap."""
    fig = _figure(figsize=(7, 3.5), layout="constrained")
    ax = fig.subplots()
    for v in versions:
        losses = np.array([np.nan if x is None else x for x in (v.losses or [])], float)
        if len(losses):
            ax.plot(np.arange(1, len(losses) + 1), losses, marker="." if len(losses) < 30 else None,
                    label=f"version {v.version}")
    ax.set(xlabel="epoch", ylabel="training loss", yscale="log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return fig


def velocity(t: np.ndarray, reference: np.ndarray, estimates: dict[str, np.ndarray], title: str) -> Figure:
    """vx, vy, vz (state columns 3-5, m/s) of each estimator against the Savitzky-Golay reference.

    Parameters
    ----------
    t : (T,) array, s
    reference : (T, 9) array
        The SG reference states [p, v, a].
    estimates : dict of method -> (T, 9) array
    title : str
    """
    fig = _figure(figsize=(10, 7), layout="constrained")
    axes = fig.subplots(3, 1, sharex=True)
    for k, (ax, label) in enumerate(zip(axes, ("vx", "vy", "vz"), strict=True)):
        ax.plot(t, reference[:, 3 + k], color=REFERENCE_COLOUR, lw=1.5, label="SG reference")
        for method, values in estimates.items():
            ax.plot(t, values[:, 3 + k], lw=1, label=method.upper(), color=colour(method))
        ax.set_ylabel(f"{label} (m/s)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize="small", ncol=len(estimates) + 1)
    axes[0].set_title(title)
    axes[-1].set_xlabel("t (s)")
    return fig


def velocity_png(model_json: bytes, flight_bytes: bytes, title: str) -> str:
    """The velocity figure of a model on a flight, as a data URI: an executor task (it runs the UKF and
    KNODE-UKF on the flight, about a second); service.web.report_figures keeps its answer."""
    from learnest.service.storage.registry import model_from_json
    from learnest.workflows.flights import evaluate_flight  # torch: only in the worker

    model = model_from_json(model_json)
    flight = CanonicalFlight.from_bytes(flight_bytes)
    out = evaluate_flight(model, flight, list(VELOCITY_METHODS), keep_estimates=True)
    estimates = {m: r["estimates"] for m, r in out["results"].items()}
    return png_data_uri(velocity(flight.t, out["reference"], estimates, title))


# -- evaluation and diagnosis reports -------------------------------------------------------------------------
def has_scores(report: dict) -> bool:
    """True when an evaluation report has at least one scored flight (something to box-plot)."""
    return any(not f.get("excluded") and f.get("mse") for f in report["flights"])


def mse_boxplot(report: dict, title: str | None = None) -> Figure:
    """The Fig. 3-style box plot of per-flight overall MSE by method (an evaluation report's scored flights)."""
    scored = [f for f in report["flights"] if not f.get("excluded")]
    methods = [m for m in BOX_ORDER if any(m in f["mse"] for f in scored)]
    data = [[f["mse"][m] for f in scored if m in f["mse"]] for m in methods]
    fig = _figure(figsize=(6, 4), layout="tight")
    ax = fig.subplots()
    ax.boxplot(data, tick_labels=[m.upper() for m in methods],
               medianprops={"color": "tab:orange", "linewidth": 2})
    ax.set_ylabel("overall MSE over [p, v, a]")
    ax.set_title(title or f"model {report.get('model')}: {len(scored)} flights")
    ax.grid(axis="y", alpha=0.3)
    return fig


BOX_MIN_FLIGHTS = 10   # below this many flights a box plot's quartiles are guesses: the dots alone are drawn
PAIRS = (("ukf", "knode-ukf"), ("mhe", "knode-mhe"))   # (prior-only, KNODE): the comparisons of the paper


def paired_mse(report: dict, title: str | None = None) -> Figure:
    """Per scored flight, each prior-only method and its KNODE variant (UKF → KNODE-UKF, MHE → KNODE-MHE)
    as two dots in the methods' colours joined by a grey line (solid: KNODE lower, dashed: higher), the
    medians as bars in the method's colour, in MSE × 1e-3 (the
    units of the report's table) on a linear axis from zero; box plots behind the dots from
    `BOX_MIN_FLIGHTS` flights on.  Methods run without their pair are drawn alone."""
    fig = _figure(figsize=(6.5, 4), layout="constrained")
    _draw_paired(fig.subplots(), report, title)
    return fig


def _draw_paired(ax, report: dict, title: str | None = None) -> None:
    """`paired_mse` on the axes ``ax``."""
    scored = [f for f in report["flights"] if not f.get("excluded") and f.get("mse")]
    ran = [m for m in BOX_ORDER if any(m in f["mse"] for f in scored)]
    columns: list[tuple[str, ...]] = [p for p in PAIRS if p[0] in ran and p[1] in ran]
    columns += [(m,) for m in ran if not any(m in p for p in columns)]
    ticks, labels, x = [], [], 0
    for column in columns:
        positions = list(range(x, x + len(column)))
        values = [[f["mse"][m] * 1e3 for f in scored if all(c in f["mse"] for c in column)] for m in column]
        if len(values[0]) >= BOX_MIN_FLIGHTS:
            ax.boxplot(values, positions=positions, widths=0.5, showfliers=False,
                       medianprops={"color": "tab:orange", "linewidth": 2})
        for row in zip(*values, strict=True):
            worse = len(row) == 2 and row[1] >= row[0]
            ax.plot(positions, row, color="grey", lw=0.9, ls="--" if worse else "-", alpha=0.8)
            for position, value, method in zip(positions, row, column, strict=True):
                ax.plot([position], [value], "o", ms=4, color=colour(method), alpha=0.9)
        for position, v, method in zip(positions, values, column, strict=True):
            ax.hlines(np.median(v), position - 0.25, position + 0.25, color=colour(method), lw=2.5)
        ticks += positions
        labels += [m.upper() for m in column]
        x += len(column) + 1
    ax.set_xticks(ticks, labels)
    ax.set_ylim(bottom=0)
    from matplotlib.lines import Line2D
    ax.legend(handles=[Line2D([], [], color="grey", lw=0.9, label="a flight: KNODE lower"),
                       Line2D([], [], color="grey", lw=0.9, ls="--", label="a flight: KNODE higher"),
                       Line2D([], [], color="black", lw=2.5, label="median (method's colour)")],
              fontsize="small", loc="upper right")
    ax.set_ylabel("overall MSE over [p, v, a]  (× 1e-3)")
    ax.set_title(title or f"model {report.get('model')}: {len(scored)} flights, one line per flight")
    ax.grid(axis="y", alpha=0.3)


SPECIFIC_FORCE = "specific_force_rmse"   # a diagnosis' before/after key that is an RMSE in m/s², not an MSE


def residual_before_after(diagnosis: dict) -> Figure:
    """A diagnosis report's figure (`learnest diagnose --plot`): the summary (`diagnosis_summary`) above the
    residual time series (`draw_residual_series`) when the report has them.  Linear axes throughout."""
    series = diagnosis.get("residual_series") or {}
    rows = sum(3 for _ in series)
    fig = _figure(figsize=(10, 4 + 1.8 * rows), layout="constrained")
    if not series:
        draw_summary(fig, diagnosis)
        return fig
    # two rows give an array of SubFigures (the stubs also allow a single one)
    top, bottom = cast("np.ndarray", fig.subfigures(2, 1, height_ratios=[4, 1.8 * rows]))
    draw_summary(top, diagnosis)
    draw_residual_series(bottom, series)
    return fig


def diagnosis_summary(diagnosis: dict) -> Figure:
    """Residual and held-out error before and after the effects (see `draw_summary`)."""
    fig = _figure(figsize=(10, 3.6), layout="constrained")
    draw_summary(fig, diagnosis)
    return fig


def residual_series(series: dict) -> Figure:
    """The residual over time before and after the effects (see `draw_residual_series`)."""
    fig = _figure(figsize=(10, 1 + 1.8 * 3 * len(series)), layout="constrained")
    draw_residual_series(fig, series)
    return fig


def draw_summary(fig, diagnosis: dict) -> None:
    """Left: each channel's √RSS of the whitened residual on the fitting data, before and after.  Then each
    estimator's MSE on each held-out flight, before and after as a pair of dots joined by a line (the
    median a bar), and the specific-force RMSE the same way when the report has one.  Linear axes from
    zero: a log axis would make a 12 % change look like a factor.

    ``fig`` is a matplotlib Figure or SubFigure.
    """
    channels = diagnosis.get("channels", {})
    flights = diagnosis.get("per_flight") or [{"before": diagnosis["before"], "after": diagnosis["after"]}]
    methods = [m for m in diagnosis.get("before", {}) if m != SPECIFIC_FORCE]
    panels = 2 + (SPECIFIC_FORCE in diagnosis.get("before", {}))
    axes = fig.subplots(1, panels, width_ratios=[1, 1.6, 0.7][:panels])
    names = list(channels)
    x = np.arange(len(names))
    axes[0].bar(x - 0.2, [np.sqrt(channels[c]["rss_before"]) for c in names], 0.4, label="before", color=BEFORE_COLOUR)
    axes[0].bar(x + 0.2, [np.sqrt(channels[c]["rss_after"]) for c in names], 0.4, label="after", color=AFTER_COLOUR)
    axes[0].set_xticks(x, names, fontsize="small")
    axes[0].set(ylabel="√RSS, whitened residual", title="residual on the fitting data")
    axes[0].legend(fontsize="small")
    _paired(axes[1], flights, methods, "MSE on held-out data (paper's SG yardstick)")
    from matplotlib.patches import Patch
    axes[1].legend(handles=[Patch(color=BEFORE_COLOUR, alpha=0.35, label="median before (prior)"),
                            Patch(color=AFTER_COLOUR, alpha=0.35, label="median after (with the effects)")],
                   fontsize="small", loc="lower right")
    axes[1].set_title(", ".join(e["id"] for e in diagnosis["effects"]) or "no effect found")
    if panels == 3:
        _paired(axes[2], flights, [SPECIFIC_FORCE], "specific force RMSE (m/s²)")
        axes[2].set_xticks([0], ["from inputs"])
    for ax in axes:
        ax.set_ylim(bottom=0)
        ax.grid(axis="y", alpha=0.3)


def _paired(ax, flights: list[dict], keys: list[str], ylabel: str) -> None:
    """Per key: before (x - 0.15) and after (x + 0.15) of every flight joined by a line; medians as bars."""
    for i, key in enumerate(keys):
        before = [f["before"][key] for f in flights if key in f["before"] and key in f["after"]]
        after = [f["after"][key] for f in flights if key in f["before"] and key in f["after"]]
        if not before:
            continue
        ax.bar([i - 0.15, i + 0.15], [np.median(before), np.median(after)], 0.3, color=[BEFORE_COLOUR, AFTER_COLOUR],
               alpha=0.35)
        for b, a in zip(before, after, strict=True):
            ax.plot([i - 0.15, i + 0.15], [b, a], color="grey", lw=0.8, marker="o", ms=3)
    ax.set_xticks(np.arange(len(keys)), [k.upper() for k in keys])
    ax.set_ylabel(ylabel)


def draw_residual_series(fig, series: dict) -> None:
    """Per channel of ``series`` (a report's ``residual_series``), one axis per body axis: the residual over
    time with the prior (before) and with the fitted effects (after), and their rms in the title.

    ``fig`` is a matplotlib Figure or SubFigure.
    """
    axes = fig.subplots(3 * len(series), 1, sharex=True, squeeze=False)[:, 0]
    for c, (channel, s) in enumerate(series.items()):
        t, before, after = np.asarray(s["t"]), np.asarray(s["before"]), np.asarray(s["after"])
        for k, name in enumerate(s["axes"]):
            ax = axes[3 * c + k]
            ax.plot(t, before[:, k], color=BEFORE_COLOUR, lw=0.8, label="before (prior)")
            ax.plot(t, after[:, k], color=AFTER_COLOUR, lw=0.8, label="after (with the effects)")
            ax.axhline(0, color="black", lw=0.5)
            ax.set_ylabel(f"{name} ({s['units']})")
            ax.grid(alpha=0.3)
        rms = [np.sqrt(np.mean(a**2)) for a in (before, after)]
        flight = str(s["flight"]).replace("$", r"\$")   # a name is text, not mathtext
        axes[3 * c].set_title(f"{channel} residual on held-out flight {flight}: rms {rms[0]:.3g} before, "
                              f"{rms[1]:.3g} after ({s['units']})", fontsize="medium")
        axes[3 * c].legend(fontsize="small", ncol=2, loc="upper right")
    axes[-1].set_xlabel("t (s) since the first sample shown")


# -- where the model helps ----------------------------------------------------------------------------------
def gain_per_flight(headline: dict, title: str | None = None) -> Figure | None:
    """Each KNODE's gain over its prior per flight, with the flight's 95 % interval, one row per flight
    labelled by its name (`learnest.workflows.headline.evaluation_headline`'s ``pairs``); a vertical line at 0
    (right of it: the KNODE's error is lower) and each comparison's median dashed.  Marks in the KNODE's
    colour (service.local.palette), a legend on the figure.  None when there is no comparison."""
    pairs = headline.get("pairs") or []
    if not pairs:
        return None
    names = list(dict.fromkeys(r["flight"] for p in pairs for r in p["rows"]))
    fig = _figure(figsize=(7.5, 1.2 + 0.32 * len(names) * max(1, len(pairs)) ** 0.5), layout="constrained")
    draw_gain(fig.subplots(), headline, title)
    return fig


def draw_gain(ax, headline: dict, title: str | None = None) -> None:
    """`gain_per_flight` on the axes ``ax`` (``headline`` has at least one pair)."""
    pairs = headline["pairs"]
    names = list(dict.fromkeys(r["flight"] for p in pairs for r in p["rows"]))
    step = 0.8 / len(pairs)
    for k, pair in enumerate(pairs):
        offset = (k - (len(pairs) - 1) / 2) * step
        c = colour(pair["knode"])
        rows = {r["flight"]: r for r in pair["rows"]}
        for i, name in enumerate(names):
            r = rows.get(name)
            if r is None:
                continue
            y = i + offset
            if r["interval_pct"]:
                lo, hi = r["interval_pct"]
                ax.hlines(y, lo, hi, color=c, lw=1.6, alpha=0.8)
            ax.plot([r["gain_pct"]], [y], "o", color=c, ms=5)
        ax.axvline(pair["median_gain_pct"], color=c, lw=1, ls="--")
        ax.plot([], [], "o-", color=c, ms=5,
                label=f"{pair['knode'].upper()} vs {pair['prior'].upper()}: gain, 95 % interval; "
                      f"dashed: median {pair['median_gain_pct']:+.1f} %")
    ax.axvline(0, color="black", lw=0.8)
    ax.set_yticks(range(len(names)), [n.replace("$", r"\$") for n in names], fontsize="small")
    ax.set_ylim(len(names) - 0.5, -0.5)
    yardstick = "error in the mocap gaps" if headline.get("yardstick") == "mocap_gaps" else \
        "MSE vs the Savitzky-Golay reference"
    ax.set_xlabel(f"gain over the prior (%), {yardstick}: right of 0, the KNODE is better")
    ax.grid(axis="x", alpha=0.3)
    ax.legend(fontsize="small", loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=1, frameon=False)
    if title:
        ax.set_title(title, fontsize="medium")


def evaluation_summary(report: dict) -> Figure:
    """The figure of `learnest evaluate --plot` and the demo's: the answer on top (each KNODE's gain over
    its prior per flight, labelled by flight, with 95 % intervals: `gain_per_flight`), the paired MSE dots
    (`paired_mse`) below.  Without a prior/KNODE pair, the paired dots alone."""
    from learnest.workflows.headline import evaluation_headline

    head = evaluation_headline(report)
    if not head["pairs"]:
        return paired_mse(report)
    flights = len({r["flight"] for p in head["pairs"] for r in p["rows"]})
    fig = _figure(figsize=(8, 5.5 + 0.32 * flights), layout="constrained")
    top, bottom = cast("np.ndarray", fig.subfigures(2, 1, height_ratios=[1.2 + 0.32 * flights, 4.3]))
    draw_gain(top.subplots(), head, title=head["sentence"] if len(head["sentence"]) < 110 else None)
    _draw_paired(bottom.subplots(), report)
    return fig
