"""The answer of a report in one sentence, the same on every surface: the evaluation report page, the
diagnosis page, `learnest evaluate`'s and `learnest diagnose`'s text and the demo.

An evaluation leads with the mocap-gap yardstick when the report carries it (the top-level ``headline``
and each flight's ``yardsticks.mocap_gaps``: how well the estimate is carried through windows where the
mocap is hidden, scored against the hidden mocap), and otherwise with the paper's yardstick, the MSE
against the Savitzky-Golay references.  Either way the sentence says which yardstick it is, the median
gain of each KNODE over its own prior, on how many flights it was better, and how every scored flight's own
95 % interval falls: worse beyond it, better beyond it, within it, or undecided (no interval could be told);
those four counts add up to the flights scored.

Everything here is plain dicts and strings (no figures, no templates) read from a report: the science's
wording of its own answer, so it sits with the workflows, where the web pages and the CLI both import it.
"""
from __future__ import annotations

import math
from statistics import median
from typing import Any

from learnest.estimators.headline import noise_clause
from learnest.estimators.metrics import VERDICTS, gain_pct, interval_verdict

PAIRS = (("knode-ukf", "ukf"), ("knode-mhe", "mhe"))   # (KNODE, its prior-only method)

# What each yardstick measures, in one sentence (shown under the headline).
YARDSTICK_TEXT = {
    "mocap_gaps": "position error inside windows where the mocap was hidden from the estimators, scored "
                  "against the hidden mocap: how well each model carries the estimate through an occlusion",
    "paper_sg": "MSE over [p, v, a] against the paper's Savitzky-Golay fit of the mocap (a smoothed "
                "reference: it flattens fast motion, so it understates differences between methods)",
}


def pair_key(knode: str, prior: str) -> str:
    """The report's key of a comparison: "knode-ukf_vs_ukf"."""
    return f"{knode}_vs_{prior}"


def _scored(report: dict) -> list[dict]:
    return [f for f in report.get("flights", []) if not f.get("excluded")]


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


def _gap_rows(report: dict, key: str) -> list[dict]:
    """Per scored flight with a gap score: name, gain (%), its 95 % interval or None."""
    rows = []
    for f in _scored(report):
        gaps = (f.get("yardsticks") or {}).get("mocap_gaps") or {}
        gain = (gaps.get("gain_pct") or {}).get(key)
        if gain is not None and _finite(gain):
            rows.append({"flight": f["flight"], "gain_pct": float(gain),
                         "interval_pct": (gaps.get("gain_interval_pct") or {}).get(key)})
    return rows


def _mse_rows(report: dict, knode: str, prior: str) -> list[dict]:
    """Per scored flight with both MSEs: name, gain 100 (1 - knode / prior) in %, its 95 % interval or None."""
    rows = []
    for f in _scored(report):
        mse = f.get("mse") or {}
        if _finite(mse.get(knode)) and _finite(mse.get(prior)) and mse[prior] > 0:
            rows.append({"flight": f["flight"], "gain_pct": gain_pct(mse[prior], mse[knode]),
                         "interval_pct": (f.get("gain_interval_pct") or {}).get(pair_key(knode, prior))})
    return rows


def _verdict_counts(rows: list[dict], scored: int) -> dict[str, int]:
    """{verdict: flights} of ``rows`` by their intervals (`interval_verdict`); the ``scored`` flights without a
    row (no gain to tell) are undecided too."""
    counts = {verdict: sum(interval_verdict(r["interval_pct"]) == verdict for r in rows) for verdict in VERDICTS}
    counts["undecided"] += scored - len(rows)
    return counts


