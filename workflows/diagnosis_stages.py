"""Named stages of a diagnosis, with one fraction for the whole run.

A diagnosis is several parts of very different cost (fitting effects, a pre-training observer, one or two
KNODE trainings, scoring before and after on each held-out flight).  `DiagnosisStages` gives each part a
share of 0..1 from a plan fixed before the run, maps each part's own progress (an effect tried, an epoch
trained, a flight scored) into that share, and reports ``on_stage(name, fraction)``: the fraction never goes
back and never leaves 0..1.  A stage's name is its kind followed by where it is in parentheses, "training the
KNODE on the repaired prior (epoch 3/20)": `stage_kind` drops the parenthesis, so a plain log can print one
line per kind of stage and a bar can show every tick.
"""
from __future__ import annotations

from collections.abc import Callable

StageCallback = Callable[[str, "float | None"], None]


def stage_kind(name: str) -> str:
    """A stage's name without its trailing "(…)" counter: "scoring before/after (b_cf_1, 1/2)" -> "scoring
    before/after"."""
    head, sep, tail = name.rpartition(" (")
    return head if sep and tail.endswith(")") else name


class DiagnosisStages:
    """The parts of one diagnosis and their shares of its progress.

    Parameters
    ----------
    on_stage : callable or None
        Called as ``on_stage(name, fraction)`` with fraction in 0..1, never lower than before; None: nothing
        is reported.
    plan : dict of str to float
        Each part's key and its relative cost (weights; normalised to sum to 1), in the order they run.
    """

    def __init__(self, on_stage: StageCallback | None, plan: dict[str, float]):
        self.on_stage = on_stage
        total = float(sum(plan.values())) or 1.0
        self.start: dict[str, float] = {}
        self.width: dict[str, float] = {}
        done = 0.0
        for key, weight in plan.items():
            self.start[key], self.width[key] = done / total, weight / total
            done += weight
        self.fraction = 0.0

    def report(self, part: str, name: str, inner: float | None = 0.0) -> None:
        """Part ``part`` is at ``inner`` (0..1 of its own work; None: unknown, kept where it was) in stage
        ``name``."""
        if self.on_stage is None:
            return
        if inner is not None and part in self.start:
            inner = min(1.0, max(0.0, float(inner)))
            self.fraction = max(self.fraction, min(1.0, self.start[part] + self.width[part] * inner))
        self.on_stage(name, self.fraction)

    def part(self, key: str) -> StageCallback | None:
        """``on_stage(name, inner)`` for a function that reports its own progress (`select_effects`)."""
        if self.on_stage is None:
            return None
        return lambda name, inner: self.report(key, name, inner)

    def epochs(self, key: str, what: str, epochs: int) -> Callable[[int, float], None] | None:
        """A training ``progress(epoch, loss)`` callback reporting "training the KNODE on <what> (epoch e/E)"."""
        if self.on_stage is None:
            return None
        return lambda epoch, _loss: self.report(key, f"training the KNODE on {what} (epoch {epoch + 1}/{epochs})",
                                                (epoch + 1) / max(1, epochs))
