"""Figures: the Fig. 3-style box plot of per-flight MSE by method."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

ORDER = ("mhe", "knode-mhe", "ukf", "knode-ukf")


def mse_boxplot(report: dict, path, title: str | None = None) -> None:
    scored = [f for f in report["flights"] if not f.get("excluded")]
    methods = [m for m in ORDER if any(m in f["mse"] for f in scored)]
    data = [[f["mse"][m] for f in scored if m in f["mse"]] for m in methods]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.boxplot(data, tick_labels=[m.upper() for m in methods],
               medianprops={"color": "tab:orange", "linewidth": 2})
    ax.set_ylabel("overall MSE over [p, v, a]")
    ax.set_title(title or f"model {report.get('model')}: {len(scored)} flights")
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def residual_before_after(diagnosis: dict, path) -> None:
    """Bar chart of the residual RMS per channel before and after the effects were added, and the
    median MSE of each estimator before/after."""
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    channels = diagnosis.get("channels", {})
    names = list(channels)
    before = [np.sqrt(channels[c]["rss_before"]) for c in names]
    after = [np.sqrt(channels[c]["rss_after"]) for c in names]
    x = np.arange(len(names))
    axes[0].bar(x - 0.2, before, 0.4, label="before")
    axes[0].bar(x + 0.2, after, 0.4, label="after")
    axes[0].set_xticks(x, names)
    axes[0].set_ylabel("√RSS of the whitened residual")
    axes[0].set_title("residual, before and after the effects")
    axes[0].legend()
    methods = list(diagnosis.get("before", {}))
    x = np.arange(len(methods))
    axes[1].bar(x - 0.2, [diagnosis["before"][m] for m in methods], 0.4, label="original model")
    axes[1].bar(x + 0.2, [diagnosis["after"][m] for m in methods], 0.4, label="with effects")
    axes[1].set_xticks(x, [m.upper() for m in methods])
    axes[1].set_ylabel("MSE (held-out data)")
    axes[1].set_yscale("log")
    axes[1].set_title(", ".join(e["id"] for e in diagnosis["effects"]) or "no effect found")
    axes[1].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
