"""Scoring metrics of every evaluation, yardstick and check: one definition each.

Errors are squared errors of estimates against a reference in the states' own units (m², (m/s)², (m/s²)² for
the 9-state flight models); a *gain* is how much smaller the KNODE's error is than its prior-only
counterpart's, in percent, 100 (1 − knode / prior); its 95 % *interval* is a paired circular block bootstrap
over time on a continuous record (`gain_interval`), and an interval over independent units where the record
comes in them, as the mocap-gap yardstick's gaps (`unit_gain_interval`); a record is *worse beyond its
interval* when the whole interval lies below 0 (the KNODE is worse there beyond what the record's own
variability explains), *better beyond* it when the whole interval lies above 0, *within* it when the interval
holds 0, and *undecided* when it has no interval (`interval_verdict`).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike

from learnest.models.checks import check_sequence

# The state groups of the 9-state flight models x = [p, v, a] (m, m/s, m/s²).
STATE_GROUPS = {"p": slice(0, 3), "v": slice(3, 6), "a": slice(6, 9)}

# Shortest block of the gain's bootstrap, s: longer than the per-step difference of two estimators' squared
# errors stays correlated on real flights (well under this on most NanoBench circles, close to it on a few);
# each record's blocks are 3x its own correlation length, and never shorter than this.
GAIN_BLOCK_S = 2.0
GAIN_MIN_BLOCKS = 3          # a record of fewer blocks has no interval: its resamples would all be alike
GAIN_REPLICATES = 1000
# How `unit_gain_interval` tells the interval from n independent units (gaps), all on the per-unit log ratios
# below GAIN_UNITS_BOOTSTRAP: the Student-t interval below GAIN_UNITS_SIGNED_RANK units (with 5 or fewer, no
# exact distribution-free 95 % interval is finite), the exact signed-rank (Hodges-Lehmann) interval from there,
# and the paired percentile bootstrap over units from GAIN_UNITS_BOOTSTRAP on.  Why: a bootstrap over few gaps
# is too narrow (it cannot show more spread than the gaps have), while these keep the coverage near 95 % from 3
# gaps on (the coverage table of docs/concepts/yardsticks.md, tests/estimators/test_unit_gain_interval.py).
# The t interval assumes normal log ratios and can hold 0 when every gap is worse by widely spread factors; the
# signed-rank interval, exact for any symmetric spread, does not.  Both estimate the typical gap's ratio, not
# the ratio of sums: where the KNODE's effect grows with how hard the gap is, they lose coverage as the gaps
# grow in number, hence the bootstrap from there.
GAIN_UNITS_SIGNED_RANK = 6
GAIN_UNITS_BOOTSTRAP = 30
VERDICTS = ("better", "worse", "within", "undecided")


# -- errors -------------------------------------------------------------------------------------------------
def squared_errors(estimates: ArrayLike, reference: ArrayLike) -> np.ndarray:
    """(estimates − reference)², shape (T, n), in the states' squared units.

    Parameters
    ----------
    estimates, reference : array_like, shape (T, n)
        Estimated and reference states, the same units per column.

    Raises
    ------
    InvalidInput
        On shapes that differ or non-finite values.
    """
    estimates = check_sequence("estimates", estimates)
    reference = check_sequence("reference", reference, rows=len(estimates), cols=estimates.shape[1])
    return (estimates - reference) ** 2


def mse(estimates: ArrayLike, reference: ArrayLike) -> float:
    """Mean squared error over every sample and column of ``estimates`` against ``reference``, both (T, n),
    in the states' squared units; unchecked (a diverged estimate's nan or inf is the score)."""
    return float(np.mean((np.asarray(estimates) - np.asarray(reference)) ** 2))


def group_scores(err2: np.ndarray, groups: dict[str, slice] | None = None) -> dict:
    """``{"mse": overall, "groups": {name: mse}}`` of squared errors ``err2`` (T, n); ``groups`` default to
    `STATE_GROUPS` for 9 states (p in m², v in m²/s², a in m²/s⁴), none otherwise."""
    if groups is None:
        groups = STATE_GROUPS if err2.shape[1] == 9 else {}
    return {"mse": float(err2.mean()), "groups": {name: float(err2[:, cols].mean()) for name, cols in groups.items()}}


def score(estimates: np.ndarray, reference: np.ndarray, groups: dict[str, slice] | None = None) -> dict:
    """`group_scores` of ``estimates`` (T, n) against ``reference`` (T, n), shapes checked."""
    return group_scores(squared_errors(estimates, reference), groups)


def rms_norm(error: ArrayLike) -> float:
    """RMS of the Euclidean norm of the rows of ``error`` (K, 3): sqrt(mean |e|²), in the error's unit; nan for
    no rows."""
    error = np.asarray(error, dtype=float)
    return float(np.sqrt(np.mean(np.sum(error**2, axis=1)))) if len(error) else float("nan")


# -- gains --------------------------------------------------------------------------------------------------
def gain_pct(prior: float, knode: float) -> float:
    """The KNODE's gain over its prior, %: 100 (1 − knode / prior), of two errors (or sums or medians of
    errors) in the same unit; positive when the KNODE's error is smaller.  ``prior`` must not be 0."""
    return float(100.0 * (1.0 - knode / prior))


