"""Figures: the Fig. 3-style box plot of per-flight MSE by method."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402

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
