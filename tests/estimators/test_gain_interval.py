"""The KNODE's gain over its prior with a 95 % interval (estimators.metrics.gain_interval): paired, and wide
enough for autocorrelated errors, against known answers."""
import numpy as np

from learnest.estimators.metrics import correlation_steps, gain_interval


def _ar1(rng, steps: int, phi: float, std: float) -> np.ndarray:
    """A stationary AR(1) series of the given marginal standard deviation."""
    shocks = rng.normal(0.0, std * np.sqrt(1.0 - phi**2), steps)
    out = np.empty(steps)
    out[0] = rng.normal(0.0, std)
    for k in range(1, steps):
        out[k] = phi * out[k - 1] + shocks[k]
    return out


def test_a_knode_whose_error_is_a_fixed_fraction_of_the_prior_s_has_that_gain_and_no_spread():
    """Paired resampling: the same blocks of both series, so a step-by-step 20 % smaller error is 20 % in
    every replicate, however uneven the errors are along the flight."""
    prior = np.random.default_rng(0).gamma(0.5, 2.0, 3000) ** 3
    low, high = gain_interval(prior, 0.8 * prior, min_block=200)
    assert abs(low - 20.0) < 1e-9 and abs(high - 20.0) < 1e-9


def _iid_interval(prior, knode, rng, replicates=400):
    """What resampling single steps (scipy.stats.bootstrap's scheme) gives."""
    rows = rng.integers(0, len(prior), size=(replicates, len(prior)))
    gains = 100.0 * (1.0 - knode[rows].sum(axis=1) / prior[rows].sum(axis=1))
    return np.percentile(gains, [2.5, 97.5])


def test_the_interval_covers_the_true_gain_of_autocorrelated_errors_where_single_samples_do_not():
    """Errors correlated over ~20 steps (AR(1), φ = 0.95), true gain 1 − σ_k²/σ_p² = 19 %: blocks of 2 s (200
    steps) or of the data's own correlation length (min_block 1) cover it about 95 % of the time; resampling
    single steps misses it far more often."""
    rng = np.random.default_rng(1)
    covered = {"2 s": 0, "own length": 0, "single steps": 0}
    trials = 150
    for _ in range(trials):
        prior = _ar1(rng, 3000, 0.95, 1.0) ** 2
        knode = _ar1(rng, 3000, 0.95, 0.9) ** 2
        intervals = {"2 s": gain_interval(prior, knode, 200, replicates=400, seed=int(rng.integers(1 << 30))),
                     "own length": gain_interval(prior, knode, 1, replicates=400, seed=int(rng.integers(1 << 30))),
                     "single steps": _iid_interval(prior, knode, rng)}
        for name, (low, high) in intervals.items():
            covered[name] += low <= 19.0 <= high
    assert covered["2 s"] / trials > 0.85 and covered["own length"] / trials > 0.85, covered
    assert covered["single steps"] / trials < 0.6, covered


def test_the_correlation_length_of_an_ar1_series_and_no_interval_for_a_record_of_few_blocks():
    """AR(1) with φ = 0.95: the autocorrelation φ^k falls below 0.05 at k = ln 0.05 / ln 0.95 ≈ 58 steps.  A
    record shorter than three blocks, or a prior without error, gets None (never flagged)."""
    rng = np.random.default_rng(2)
    assert 50 <= correlation_steps(_ar1(rng, 100_000, 0.95, 1.0)) <= 67
    assert correlation_steps(rng.normal(size=10_000)) == 1
    prior = _ar1(rng, 3000, 0.95, 1.0) ** 2
    knode = _ar1(rng, 3000, 0.95, 0.9) ** 2
    assert gain_interval(prior, knode, 200) is not None
    assert gain_interval(prior[:500], knode[:500], 200) is None
    assert gain_interval(np.zeros(3000), knode, 200) is None