def correlation_steps(series: np.ndarray, level: float = 0.05) -> int:
    """The first lag (steps) at which the autocorrelation of ``series`` (T,) falls below ``level``; T if never."""
    centred = np.asarray(series, dtype=float) - np.mean(series)
    steps = len(centred)
    spectrum = np.fft.rfft(centred, 2 * steps)                       # zero-padded: the linear autocorrelation
    autocorrelation = np.fft.irfft(spectrum * np.conj(spectrum))[:steps]
    if autocorrelation[0] <= 0:
        return 1
    below = np.flatnonzero(autocorrelation / autocorrelation[0] < level)
    return int(below[0]) if len(below) else steps


def gain_interval(prior_error: ArrayLike, knode_error: ArrayLike, min_block: int,
                  replicates: int = GAIN_REPLICATES, seed: int = 0) -> list[float] | None:
    """95 % interval of the KNODE's MSE gain over its prior on one record, by a paired circular block bootstrap.

    The gain is 100 (1 − Σ knode_error / Σ prior_error).  Both series are resampled with the same blocks of
    consecutive steps, so what the two estimators share (the flight's hard stretches) cancels, and the errors'
    autocorrelation stays inside the blocks: a block is 3 times the lag at which the autocorrelation of the
    per-step difference falls below 0.05 (`correlation_steps`), and at least ``min_block``.  Blocks wrap around
    the record's end (Politis & Romano's circular bootstrap): every step is drawn equally often, where plain
    moving blocks under-draw the first and last steps, which hold the filters' start-up error, and shift the
    interval off the gain.  Each resample is T steps long, its last block cut short.
    Why not ``scipy.stats.bootstrap``: it resamples single observations, which for autocorrelated estimation
    errors gives intervals several times too narrow (`tests/estimators/test_gain_interval.py`).

    Parameters
    ----------
    prior_error, knode_error : array_like, shape (T,)
        Squared estimation error per step (mean over the state's columns), of the prior-only and the KNODE
        estimator on the same steps, in the states' squared units.
    min_block : int
        Shortest block, steps.
    replicates : int
        Bootstrap replicates.
    seed : int
        Seed of the block starts (the interval is reproducible).

    Returns
    -------
    list of float or None
        [2.5 %, 97.5 %] percentiles of the gain, %.  A flight whose upper bound is below 0 is worse with the
        KNODE beyond what the flight's own variability explains (`worse_beyond_interval`).  None when the
        record holds fewer than `GAIN_MIN_BLOCKS` blocks or the prior's error is zero (no interval can be told).
    """
    prior = np.asarray(prior_error, dtype=float).reshape(-1)
    knode = np.asarray(knode_error, dtype=float).reshape(-1)
    steps = len(prior)
    if steps == 0 or not np.sum(prior) > 0:
        return None
    block = max(int(min_block), 3 * correlation_steps(knode - prior), 1)
    if steps < GAIN_MIN_BLOCKS * block:
        return None
    # the sum of each block (starting anywhere, wrapping), from cumulative sums of the record with its first
    # block - 1 steps appended; a resample is n_full whole blocks and one of the remaining length
    n_full, rest = divmod(steps, block)
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, steps, size=(replicates, n_full))
    tail = rng.integers(0, steps, size=replicates)

    def resampled_sums(error: np.ndarray) -> np.ndarray:
        cumulative = np.concatenate([[0.0], np.cumsum(np.concatenate([error, error[:block - 1]]))])
        whole = (cumulative[starts + block] - cumulative[starts]).sum(axis=1)
        return whole + cumulative[tail + rest] - cumulative[tail]

    prior_sum, knode_sum = resampled_sums(prior), resampled_sums(knode)
    gains = 100.0 * (1.0 - knode_sum / np.maximum(prior_sum, np.finfo(float).tiny))
    return [float(np.percentile(gains, 2.5)), float(np.percentile(gains, 97.5))]


