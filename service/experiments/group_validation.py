"""Pooled training whose residual scale is chosen by holding out whole groups of its own training flights: the
science lives in `estimators.group_training` (every surface and ``le.KNODE().fit`` call it there); these names stay
importable from here for the studies that use them."""
from __future__ import annotations

from learnest.estimators.group_training import (  # noqa: F401  (re-exported)
    NO_SCALE,
    PAIR,
    gap_gains_by_scale,
    group_summary,
    train_with_scale_choice,
)
