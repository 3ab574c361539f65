"""The gain's 95 % interval over the gaps of the mocap-gap yardstick (estimators.metrics.unit_gain_interval):
every flight with two gaps or more gets one, and it covers a known gain at its nominal rate from 3 gaps to 50
(Student-t below 6 gaps, exact signed-rank from 6, bootstrap over gaps from 30)."""
import numpy as np
import pytest

from learnest.estimators.headline import headline
from learnest.estimators.metrics import (
    GAIN_UNITS_BOOTSTRAP,
    GAIN_UNITS_SIGNED_RANK,
    interval_verdict,
    unit_gain_interval,
    unit_interval_method,
)
from learnest.estimators.yardsticks import gap_gain, per_gap_sums

GAP_SAMPLES = 50          # a 0.5-s gap at 100 Hz
REPLICATES = 400


def _gap_errors(rng, gaps: int, ratio: float, correlation: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Per-sample squared position errors (gaps * GAP_SAMPLES,) of a prior and a KNODE coasting through
    ``gaps`` gaps: each starts the gap with a velocity error and keeps an acceleration error, e(t) = v t +
    b t² / 2 (3-D), so its squared error grows through the gap.  Gaps differ in difficulty (a lognormal scale
    shared by both estimators) and the two estimators' errors are correlated (the same hard stretch); the
    KNODE's error vectors are sqrt(ratio) times the prior's in distribution, so the true ratio of expected
    gap errors is ``ratio`` and the true gain is 100 (1 - ratio)."""
    t = np.arange(1, GAP_SAMPLES + 1) * 0.01
    difficulty = rng.lognormal(0.0, 0.8, gaps)[:, None]      # on the squared error

    def drift(shared: np.ndarray) -> np.ndarray:     # (gaps, 2, 3) -> (gaps, samples) squared error
        own = correlation * shared + np.sqrt(1 - correlation**2) * rng.standard_normal(shared.shape)
        v, b = 0.05 * own[:, 0], 0.5 * own[:, 1]     # m/s, m/s²
        e = v[:, None, :] * t[None, :, None] + 0.5 * b[:, None, :] * t[None, :, None] ** 2
        return np.sum(e**2, axis=2)

    shared = rng.standard_normal((gaps, 2, 3))
    prior = difficulty * drift(shared)
    knode = ratio * difficulty * drift(shared)
    return prior.reshape(-1), knode.reshape(-1)


def _windows(gaps: int) -> list[tuple[int, int]]:
    return [(k * GAP_SAMPLES, (k + 1) * GAP_SAMPLES) for k in range(gaps)]


@pytest.mark.parametrize("gaps", [3, 5, 6, 11, 20, 50])
@pytest.mark.parametrize("true_gain", [20.0, -30.0])
def test_the_interval_over_gaps_covers_a_known_gain_about_95_percent_of_the_time(gaps, true_gain):
    """400 seeded flights of simulated gap errors with a known true gain: the 95 % interval covers it in
    90-99 % of them, with 3 and 5 gaps (Student-t of the log ratios), 6 to 20 (signed-rank) and 50 (bootstrap
    over the gaps); every flight gets one, and it holds the flight's own gain."""
    rng = np.random.default_rng(gaps * 1000 + int(true_gain))
    covered = 0
    for replicate in range(REPLICATES):
        prior, knode = _gap_errors(rng, gaps, 1.0 - true_gain / 100.0)
        gain, interval = gap_gain(prior, knode, _windows(gaps))
        assert interval is not None and interval[0] <= gain <= interval[1]
        covered += interval[0] <= true_gain <= interval[1]
    print(f"{gaps} gaps, true gain {true_gain:+.0f} %: coverage {covered / REPLICATES:.3f}")
    assert 0.90 <= covered / REPLICATES <= 0.99


def test_the_bootstrap_takes_over_from_many_gaps_and_both_are_paired():
    """A KNODE whose every gap error is 0.8 times the prior's has a gain of 20 % and no spread, with either
    method; the per-gap sums are the gaps' own."""
    rng = np.random.default_rng(3)
    for gaps in (2, GAIN_UNITS_SIGNED_RANK - 1, GAIN_UNITS_SIGNED_RANK, GAIN_UNITS_BOOTSTRAP - 1,
                 GAIN_UNITS_BOOTSTRAP, 80):
        prior = rng.lognormal(0.0, 1.0, gaps)
        assert unit_gain_interval(prior, 0.8 * prior) == pytest.approx([20.0, 20.0])
    err2 = np.arange(6.0)
    assert per_gap_sums(err2, [(10, 12), (20, 24)]).tolist() == [1.0, 2.0 + 3.0 + 4.0 + 5.0]


def test_six_gaps_all_worse_by_uneven_factors_are_worse_beyond_the_interval():
    """A KNODE with a constant acceleration error (tests/models/test_residual_scale.py) is worse than its
    prior in each of 6 gaps, by factors from 1.4 to 210: the exact signed-rank interval says so (every sign
    alike has probability 2 / 64), where a t interval, which takes the log ratios for normal, holds 0."""
    prior = np.ones(6)
    knode = np.array([1.38, 1.41, 209.75, 4.37, 3.23, 117.75])
    low, high = unit_gain_interval(prior, knode)
    assert high < 0 and interval_verdict([low, high]) == "worse"
    assert high == pytest.approx(-38.0) and low == pytest.approx(100 * (1 - 209.75))   # the extreme gaps' ratios
    assert "signed-rank" in unit_interval_method(6) and "Student-t" in unit_interval_method(5)
    assert "bootstrap" in unit_interval_method(GAIN_UNITS_BOOTSTRAP) and unit_interval_method(1) is None


def test_no_interval_only_for_one_gap_or_no_prior_error_and_that_flight_is_undecided():
    prior, knode = _gap_errors(np.random.default_rng(4), 2, 0.8)
    assert unit_gain_interval(prior[:1], knode[:1]) is None                 # one unit
    assert gap_gain(prior[:GAP_SAMPLES], knode[:GAP_SAMPLES], _windows(1))[1] is None
    assert gap_gain(np.zeros_like(prior), knode, _windows(2)) == (None, None)
    assert gap_gain(prior, knode, _windows(2))[1] is not None               # two gaps are enough
    assert [interval_verdict(i) for i in ([-9, -1], [1, 9], [-1, 9], None)] == ["worse", "better", "within",
                                                                               "undecided"]


def _flight(name, gain=None, interval=None, gaps=3, skipped=None):
    mocap = {"rmse_m": {} if skipped else {"ukf": 0.02, "knode-ukf": 0.02},
             "gain_pct": {} if skipped or gain is None else {"knode-ukf_vs_ukf": gain},
             "gain_interval_pct": {} if skipped else {"knode-ukf_vs_ukf": interval},
             "gaps": 0 if skipped else gaps, "gap_s": 0.5, "every_s": 2.5, "start_s": 5.0, "skipped": skipped}
    return {"flight": name, "mse": {"ukf": 1e-3, "knode-ukf": 1e-3}, "yardsticks": {"mocap_gaps": mocap}}


def test_the_headline_counts_every_scored_flight_once():
    """Better beyond, worse beyond, within and undecided add up to the flights scored: a flight too short for
    a gap, one with a single gap and one whose prior had no gap error are undecided, with the reason."""
    flights = [_flight("better", 30.0, [10.0, 45.0]), _flight("worse1", -33.0, [-50.0, -12.0], gaps=11),
               _flight("worse2", -22.0, [-40.0, -3.0], gaps=11), _flight("within", 5.0, [-10.0, 20.0]),
               _flight("one_gap", 8.0, None, gaps=1), _flight("zero_prior", None, None),
               _flight("short", skipped="the kept flight is 4.0 s long, too short for one mocap gap"),
               {"flight": "excluded", "excluded": True, "reason": "training flight"}]
    head = headline(flights).to_dict()
    key = "knode-ukf_vs_ukf"
    assert head["flights_scored"] == 7
    assert (head["flights_better_beyond_interval"][key], head["flights_worse_beyond_interval"][key],
            head["flights_within_interval"][key], head["flights_undecided"][key]) == (1, 2, 1, 3)
    assert head["flights_worse_names"][key] == ["worse1", "worse2"]
    assert [n.split(":")[0] for n in head["flights_undecided_names"][key]] == ["one_gap", "zero_prior", "short"]
    assert "one gap" in head["flights_undecided_names"][key][0]
    assert "too short" in head["flights_undecided_names"][key][2]
    assert head["flights_with_gaps"] == 6 and head["flights_better"][key] == 3
