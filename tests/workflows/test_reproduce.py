"""Quick Table I (2 seeds, short trajectories): the paper's finding must hold on both tasks."""
import pytest

from learnest.workflows.table1 import ReproduceSettings, reproduce


@pytest.mark.slow
@pytest.mark.parametrize("task,samples,epochs", [("cartpole", 1500, None), ("robot", 1000, 500)])
def test_quick_reproduction_shows_the_papers_ordering(task, samples, epochs):
    # robot: 500 epochs (not the paper's 10000) keep KNODE-MHE/UKF 16x/19x better than MHE/UKF on these two
    # seeds, far past the 2x asserted, in half the time of 1000.
    # the cartpole with the paper's Algorithm 1 (filter, no rounds): its default joint fit would add ~1 min here
    # (tests/estimators/test_joint_training.py tests it, benchmarks/results/table1_cartpole.txt measures it)
    observer = "filter" if task == "cartpole" else None
    report = reproduce(ReproduceSettings(task, eval_samples=samples, epochs=epochs, observer_rounds=0,
                                         observer=observer), seeds=2, workers=2)
    mu = {row: r["mu"] for row, r in report["rows"].items()}
    for estimator in ("MHE", "UKF"):
        prior, knode = mu[estimator], mu[f"KNODE-{estimator}"]
        full, true = mu[f"KNODE-{estimator} (full state)"], mu[f"{estimator} (true dynamics)"]
        factor = {"cartpole": {"MHE": 5, "UKF": 10}, "robot": {"MHE": 2, "UKF": 2}}[task][estimator]
        assert knode * factor < prior, f"{task} KNODE-{estimator} {knode:.2e} vs {estimator} {prior:.2e}"
        assert true < full, f"{task}: true dynamics should beat the full-state KNODE ({estimator})"
        assert full < 1.5 * knode, f"{task}: full-state KNODE should not lose to partial ({estimator})"
    assert set(report["rows"]) == {"MHE", "KNODE-MHE", "KNODE-MHE (full state)", "MHE (true dynamics)", "UKF",
                                   "KNODE-UKF", "KNODE-UKF (full state)", "UKF (true dynamics)"}
    for seed in report["per_seed"]:   # each evaluation run is judged against its KNODE's training envelope
        assert isinstance(seed["envelope"]["outside_training_envelope"], bool)


def test_table_ratios_against_the_truth_and_the_prior_by_seed_and_inside_the_envelope():
    """Known answers on three made-up seeds: ratio of means, per-seed median, and the unflagged seeds alone."""
    from learnest.workflows.table1 import seed_ratios

    def seed(knode, true, flagged):
        return {"mse": {"KNODE-MHE": knode, "MHE (true dynamics)": true},
                "envelope": {"outside_training_envelope": flagged}}

    seeds = [seed(2.0, 1.0, False), seed(3.0, 1.0, False), seed(10.0, 2.0, True)]
    ratios = seed_ratios(seeds, "KNODE-MHE", "MHE (true dynamics)")
    assert ratios["ratio of means"] == pytest.approx(15.0 / 4.0)
    assert ratios["per-seed median"] == pytest.approx(3.0)
    assert ratios["ratio of means over the 2 seeds inside the envelope"] == pytest.approx(2.5)
    assert list(seed_ratios(seeds[:2], "KNODE-MHE", "MHE (true dynamics)")) == ["ratio of means", "per-seed median"]


@pytest.mark.slow
def test_a_fresh_draw_of_seeds_scores_the_runs_of_those_seeds():
    """``first_seed`` moves the draw: a table starting at seed 7 scores the evaluation run simulated with seed
    20000 + 7 (its prior UKF row, recomputed here from that simulation, is the same number)."""
    import numpy as np

    from learnest.errors import InvalidInput
    from learnest.estimators.params import EstimatorParams
    from learnest.estimators.ukf import run_ukf
    from learnest.models.knode import HybridModel
    from learnest.models.systems import make_system
    from learnest.workflows.table1 import format_table

    settings = ReproduceSettings("cartpole", eval_samples=60, epochs=1, observer_rounds=0, observer="filter")
    report = reproduce(settings, seeds=1, first_seed=7)
    assert report["first_seed"] == 7 and [s["seed"] for s in report["per_seed"]] == [7]
    system = make_system("cartpole")
    test = system.simulate(20_007, 60)
    params = EstimatorParams(HybridModel(system, "prior"), system.dt, system.Q, system.R, system.P0, test.x_noisy[0])
    prior_ukf = run_ukf(params, test.y, test.u).means
    assert report["per_seed"][0]["mse"]["UKF"] == pytest.approx(np.mean((prior_ukf - test.x) ** 2), rel=1e-12)
    assert format_table(report).startswith("Table I — cartpole, seed 7 (MSE x 1e-3)")
    with pytest.raises(InvalidInput, match="first_seed"):
        reproduce(settings, seeds=1, first_seed=-1)


@pytest.mark.slow
def test_identified_noise_lifts_the_prior_filters_and_the_paper_noise_gives_the_paper_rows():
    """One cartpole seed, short runs: with each model's process noise identified on its training run, the prior's
    UKF and MHE are several times better than with the paper's fixed noise (which leaves the prior's error to the
    filter's gain alone), and the KNODE rows still beat them; the default (paper noise) reports no noise factors."""
    from learnest.workflows.table1 import run_seed

    settings = ReproduceSettings("cartpole", eval_samples=1000, epochs=20, observer="filter", observer_rounds=0)
    paper = run_seed(settings, 0)
    identified = run_seed(ReproduceSettings(**{**settings.__dict__, "noise": "identified"}), 0)
    assert paper["noise"] is None and set(identified["noise"]) == {"prior", "KNODE", "KNODE (full state)",
                                                                   "true dynamics"}
    assert identified["noise"]["prior"]["Q:p_dot"] > 3.0     # the prior needs more velocity noise than the paper's
    for estimator in ("UKF", "MHE"):
        assert identified["mse"][estimator] * 3 < paper["mse"][estimator], (estimator, identified["mse"], paper["mse"])
        assert identified["mse"][f"KNODE-{estimator}"] < identified["mse"][estimator]
