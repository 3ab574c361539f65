"""The KNODE's gain over its prior with a 95 % interval (estimators.evaluate.gain_interval): paired, and wide
enough for autocorrelated errors, against known answers."""
import numpy as np

from learnest.estimators.evaluate import gain_interval


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
    low, high = gain_interval(prior, 0.8 * prior, block=200)
    assert abs(low - 20.0) < 1e-9 and abs(high - 20.0) < 1e-9


def test_the_interval_covers_the_true_gain_of_autocorrelated_errors_where_single_samples_do_not():
    """Errors correlated over ~20 steps (AR(1), φ = 0.95), true gain 1 − σ_k²/σ_p² = 19 %: the 2-s-like
    blocks cover it about 95 % of the time; resampling single steps (block 1) misses it far more often."""
    rng = np.random.default_rng(1)
    covered = {200: 0, 1: 0}
    trials = 150
    for _ in range(trials):
        prior = _ar1(rng, 3000, 0.95, 1.0) ** 2
        knode = _ar1(rng, 3000, 0.95, 0.9) ** 2
        for block in covered:
            low, high = gain_interval(prior, knode, block=block, replicates=400, seed=int(rng.integers(1 << 30)))
            covered[block] += low <= 19.0 <= high
    assert covered[200] / trials > 0.85
    assert covered[1] / trials < 0.6
