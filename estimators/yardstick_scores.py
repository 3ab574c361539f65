"""What the yardsticks of one flight give (`FlightYardsticks`: mocap gaps, fast reference, the paper's SG score),
as types of plain numbers: `estimators.yardsticks` computes them, an evaluation's report (`evaluation_report`)
names them, and neither needs the other's imports."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from learnest.models.presets import GAP_EVERY_S, GAP_S, GAP_START_S

from .headline import MEASURES

# The fast reference's Savitzky–Golay windows, s: 5 samples at 100 Hz for the velocity (its noise from 1 mm
# of mocap noise ~0.03 m/s), 15 for the acceleration (a second derivative needs more samples: ~0.15 m/s²).
FAST_VELOCITY_WINDOW_S = 0.05
FAST_ACCELERATION_WINDOW_S = 0.15


@dataclass(frozen=True)
class MocapGaps:
    """The mocap-gap yardstick of one flight.

    Attributes
    ----------
    rmse_m : dict
        {method: RMS of the 3-D position error inside the gaps, m}.
    gain_pct : dict
        {"knode-ukf_vs_ukf": 100 (1 − Σ|e_knode|² / Σ|e_prior|²) over the gap samples, %, ...}: the gain in
        mean squared gap error (the same quantity as the interval); None where the prior's error is zero.
    gain_interval_pct : dict
        {same keys: [low, high] 95 % interval, %, over the gaps as independent units, or None when it cannot be
        told (one gap, or no prior error)} (`gap_gain`, `estimators.metrics.unit_gain_interval`).
    interval_method : str or None
        How the intervals were told (`estimators.metrics.unit_interval_method`), None without one.
    gap_s, every_s, start_s : float
        The plan (`GapPlan`), s.
    gaps : int
        Gaps scored.
    ms_per_step : dict
        {method: wall time of the gap-masked run per sample, ms} (the cost of this yardstick).
    skipped : str or None
        Why the flight has no gap score (too short; turned off), else None.
    """

    rmse_m: dict[str, float] = field(default_factory=dict)
    gain_pct: dict[str, float | None] = field(default_factory=dict)
    gain_interval_pct: dict[str, list[float] | None] = field(default_factory=dict)
    interval_method: str | None = None
    gap_s: float = GAP_S
    every_s: float = GAP_EVERY_S
    start_s: float = GAP_START_S
    gaps: int = 0
    ms_per_step: dict[str, float] = field(default_factory=dict)
    skipped: str | None = None
    measures: str = MEASURES["mocap_gaps"]

    def to_dict(self) -> dict:
        """JSON-able dict (the report's ``yardsticks.mocap_gaps``)."""
        return asdict(self)


@dataclass(frozen=True)
class FastReference:
    """The fast-reference yardstick of one flight.

    Attributes
    ----------
    velocity_rmse_m_s : dict
        {method: RMS of the 3-D velocity error outside the gaps, m/s}, ``onboard`` included where logged.
    acceleration_rmse_m_s2 : dict
        {method: the same for the acceleration, m/s²} (``onboard`` where its acceleration is logged).
    window_s : float
        The velocity derivative's window, s.
    acceleration_window_s : float
        The acceleration derivative's window, s.
    samples : int
        Samples scored (outside the gaps).
    """

    velocity_rmse_m_s: dict[str, float] = field(default_factory=dict)
    acceleration_rmse_m_s2: dict[str, float] = field(default_factory=dict)
    window_s: float = FAST_VELOCITY_WINDOW_S
    acceleration_window_s: float = FAST_ACCELERATION_WINDOW_S
    samples: int = 0
    measures: str = MEASURES["fast_reference"]

    def to_dict(self) -> dict:
        """JSON-able dict (the report's ``yardsticks.fast_reference``)."""
        return asdict(self)


@dataclass(frozen=True)
class PaperSG:
    """The paper's score of one flight: ``mse`` {method: MSE over [p, v, a] against the SG references, in
    the states' squared SI units} (the report's per-flight ``mse``), ``window_s`` the SG window, s."""

    mse: dict[str, float] = field(default_factory=dict)
    window_s: float | None = None
    measures: str = MEASURES["paper_sg"]

    def to_dict(self) -> dict:
        """JSON-able dict (the report's ``yardsticks.paper_sg``)."""
        return asdict(self)


@dataclass(frozen=True)
class FlightYardsticks:
    """The three yardsticks of one flight, the gap score first."""

    mocap_gaps: MocapGaps
    fast_reference: FastReference
    paper_sg: PaperSG

    def to_dict(self) -> dict:
        """``{"mocap_gaps": {...}, "fast_reference": {...}, "paper_sg": {...}}``."""
        return {"mocap_gaps": self.mocap_gaps.to_dict(), "fast_reference": self.fast_reference.to_dict(),
                "paper_sg": self.paper_sg.to_dict()}