def evaluation_headline(report: dict) -> dict:
    """The answer of an evaluation report (evaluate_flights' JSON).

    Returns
    -------
    dict
        ``yardstick`` ("mocap_gaps" or "paper_sg"), ``measures`` (what it measures, one sentence),
        ``sentence`` (the first comparison's, or why there is none), and ``pairs``: per KNODE that ran with
        its prior, ``knode``, ``prior``, ``key``, ``median_gain_pct``, ``better``, ``worse_beyond_interval``,
        ``better_beyond_interval``, ``within_interval``, ``undecided`` (flights whose gain has no interval)
        and ``undecided_names`` (["name: why"]), ``scored`` (flights scored: the four counts add up to it),
        ``flights`` (how many have a gain on this yardstick), ``rows`` (per flight ``flight``, ``gain_pct``,
        ``interval_pct`` [low, high] or None) and ``sentence``.  Gains are in %, positive: the KNODE's error
        is lower than its prior's.
    """
    given = report.get("headline") or {}
    gaps = given.get("yardstick") == "mocap_gaps"
    pairs = []
    for knode, prior in PAIRS:
        key = pair_key(knode, prior)
        rows = _gap_rows(report, key) if gaps else _mse_rows(report, knode, prior)
        if not rows:
            continue
        scored = len(_scored(report))
        counts = _verdict_counts(rows, scored)
        undecided_names = [f"{r['flight']}: no interval" for r in rows if r["interval_pct"] is None]
        if gaps:   # the service's own counts: the JSON, the page and the CLI say the same numbers
            mid = (given.get("median_gain_pct") or {}).get(key)
            better = (given.get("flights_better") or {}).get(key)
            worse = (given.get("flights_worse_beyond_interval") or {}).get(key)
            given_counts = {"better": (given.get("flights_better_beyond_interval") or {}).get(key),
                            "within": (given.get("flights_within_interval") or {}).get(key),
                            "undecided": (given.get("flights_undecided") or {}).get(key)}
            # the headline's own four counts; a report stored before it carried them is told from its rows
            if all(isinstance(v, int) for v in given_counts.values()):
                counts.update({verdict: value for verdict, value in given_counts.items() if isinstance(value, int)})
                scored = int(given.get("flights_scored", scored))
                undecided_names = list((given.get("flights_undecided_names") or {}).get(key) or [])
        else:
            mid = (report.get("improvement_pct") or {}).get(key)   # the medians' ratio, as the tables show it
            better = worse = None
        mid = float(mid) if mid is not None and _finite(mid) else median(r["gain_pct"] for r in rows)
        better = int(better) if isinstance(better, int) else sum(r["gain_pct"] > 0 for r in rows)
        worse = int(worse) if isinstance(worse, int) else counts["worse"]
        pair: dict[str, Any] = {"knode": knode, "prior": prior, "key": key, "median_gain_pct": mid, "better": better,
                                "worse_beyond_interval": worse, "better_beyond_interval": counts["better"],
                                "within_interval": counts["within"], "undecided": counts["undecided"],
                                "undecided_names": undecided_names, "scored": scored, "flights": len(rows),
                                "rows": rows}
        pair["sentence"] = _sentence(pair, gaps) + noise_clause(report.get("noise") or {}, knode, prior)
        pairs.append(pair)
    yardstick = "mocap_gaps" if gaps else "paper_sg"
    if pairs:
        sentence = pairs[0]["sentence"]
    elif gaps and any((given.get("flights_undecided") or {}).values()):
        scored = int(given.get("flights_scored") or len(_scored(report)))
        reasons = "; ".join(given.get("flights_without_gaps") or [])
        sentence = (f"No flight had a mocap gap to score: the KNODE's gain is undecided (no interval) on all "
                    f"{scored} flight{'s' if scored != 1 else ''} scored ({reasons}).")
    elif _scored(report):
        sentence = "No KNODE ran beside its prior: there is no gain to report (run ukf with knode-ukf, or mhe " \
                   "with knode-mhe)."
    else:
        sentence = "No flight was scored: see the reasons in the table."
    if report.get("learned") is False:
        sentence += " The residual did not improve held-out prediction in training: this version equals its prior."
    return {"yardstick": yardstick, "measures": YARDSTICK_TEXT[yardstick], "sentence": sentence, "pairs": pairs}


def gap_methods(report: dict) -> list[str]:
    """The methods scored on the mocap-gap yardstick in any flight of ``report`` (priors next to their KNODE)."""
    found = {m for f in _scored(report)
             for m in (((f.get("yardsticks") or {}).get("mocap_gaps") or {}).get("rmse_m") or {})}
    order = ["ukf", "knode-ukf", "mhe", "knode-mhe"]
    return [m for m in order if m in found] + sorted(found - set(order))


