"""Where the mocap-gap yardstick hides the mocap (`GapPlan`): plain numbers, checked without numpy, so the
command line refuses a bad ``--gap-s`` / ``--gap-every-s`` before it loads the estimators
(`learnest.estimators.yardsticks` runs the gaps)."""
from __future__ import annotations

import math
from dataclasses import dataclass

from learnest.errors import InvalidInput
from learnest.models.presets import GAP_EVERY_S, GAP_S, GAP_START_S, MAX_GAPS, gap_plan_problem


@dataclass(frozen=True)
class GapPlan:
    """Where the mocap is hidden.

    Attributes
    ----------
    gap_s : float
        Length of each gap, s (0 turns the gap yardstick off).
    every_s : float
        Time from one gap's start to the next's, s; longer than ``gap_s``, so the estimator sees mocap
        between gaps.  Gaps, and the mocap between them, last `MIN_GAP_S` at least, and one sample of the
        flight they are laid on (`windows`), at most `MAX_GAPS` per flight: InvalidInput otherwise.
    start_s : float
        No gap starts before this, s from the kept flight's start.
    """

    gap_s: float = GAP_S
    every_s: float = GAP_EVERY_S
    start_s: float = GAP_START_S

    def __post_init__(self) -> None:
        # bounded before any window is laid: a 1e-300-s spacing would never reach the flight's end
        problem = self.problem_on()
        if problem is not None:
            raise InvalidInput(problem)

    def problem_on(self, dt: float | None = None, n_samples: int | None = None) -> str | None:
        """Why the plan is out of bounds, naming the field ("gap_every_s must be longer than the gap ..."), or
        None: on its own, or on a flight of ``n_samples`` samples ``dt`` s apart (a gap, and the mocap between
        gaps, one sample at least; at most `MAX_GAPS` gaps) (`learnest.models.presets.gap_plan_problem`)."""
        problem = gap_plan_problem(self.gap_s, self.every_s, self.start_s, dt=dt, n_samples=n_samples)
        return None if problem is None else f"{problem[0]} {problem[1]}"

    def windows(self, n_samples: int, dt: float) -> list[tuple[int, int]]:
        """[(first, stop), ...] sample indices of each gap (stop exclusive) that fits wholly in the record.

        Raises
        ------
        InvalidInput
            A gap, or the mocap between two gaps, shorter than one sample ``dt``, or more than `MAX_GAPS` gaps
            on the record (`problem_on`).
        """
        if self.gap_s <= 0:
            return []
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise InvalidInput(f"the sample period must be a positive number of seconds, got {dt!r}")
        problem = self.problem_on(dt, n_samples)
        if problem is not None:
            raise InvalidInput(problem)
        length = max(1, int(round(self.gap_s / dt)))
        out: list[tuple[int, int]] = []
        start_s = self.start_s
        for _ in range(MAX_GAPS + 1):   # checked above: never more gaps than this
            first = int(round(start_s / dt))
            if first + length > n_samples:
                break
            out.append((first, first + length))
            start_s += self.every_s
        return out

    def too_short(self, n_samples: int, dt: float) -> str | None:
        """Why a record of ``n_samples`` gets no gap, or None when at least one fits."""
        if self.gap_s <= 0:
            return "the gap yardstick was turned off (gap length 0 s)"
        if self.windows(n_samples, dt):
            return None
        return (f"the kept flight is {n_samples * dt:.1f} s long, too short for one mocap gap (the first "
                f"{self.gap_s:g}-s gap starts after {self.start_s:g} s)")
