"""Where the mocap-gap yardstick hides the mocap (`GapPlan`): plain numbers, checked without numpy, so the
command line refuses a bad ``--gap-s`` / ``--gap-every-s`` before it loads the estimators
(`learnest.estimators.yardsticks` runs the gaps)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from learnest.errors import InvalidInput
from learnest.models.presets import GAP_EVERY_S, GAP_S, GAP_START_S


@dataclass(frozen=True)
class GapPlan:
    """Where the mocap is hidden.

    Attributes
    ----------
    gap_s : float
        Length of each gap, s (0 turns the gap yardstick off).
    every_s : float
        Time from one gap's start to the next's, s; longer than ``gap_s``, so the estimator sees mocap
        between gaps.
    start_s : float
        No gap starts before this, s from the kept flight's start.
    """

    gap_s: float = GAP_S
    every_s: float = GAP_EVERY_S
    start_s: float = GAP_START_S

    def __post_init__(self) -> None:
        for name in ("gap_s", "every_s", "start_s"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise InvalidInput(f"{name} must be a non-negative number of seconds, got {value!r}")
        if self.gap_s > 0 and not self.every_s > self.gap_s:
            raise InvalidInput(f"gap every {self.every_s} s must be longer than the gap ({self.gap_s} s): the "
                               "estimator needs mocap between gaps")

    def windows(self, n_samples: int, dt: float) -> list[tuple[int, int]]:
        """[(first, stop), ...] sample indices of each gap (stop exclusive) that fits wholly in the record."""
        if self.gap_s <= 0:
            return []
        length = max(1, int(round(self.gap_s / dt)))
        out: list[tuple[int, int]] = []
        start_s = self.start_s
        while True:
            first = int(round(start_s / dt))
            if first + length > n_samples:
                return out
            out.append((first, first + length))
            start_s += self.every_s

    def too_short(self, n_samples: int, dt: float) -> str | None:
        """Why a record of ``n_samples`` gets no gap, or None when at least one fits."""
        if self.gap_s <= 0:
            return "the gap yardstick was turned off (gap length 0 s)"
        if self.windows(n_samples, dt):
            return None
        return (f"the kept flight is {n_samples * dt:.1f} s long, too short for one mocap gap (the first "
                f"{self.gap_s:g}-s gap starts after {self.start_s:g} s)")