def _interval_text(rows: list[dict]) -> str:
    """The spread of the flights' gains: "flights from -3 % to +25 %" (a single flight: its interval)."""
    if len(rows) == 1:
        ci = rows[0]["interval_pct"]
        return f"95 % interval [{ci[0]:+.1f}, {ci[1]:+.1f}] %" if ci else "one flight, no interval"
    gains = [r["gain_pct"] for r in rows]
    low, high = f"{min(gains):+.1f}", f"{max(gains):+.1f}"
    return f"{low} % on every flight" if low == high else f"flights from {low} % to {high} %"


def _sentence(pair: dict, gaps: bool) -> str:
    knode, prior, n = pair["knode"].upper(), pair["prior"].upper(), pair["flights"]
    gain = pair["median_gain_pct"]
    how = f"{abs(gain):.1f} % {'better' if gain >= 0 else 'worse'} than its prior {prior}"
    what = (f"{knode} carried the estimate through mocap gaps {how}" if gaps else
            f"{knode} scored {how} on the paper's Savitzky-Golay MSE")
    worse = pair["worse_beyond_interval"]
    scored = pair["scored"]
    return (f"{what} (median of {n} flight{'s' if n != 1 else ''}; {_interval_text(pair['rows'])}): better on "
            f"{pair['better']} of {n}; of {scored} flight{'s' if scored != 1 else ''} scored, worse beyond its 95 % "
            f"interval on {worse or 'none'}, better beyond it on {pair['better_beyond_interval'] or 'none'}, "
            f"within it on {pair['within_interval'] or 'none'}, undecided (no interval) on "
            f"{pair['undecided'] or 'none'}.")


# -- the diagnosis --------------------------------------------------------------------------------------
def diagnosis_split(report: dict, flight_names: list[str] | None = None) -> dict:
    """Which flights the diagnosis fitted its effects on and which it scored, as the code split them.

    ``report``'s ``fitting_flights`` / ``scored_flights`` when it has them; else the scored flights are the
    names in ``per_flight`` and the fitting ones the rest of ``flight_names`` (the diagnosis' flights in
    order).  One flight is both: fitted on its first 60 %, scored on the rest (``split`` says so).

    Returns
    -------
    dict
        ``fitting`` and ``scored`` (lists of names) and ``text`` (the report's ``split`` sentence).
    """
    scored = list(report.get("scored_flights") or [p["flight"] for p in report.get("per_flight", [])])
    fitting = report.get("fitting_flights")
    if fitting is None:
        names = [n for n in (flight_names or []) if n is not None]
        fitting = [n for n in names if n not in scored] or names[:1]
    return {"fitting": list(fitting), "scored": scored, "text": report.get("split") or ""}


def diagnosis_headline(report: dict) -> str:
    """The diagnosis' answer in one sentence: what it found and whether adding it helped on held-out data."""
    effects = [e["id"] for e in report.get("effects", [])]
    found = (f"Found {', '.join(effects)}" if effects else
             "Found no effect that explains the residual better than noise")
    before, after = report.get("before") or {}, report.get("after") or {}
    improved = report.get("improved_flights") or {}
    key = next((k for k in ("specific_force_rmse", "knode-ukf", "ukf", "knode-mhe", "mhe")
                if _finite(before.get(k)) and _finite(after.get(k))), None)
    if key is None:
        return found + "."
    change = gain_pct(before[key], after[key]) if before[key] else 0.0
    what = ("the specific force predicted from the inputs" if key == "specific_force_rmse"
            else f"{key.upper()}'s MSE")
    on = f" (better on {improved[key]} flights)" if key in improved else ""
    return (f"{found}; with {'it' if len(effects) == 1 else 'them'} {what} on the scored flights is "
            f"{abs(change):.1f} % {'better' if change >= 0 else 'worse'}{on}." if effects else
            f"{found}; {what} on the scored flights: {before[key]:.4g} before, {after[key]:.4g} after{on}.")
