"""What an evaluation says first, and what each yardstick measures (`estimators.yardsticks` computes them).

Apart from the yardsticks so that `estimators.evaluate.summarize` can state the headline without importing
the module that runs the estimators through it.
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from learnest.models.training import NOT_LEARNED
from learnest.records import ReportView

from .metrics import VERDICTS, interval_verdict

MEASURES = {
    "mocap_gaps": "position error (m, RMS of the 3-D error) inside windows where the mocap was hidden from the "
                  "estimator, against the hidden mocap: how well the model carries the estimate through occlusions",
    "fast_reference": "velocity error (m/s, RMS of the 3-D error) outside the gaps against a short-window "
                      "derivative of the raw mocap: how closely the estimate follows the motion",
    "paper_sg": "the MSE over [p, v, a] against a Savitzky-Golay fit of the mocap position (1.5-s window by "
                "default), which is smoother than the motion itself (the paper's protocol and its Table I)",
}
NOTHING_LEARNED = NOT_LEARNED   # the training surfaces' sentence, word for word


# -- over flights -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Headline:
    """What an evaluation says first: the KNODE's gain on the mocap-gap yardstick over the scored flights.

    Attributes
    ----------
    yardstick : str
        "mocap_gaps".
    median_gain_pct : dict
        {"knode-ukf_vs_ukf": median over the flights with gaps of the per-flight gap gain, %, ...}.
    flights_better : dict
        {same keys: number of flights whose gap gain is above 0}.
    flights_worse_beyond_interval : dict
        {same keys: number of flights whose gain's 95 % interval lies wholly below 0}.
    flights_worse_names : dict
        {same keys: [names] of those flights}.
    flights_better_beyond_interval : dict
        {same keys: number of flights whose gain's 95 % interval lies wholly above 0}.
    flights_within_interval : dict
        {same keys: number of flights whose gain's 95 % interval holds 0}.
    flights_undecided : dict
        {same keys: number of scored flights whose gain has no interval: no gap score (too short, turned
        off), one gap, or no prior error in the gaps}.  Never left out: per key, better beyond + worse beyond +
        within + undecided = ``flights_scored``.
    flights_undecided_names : dict
        {same keys: ["name: why", ...] of those flights}.
    flights_scored : int
        Flights the yardstick scored (not excluded), with or without gaps.
    median_rmse_m : dict
        {method: median over the flights with gaps of the gap RMSE, m}.
    flights_with_gaps : int
        Scored flights that had at least one gap.
    flights_without_gaps : list of str
        Scored flights without a gap score ("name: reason").
    gap_s, every_s, start_s : float or None
        The gap plan of the flights (`GapPlan`), s; None when no flight was scored.
    measures : str
        What the yardstick measures, one sentence.
    noise : dict
        {method: "identified" | "paper"}: the noise each method ran with (the report's ``noise``).
    """

    yardstick: str = "mocap_gaps"
    median_gain_pct: dict[str, float | None] = field(default_factory=dict)
    flights_better: dict[str, int] = field(default_factory=dict)
    flights_worse_beyond_interval: dict[str, int] = field(default_factory=dict)
    flights_worse_names: dict[str, list[str]] = field(default_factory=dict)
    flights_better_beyond_interval: dict[str, int] = field(default_factory=dict)
    flights_within_interval: dict[str, int] = field(default_factory=dict)
    flights_undecided: dict[str, int] = field(default_factory=dict)
    flights_undecided_names: dict[str, list[str]] = field(default_factory=dict)
    flights_scored: int = 0
    median_rmse_m: dict[str, float] = field(default_factory=dict)
    flights_with_gaps: int = 0
    flights_without_gaps: list[str] = field(default_factory=list)
    gap_s: float | None = None
    every_s: float | None = None
    start_s: float | None = None
    measures: str = MEASURES["mocap_gaps"]
    noise: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-able dict (the report's ``headline``)."""
        return asdict(self)


class ReportHeadline(dict[str, Any]):
    """A report's ``headline`` as `le.evaluate` returns it: the same JSON-able dict (`Headline.to_dict`), which
    prints as its sentence (`headline_sentence`) and whose repr names its type and the gains, not 15-digit
    floats."""

    def __str__(self) -> str:
        return headline_sentence(self)

    def __repr__(self) -> str:
        gains = {k: None if v is None else round(v, 2) for k, v in (self.get("median_gain_pct") or {}).items()}
        return (f"ReportHeadline(yardstick={self.get('yardstick')!r}, median_gain_pct={gains}, "
                f"flights_better={self.get('flights_better')}, flights_worse_beyond_interval="
                f"{self.get('flights_worse_beyond_interval')}, flights_scored={self.get('flights_scored')}, "
                f"flights_with_gaps={self.get('flights_with_gaps')})")


def _count(n: int | None) -> str:
    return str(n) if n else "none"


def headline_sentence(head: Mapping) -> str:
    """The headline (`Headline.to_dict`) in words: per KNODE and its prior, the median gain in the mocap gaps,
    on how many flights it was better, and how each scored flight's 95 % interval falls."""
    scored, with_gaps = int(head.get("flights_scored") or 0), int(head.get("flights_with_gaps") or 0)
    if not scored:
        return "No flight was scored."
    if not with_gaps:
        return (f"No flight had a mocap gap to score: the KNODE's gain is undecided on all {scored} flight"
                f"{'s' if scored != 1 else ''} scored ({'; '.join(head.get('flights_without_gaps') or [])}).")
    sentences = []
    # the UKF pair first, as every surface orders them
    for key, gain in sorted((head.get("median_gain_pct") or {}).items(), key=lambda item: "mhe" in item[0]):
        if gain is None:
            continue
        knode, prior = (part.upper() for part in key.split("_vs_"))
        n = with_gaps
        sentences.append(
            f"{knode} carried the estimate through mocap gaps {abs(gain):.1f} % {'better' if gain >= 0 else 'worse'} "
            f"than its prior {prior} (median of {n} flight{'s' if n != 1 else ''} with gaps): better on "
            f"{head['flights_better'].get(key, 0)} of {n}; of {scored} flight{'s' if scored != 1 else ''} scored, "
            f"worse beyond its 95 % interval on {_count(head['flights_worse_beyond_interval'].get(key))}, better "
            f"beyond it on {_count(head['flights_better_beyond_interval'].get(key))}, within it on "
            f"{_count(head['flights_within_interval'].get(key))}, undecided (no interval) on "
            f"{_count(head['flights_undecided'].get(key))}."
            + noise_clause(head.get("noise") or {}, knode.lower(), prior.lower()))
    return " ".join(sentences) or "No KNODE ran beside its prior: there is no gain to report."


def noise_clause(noise: Mapping, knode: str, prior: str) -> str:
    """What noise the two sides of a comparison ran with ({method: "identified" | "paper"}), as a sentence
    starting with a space; "" when ``noise`` does not say."""
    if knode not in noise or prior not in noise:
        return ""
    if noise[knode] == noise[prior] == "identified":
        return " Each ran with its own noise, identified on the training flights."
    if noise[knode] == noise[prior] == "paper":
        return " Both ran with the system's fixed noise (the paper's)."
    return (f" Noise: {knode.upper()} {noise[knode]}, {prior.upper()} {noise[prior]}: not tuned the same way, "
            "so not like with like.")


def _pair_keys(flights: Sequence[ReportView]) -> list[str]:
    """The comparisons "knode-ukf_vs_ukf", ... of the flights: those with a gap gain, and those whose KNODE
    and prior both ran (a flight without a gap score still ran them: it counts, undecided)."""
    keys = {k for f in flights for k in f["yardsticks"]["mocap_gaps"].get("gain_pct") or {}}
    keys |= {f"knode-{base}_vs_{base}" for f in flights for base in ("ukf", "mhe")
             if {base, f"knode-{base}"} <= set(f.get("mse") or {})}
    return sorted(keys)


def _undecided_reason(gaps: Mapping, key: str) -> str:
    """Why a flight's gain on ``key`` has no interval, in words."""
    if gaps.get("skipped"):
        return str(gaps["skipped"])
    if (gaps.get("gain_pct") or {}).get(key) is None:
        return "no gap score for this comparison (the prior's error in the gaps is zero, or it did not run)"
    if gaps.get("gaps", 0) < 2:
        return "one gap: an interval needs two"
    return "no interval could be told"


def flight_verdict(flight_report: ReportView, key: str) -> str:
    """The verdict on one scored flight for one comparison ``key`` ("knode-ukf_vs_ukf", ...), one of
    `estimators.metrics.VERDICTS`: where the 95 % interval of the KNODE's gain in the mocap gaps lies
    (`estimators.metrics.interval_verdict`); "undecided" without a gap score or an interval.

    The one measure every surface states per flight: the headline counts these verdicts, and the recommended
    estimate (`estimators.evaluate.recommended_model`) follows them, so the three cannot disagree.

    Parameters
    ----------
    flight_report : mapping
        A scored flight's report entry, with its ``yardsticks.mocap_gaps`` (``gain_pct``, ``gain_interval_pct``).
    key : str
        The comparison, ``"knode-<base>_vs_<base>"``.

    Returns
    -------
    str
        "better", "worse", "within" or "undecided".
    """
    gaps = (flight_report.get("yardsticks") or {}).get("mocap_gaps") or {}
    decided = bool(gaps) and not gaps.get("skipped") and (gaps.get("gain_pct") or {}).get(key) is not None
    return interval_verdict((gaps.get("gain_interval_pct") or {}).get(key) if decided else None)


def flight_verdicts(flight_report: ReportView) -> dict[str, str]:
    """{comparison: `flight_verdict`} for every KNODE that ran beside its prior on one scored flight (a report
    entry with its yardsticks); {} for a prior-only evaluation."""
    return {key: flight_verdict(flight_report, key) for key in _pair_keys([flight_report])}


def headline(flight_reports: Sequence[ReportView]) -> Headline:
    """The `Headline` of per-flight report entries (their ``yardsticks.mocap_gaps``); excluded flights and
    entries without yardsticks are left out.  Every other flight is counted once per comparison: better
    beyond its interval, worse beyond it, within it, or undecided (`estimators.metrics.interval_verdict`)."""
    scored = [f for f in flight_reports if not f.get("excluded") and f.get("yardsticks")]
    with_gaps = [f for f in scored if not f["yardsticks"]["mocap_gaps"].get("skipped")]
    without = [f"{f['flight']}: {f['yardsticks']['mocap_gaps']['skipped']}" for f in scored
               if f["yardsticks"]["mocap_gaps"].get("skipped")]
    gaps = [(f["flight"], f["yardsticks"]["mocap_gaps"]) for f in with_gaps]
    keys = _pair_keys(scored)
    methods = sorted({m for _, g in gaps for m in g["rmse_m"]})
    median_gain, better, worse_names, undecided_names = {}, {}, {}, {}
    counts: dict[str, dict[str, int]] = {verdict: {} for verdict in VERDICTS}
    for key in keys:
        values = [g["gain_pct"][key] for _, g in gaps if g["gain_pct"].get(key) is not None]
        median_gain[key] = float(np.median(values)) if values else None
        better[key] = int(sum(bool(v > 0) for v in values))
        verdicts = [(f["flight"], flight_verdict(f, key), f["yardsticks"]["mocap_gaps"]) for f in scored]
        for verdict in VERDICTS:
            counts[verdict][key] = sum(v == verdict for _, v, _ in verdicts)
        worse_names[key] = [name for name, v, _ in verdicts if v == "worse"]
        undecided_names[key] = [f"{name}: {_undecided_reason(g, key)}" for name, v, g in verdicts if v == "undecided"]
    median_rmse = {m: float(np.median([g["rmse_m"][m] for _, g in gaps if m in g["rmse_m"]])) for m in methods}
    plan = scored[0]["yardsticks"]["mocap_gaps"] if scored else {}
    return Headline(median_gain_pct=median_gain, flights_better=better,
                    flights_worse_beyond_interval=counts["worse"], flights_worse_names=worse_names,
                    flights_better_beyond_interval=counts["better"], flights_within_interval=counts["within"],
                    flights_undecided=counts["undecided"], flights_undecided_names=undecided_names,
                    flights_scored=len(scored), median_rmse_m=median_rmse, flights_with_gaps=len(with_gaps),
                    flights_without_gaps=without, gap_s=plan.get("gap_s"), every_s=plan.get("every_s"),
                    start_s=plan.get("start_s"))


def learned_note(meta: Mapping) -> dict:
    """What an evaluation report says about whether the model learned anything: ``learned`` (the model's
    ``learned`` flag: True, False, or None when the model does not say) and ``learned_note``: the model's
    own note where it recorded one (`models.training.NOT_CHECKED` for a model trained with nothing held out,
    which kept its last epoch unchecked), else `NOT_LEARNED` when it learned nothing, else None."""
    learned = meta.get("learned")
    learned = None if learned is None else bool(learned)
    note = meta.get("learned_note") or (NOTHING_LEARNED if learned is False else None)
    return {"learned": learned, "learned_note": note}