def gain_interval_over_time(prior_error: ArrayLike, knode_error: ArrayLike, dt: float) -> list[float] | None:
    """`gain_interval` of two per-step error series (T,) of a record sampled every ``dt`` s, blocks at least
    `GAIN_BLOCK_S` long: the interval every per-flight gain of an evaluation carries."""
    return gain_interval(prior_error, knode_error, round(GAIN_BLOCK_S / dt))


def _signed_rank_limits(log_ratio: np.ndarray, level: float = 0.95) -> tuple[float, float] | None:
    """The exact ``level`` interval of the centre of a symmetric distribution from the sample ``log_ratio``
    (n,): the Hodges-Lehmann interval of the Wilcoxon signed-rank test, between the k-th smallest and k-th
    largest of the n (n + 1) / 2 Walsh averages, k from the statistic's exact null distribution; None when no
    such interval is finite (n ≤ 5 at 95 %)."""
    n = len(log_ratio)
    counts = np.zeros(n * (n + 1) // 2 + 1)
    counts[0] = 1.0
    for rank in range(1, n + 1):          # subsets of the ranks 1..n by their sum: the null distribution of W+
        shifted = counts.copy()
        shifted[rank:] += counts[:-rank]
        counts = shifted
    below = np.cumsum(counts) / 2.0**n
    k = int(np.sum(below <= (1.0 - level) / 2.0))      # P(W+ ≤ k - 1) ≤ (1 - level) / 2
    if k < 1:
        return None
    first, second = np.triu_indices(n)
    walsh = np.sort((log_ratio[first] + log_ratio[second]) / 2.0)
    return float(walsh[k - 1]), float(walsh[len(walsh) - k])


def unit_gain_interval(prior_units: ArrayLike, knode_units: ArrayLike, replicates: int = GAIN_REPLICATES,
                       seed: int = 0) -> list[float] | None:
    """95 % interval of the KNODE's gain over its prior from independent units of one record (the gaps of the
    mocap-gap yardstick), from two of them on.

    The gain is 100 (1 − Σ knode / Σ prior) over the units.  Each unit's error is the sum of its squared
    errors, one number per estimator; the units are independent (the estimate re-converges on the mocap
    between two gaps) and paired (both estimators fly the same gap).  A gap's error scales with how hard it
    is (a fast turn drifts more for both estimators) and the KNODE's effect is a factor on it, so the small-
    sample intervals work on the per-unit log ratios log(knode / prior), which remove the shared difficulty:

    - 2 to 5 units: the Student-t interval (n − 1 degrees of freedom) of their mean.  No exact
      distribution-free 95 % interval is finite from so few; a bootstrap over them is too narrow (it cannot
      show more spread than the few units have, and covers the true gain far less often than 95 %).
    - `GAIN_UNITS_SIGNED_RANK` (6) to `GAIN_UNITS_BOOTSTRAP` − 1 units: the exact interval of the Wilcoxon
      signed-rank test (Hodges-Lehmann), valid for any symmetric spread of the log ratios; it does not take
      them for normal, which a few far-off gaps are not.
    - From `GAIN_UNITS_BOOTSTRAP` (30) units on: the paired percentile bootstrap over units of the gain
      itself (both estimators' units resampled together), whose target is the ratio of sums the gain reports.

    Each interval on the log ratio is mapped to a gain, 100 (1 − exp(·)), and every interval is widened to
    hold the record's gain where it lies outside (the log-ratio intervals estimate the typical unit's ratio,
    the gain weights the hard units more), so "worse beyond the interval" never contradicts the gain's sign.
    Coverage measured in `tests/estimators/test_unit_gain_interval.py`.

    Parameters
    ----------
    prior_units, knode_units : array_like, shape (n,)
        Each unit's summed squared error of the prior-only and the KNODE estimator, in the states' squared
        units (m² for the gaps' position).
    replicates : int
        Bootstrap replicates (from `GAIN_UNITS_BOOTSTRAP` units on).
    seed : int
        Seed of the bootstrap (the interval is reproducible).

    Returns
    -------
    list of float or None
        [low, high], %, or None when no interval can be told: fewer than 2 units, or no prior error at all.
        A unit with zero error on one side counts as the smallest positive number (its log ratio is huge,
        and so is the interval).
    """
    prior = np.asarray(prior_units, dtype=float).reshape(-1)
    knode = np.asarray(knode_units, dtype=float).reshape(-1)
    units = len(prior)
    if units < 2 or len(knode) != units or not np.sum(prior) > 0 or not np.all(np.isfinite(prior + knode)):
        return None
    gain = gain_pct(float(np.sum(prior)), float(np.sum(knode)))
    if units < GAIN_UNITS_BOOTSTRAP:
        tiny = np.finfo(float).tiny
        log_ratio = np.log(np.maximum(knode, tiny)) - np.log(np.maximum(prior, tiny))
        limits = _signed_rank_limits(log_ratio) if units >= GAIN_UNITS_SIGNED_RANK else None
        if limits is None:
            from scipy.stats import t as student_t

            half = float(student_t.ppf(0.975, units - 1) * np.std(log_ratio, ddof=1) / np.sqrt(units))
            centre = float(np.mean(log_ratio))
            limits = (centre - half, centre + half)
        low, high = 100.0 * (1.0 - np.exp(limits[1])), 100.0 * (1.0 - np.exp(limits[0]))
    else:
        draws = np.random.default_rng(seed).integers(0, units, size=(replicates, units))
        gains = 100.0 * (1.0 - knode[draws].sum(axis=1) / np.maximum(prior[draws].sum(axis=1), np.finfo(float).tiny))
        low, high = np.percentile(gains, 2.5), np.percentile(gains, 97.5)
    return [float(min(low, gain)), float(max(high, gain))]


def unit_interval_method(units: int) -> str | None:
    """How `unit_gain_interval` tells the interval of a record of ``units`` units, in words (None: it cannot)."""
    if units < 2:
        return None
    if units < GAIN_UNITS_SIGNED_RANK:
        return f"Student-t interval of the {units} per-gap log ratios"
    if units < GAIN_UNITS_BOOTSTRAP:
        return f"exact signed-rank (Hodges-Lehmann) interval of the {units} per-gap log ratios"
    return f"paired percentile bootstrap over the {units} gaps"


# -- counting over records ------------------------------------------------------------------------------------
def worse_beyond_interval(interval: Sequence[float] | None) -> bool:
    """True when the gain's 95 % interval [low, high] (%) lies wholly below 0; False for None (no interval)."""
    return interval is not None and interval[1] < 0


def better_beyond_interval(interval: Sequence[float] | None) -> bool:
    """True when the gain's 95 % interval [low, high] (%) lies wholly above 0; False for None (no interval)."""
    return interval is not None and interval[0] > 0


def interval_verdict(interval: Sequence[float] | None) -> str:
    """What a record's gain interval [low, high] (%) says, one of `VERDICTS`: "worse" (wholly below 0),
    "better" (wholly above 0), "within" (it holds 0) or "undecided" (None: no interval could be told).
    Every record falls in exactly one, so the counts over records add up to the records."""
    if interval is None:
        return "undecided"
    if worse_beyond_interval(interval):
        return "worse"
    return "better" if better_beyond_interval(interval) else "within"
