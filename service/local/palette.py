"""One colour per estimator, used the same way by every figure: the zoomable plotly figures of the pages,
the matplotlib PNGs of the pages and the CLI's --plot files.  A prior-only method and its KNODE variant
share a hue family (UKF blue / KNODE-UKF orange, MHE green / KNODE-MHE red: matplotlib's tab10 order), so
a reader who learnt the colours on one page reads every other figure with them.

Good and bad are never told by colour on the same marks as a method: a gain figure draws its marks in the
method's colour and tells better from worse by the side of the zero line (and says so in its legend).
"""
from __future__ import annotations

METHOD_COLOURS = {"ukf": "#1f77b4", "knode-ukf": "#ff7f0e", "mhe": "#2ca02c", "knode-mhe": "#d62728",
                  "onboard": "#9467bd"}
REFERENCE_COLOUR = "#000000"
OTHER_COLOUR = "#7f7f7f"     # a method this table does not know
GAP_SHADE = "#bbbbbb"        # the mocap gaps shaded behind a time axis
# a diagnosis' before (the prior) and after (with the effects): greys, never a method's colour
BEFORE_COLOUR, AFTER_COLOUR = "#a0a0a0", "#303030"


def colour(method: str) -> str:
    """The colour of ``method`` ("ukf", "knode-ukf", "mhe", "knode-mhe", "onboard"), grey for others."""
    return METHOD_COLOURS.get(method.lower(), OTHER_COLOUR)
