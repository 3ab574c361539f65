"""Figures of the registry pages (service.web.registry_pages): loss curves of one or more versions."""
from __future__ import annotations

import numpy as np

from ..local.figures import png_data_uri


def _curve(values) -> np.ndarray:
    return np.array([np.nan if x is None else x for x in (values or [])], float)


def loss_curves_of(versions: list[dict]) -> str | None:
    """Training (solid) and validation (dashed, same colour) loss per epoch of each version, log scale, as a
    PNG data URI; None when no version has losses.  ``versions`` are dicts with ``ref``, ``losses`` and
    ``validation_losses`` (a None loss, a diverged epoch, is a gap)."""
    drawn = [v for v in versions if v.get("losses")]
    if not drawn:
        return None
    from matplotlib.figure import Figure  # imported when a figure is drawn: starting the app stays fast

    fig = Figure(figsize=(7, 3.5), layout="constrained")
    ax = fig.subplots()
    for k, v in enumerate(drawn):
        colour = f"C{k % 10}"
        training = _curve(v["losses"])
        ax.plot(np.arange(1, len(training) + 1), training, color=colour, label=f"{v['ref']} training")
        validation = _curve(v.get("validation_losses"))
        if len(validation):
            ax.plot(np.arange(1, len(validation) + 1), validation, color=colour, ls="--",
                    label=f"{v['ref']} validation")
    ax.set(xlabel="epoch", ylabel="loss (one-step, mean)", yscale="log")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    return png_data_uri(fig)
