"""`ingest.align`'s reading of a log's start and of its streams' timing, against known answers."""
import numpy as np

from learnest.ingest.align import GAP_STEPS, started_in_air, stream_timing

RATE_HZ = 100.0


def _head(z, rng_seed=0):
    t = np.arange(0.0, 6.0, 1.0 / RATE_HZ)
    rng = np.random.default_rng(rng_seed)
    p = np.column_stack([0.1 + 0 * t, 0 * t, z(t)]) + rng.normal(0.0, 3e-4, (len(t), 3))   # 0.3 mm mocap noise
    return p


def test_a_take_off_within_the_first_half_second_is_not_a_start_in_the_air():
    for t0 in (0.1, 0.2, 0.3):
        p = _head(lambda t, t0=t0: 0.03 + np.minimum(np.clip(t - t0, 0, None) * 0.5, 1.0))   # climbs at 0.5 m/s
        assert started_in_air(p, RATE_HZ) == (False, ""), t0


def test_a_log_that_starts_hovering_and_bobbing_at_its_lowest_height_starts_in_the_air():
    # a hover at 0.3 m that sinks and rises by 1 cm, then lands at 0.3 m (its lowest height is the hover's)
    in_air, why = started_in_air(_head(lambda t: 0.3 + 0.01 * np.sin(2 * np.pi * 2.0 * t)), RATE_HZ)
    assert in_air and "moving by" in why


def test_gaps_are_counted_against_the_positive_steps_not_repeated_stamps():
    # a log that stamps every row twice (zero steps), at 100 Hz, with one gap (1.99 s to 2.10 s)
    stamps = np.r_[np.arange(0.0, 2.0, 0.01), np.arange(2.1, 4.0, 0.01)]
    t = np.repeat(stamps, 2)
    timing = stream_timing(t)
    assert 0.11 > GAP_STEPS * 0.01 and timing["gaps"] == 1
    assert timing["longest_gap_s"] == 0.11 and timing["rate_hz"] == 100.0
