"""What an evaluation is asked to do, as one frozen type (`EvaluationSettings`).

Every surface states an evaluation in it: the command line, the API's request, the web form, the scheduler
and `le.evaluate`.  It is checked once, where it is built (the gap plan by `GapPlan`, the rest here), holds the
defaults once (its fields'), and travels as itself to the estimators.  It becomes JSON only where it is kept (a
job's stored arguments, an evaluation's row, the result cache's key) and is read back at once (`from_json`).

Plain numbers and names, checked without numpy: the command line refuses bad options before the estimators load.
"""
from __future__ import annotations

import numbers
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, Literal, get_args

from learnest.errors import InvalidInput
from learnest.models.presets import (
    EVALUATION_METHODS,
    GAP_EVERY_S,
    GAP_S,
    MHE_HORIZON,
    SG_WINDOW,
    SG_WINDOW_RANGE,
    check_mhe_options,
    parse_methods,
)

from .gap_plan import GapPlan

# the noise a model's filters may run with (`models.noise.NOISE_SOURCES`; that module loads numpy)
Noise = Literal["identified", "paper"]
NOISE_CHOICES: tuple[Noise, ...] = get_args(Noise)


def _seconds(value):
    """A real number as a float (numpy's and whole ones too, so the stored JSON is alike); anything else as given,
    for `GapPlan` to refuse by name."""
    return float(value) if isinstance(value, numbers.Real) and not isinstance(value, bool) else value


@dataclass(frozen=True)
class EvaluationSettings:
    """Settings of an evaluation that change a flight's result.

    Attributes
    ----------
    methods : tuple of str
        Estimators to score, from `models.presets.EVALUATION_METHODS` (``onboard``: the log's own estimate);
        names are read as `models.presets.parse_methods` reads them (case and spaces ignored).
    horizon : int
        MHE window N, samples (at least 1).
    include_bad : bool
        Also score flights that failed the quality checks.
    sg_window : int
        Savitzky–Golay window of the reference states, samples, within `models.presets.SG_WINDOW_RANGE` (an even
        one is used as the next odd length, `ingest.baseline.centred_window`); the paper's 150 (≈ 1.5 s at
        100 Hz) by default.  Shorter windows follow fast manoeuvres (a 1.5-s window clips their velocity peaks).
    gap_s, gap_every_s : float
        The mocap-gap yardstick's gaps: length (0 turns it off) and spacing, s.
    noise : {"identified", "paper"}
        Each model with its own identified noise, or both with the system's fixed noise
        (`estimators.prepared.prepare`).
    gaps : GapPlan
        Where the yardstick hides the mocap, made from ``gap_s`` and ``gap_every_s`` (not an argument).

    Raises
    ------
    InvalidInput
        Naming the setting and the value given, when one is out of its bounds.
    """

    methods: tuple[str, ...] = EVALUATION_METHODS
    horizon: int = MHE_HORIZON
    include_bad: bool = False
    sg_window: int = SG_WINDOW
    gap_s: float = GAP_S
    gap_every_s: float = GAP_EVERY_S
    noise: Noise = "identified"
    gaps: GapPlan = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        given = self.methods
        if isinstance(given, str) or not all(isinstance(m, str) for m in given):
            raise InvalidInput(f"methods must be a list of estimator names, got {given!r}")
        check_mhe_options(self.horizon)
        if not isinstance(self.include_bad, bool):
            raise InvalidInput(f"include_bad must be true or false, got {self.include_bad!r}")
        low, high = SG_WINDOW_RANGE
        if isinstance(self.sg_window, bool) or not isinstance(self.sg_window, numbers.Integral) \
                or not low <= self.sg_window <= high:
            raise InvalidInput(f"sg_window must be {low} to {high} samples, got {self.sg_window!r}")
        if self.noise not in NOISE_CHOICES:
            raise InvalidInput(f"noise must be one of {', '.join(NOISE_CHOICES)}, got {self.noise!r}")
        # frozen: the normalised values are set once, here, as every constructor of the type passes through
        set_ = object.__setattr__
        try:
            methods = parse_methods(",".join(given), EVALUATION_METHODS)
        except InvalidInput as err:   # named, as every other setting's error is
            raise InvalidInput(f"methods: {err}") from None
        set_(self, "methods", tuple(methods))
        set_(self, "horizon", int(self.horizon))
        set_(self, "sg_window", int(self.sg_window))
        plan = GapPlan(_seconds(self.gap_s), _seconds(self.gap_every_s))   # the gap plan's one check
        set_(self, "gaps", plan)
        set_(self, "gap_s", plan.gap_s)
        set_(self, "gap_every_s", plan.every_s)

    def to_json(self) -> dict[str, Any]:
        """The settings as JSON-able values, for where they are stored (`from_json` reads them back)."""
        return {"methods": list(self.methods), "horizon": self.horizon, "include_bad": self.include_bad,
                "sg_window": self.sg_window, "gap_s": self.gap_s, "gap_every_s": self.gap_every_s,
                "noise": self.noise}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]):
        """Stored settings (`to_json`) as the type again; a setting absent from the stored JSON takes its
        default."""
        return cls(**{f.name: data[f.name] for f in fields(cls) if f.init and f.name in data})
