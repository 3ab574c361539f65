"""The yardsticks of an evaluation (estimators.yardsticks): mocap gaps, the fast reference with the onboard
estimate, and the paper's SG score, against known answers."""
from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.kf import linearize
from learnest.estimators.mhe import MHE
from learnest.estimators.params import EstimatorParams
from learnest.estimators.yardsticks import (
    NOTHING_LEARNED,
    GapPlan,
    PositionGapModel,
    fast_derivatives,
    gap_mask,
    masked_measurements,
    rms_norm,
    run_with_gaps,
)
from learnest.ingest import read_flights
from learnest.ingest.flight import Flight
from learnest.ingest.sim import Circle, simulate, write_flight
from learnest.models.knode import HybridModel, Residual
from learnest.models.systems import make_system
from learnest.service.cli import format_report
from learnest.workflows.flights import evaluate_flights

RADIUS, SPEED = 0.5, 1.0          # m, m/s: ω = 2 rad/s, the circle's centripetal jerk ω² v is what the prior lacks
SAMPLE = "sample_logs/B2_circle_fast_rep1.csv"   # a real NanoBench flight with the onboard EKF's estimate


def _circle(tmp_path_factory, seed: int, duration_s: float = 20.0, speed: float = SPEED) -> Flight:
    sim = simulate(Circle(radius=RADIUS, speed=speed, duration_s=duration_s), seed=seed, name=f"circle{seed}")
    return read_flights(write_flight(sim, "nanobench", tmp_path_factory.mktemp(f"circle{seed}"), f"circle{seed}"))[0]


@pytest.fixture(scope="module")
def circles(tmp_path_factory):
    return {seed: _circle(tmp_path_factory, seed) for seed in (3, 4)}


def _true_circle_model() -> HybridModel:
    """The kinematic prior plus exactly the missing physics: the jerk −ω² v in the plane of a circle flown at
    constant speed (ω = v / r)."""
    system = make_system("quadrotor")
    weight, bias = np.zeros((9, 9)), np.zeros(9)
    weight[6, 3] = weight[7, 4] = -(SPEED / RADIUS) ** 2
    return HybridModel(system, "knode", Residual([(weight, bias)]), {"name": "true-circle"})


def _fitted_circle_model(flight: Flight) -> HybridModel:
    """A KNODE whose residual jerk is fitted to one circle: least squares of the in-plane jerk on the in-plane
    velocity over the states Phase 1 of Algorithm 1 makes of that flight (the pre-training observer): it
    learns that circle's −ω² v."""
    from learnest.estimators.observers import pretraining_observer

    system = make_system("quadrotor", dt=flight.dt, n_samples=len(flight.t))
    zeta = pretraining_observer(system, flight.measurements(), np.zeros((len(flight.t), 0)), flight.dt)
    jerk = np.diff(zeta[:, 6:8], axis=0) / flight.dt
    coefficients, *_ = np.linalg.lstsq(zeta[:-1, 3:5], jerk, rcond=None)
    weight, bias = np.zeros((9, 9)), np.zeros(9)
    weight[6:8, 3:5] = coefficients.T
    return HybridModel(make_system("quadrotor"), "knode", Residual([(weight, bias)]), {"name": "fitted-circle"})


def _masked_kalman_filter(model, y, dt, Q, R, x0, P0, inside):
    """The textbook Kalman filter of a linear model that skips the position rows of y inside the gaps."""
    F, H = linearize(model, dt)
    x, P, out = x0.copy(), P0.copy(), np.empty((len(y), len(x0)))
    for k in range(len(y)):
        if k:
            x, P = F @ x, F @ P @ F.T + Q
        rows = [3, 4, 5] if inside[k] else list(range(6))
        S = H[rows] @ P @ H[rows].T + R[np.ix_(rows, rows)]
        K = P @ H[rows].T @ np.linalg.inv(S)
        x, P = x + K @ (y[k, rows] - H[rows] @ x), P - K @ S @ K.T
        out[k] = x
    return out


def test_inside_a_gap_the_ukf_and_the_mhe_skip_the_position_update_exactly(circles):
    """The mask input makes a hidden position carry no information: on the linear kinematic prior the UKF
    equals the Kalman filter that skips those rows, and so does the full-information MHE (its window holds
    the whole record), both through the compiled loops."""
    flight = circles[3]
    steps = 260
    system = make_system("quadrotor", dt=flight.dt, n_samples=steps)
    prior = HybridModel(system, "prior")
    y, u = flight.measurements()[:steps], np.zeros((steps, 0))
    x0 = np.concatenate([flight.p[0], np.zeros(3), flight.a_meas[0]])
    plan = GapPlan(gap_s=0.5, every_s=1.0, start_s=0.6)
    windows = plan.windows(steps, flight.dt)
    assert windows == [(60, 110), (160, 210)]
    inside = gap_mask(steps, windows)
    expected = _masked_kalman_filter(prior, y, flight.dt, system.Q, system.R, x0, system.P0, inside)
    params = EstimatorParams(prior, flight.dt, system.Q, system.R, system.P0, x0)
    ukf = run_with_gaps(["ukf"], params, params, y, u, inside, 20)
    np.testing.assert_allclose(ukf["ukf"]["estimates"], expected, atol=1e-6)
    y_gap, u_gap = masked_measurements(y, u, inside)
    mhe = MHE(replace(params, model=PositionGapModel(prior)), horizon=steps).run(y_gap, u_gap).means
    np.testing.assert_allclose(mhe, expected, atol=1e-6)
    # and the gap matters: without it the filter would have used the mocap there
    unmasked = _masked_kalman_filter(prior, y, flight.dt, system.Q, system.R, x0, system.P0, np.zeros(steps, bool))
    assert np.abs(unmasked[inside, :3] - expected[inside, :3]).max() > 0.01


def test_the_gap_score_ranks_the_true_dynamics_first_the_trained_model_next_and_the_prior_last(circles,
                                                                                                tmp_path_factory):
    """Simulated circles whose unmodelled effect is known (the centripetal jerk −ω² v the kinematic prior
    lacks, ω = 2 rad/s here): in the gaps the model with the exact effect drifts least, a KNODE trained on a
    slower circle (ω = 1.6 rad/s: part of the effect) less than the prior, and the prior most."""
    slower = _circle(tmp_path_factory, 6, speed=0.8)
    trained = _fitted_circle_model(slower)            # the effect of a slower circle: −(0.8 / 0.5)² v = −2.56 v
    fitted = np.diag(trained.residual.layers[0][0][6:8, 3:5])
    np.testing.assert_allclose(fitted, -(0.8 / RADIUS) ** 2, rtol=0.1)
    scores = {}
    for name, model in (("true", _true_circle_model()), ("trained", trained)):
        report = evaluate_flights(model, [circles[3]], ["ukf", "knode-ukf", "mhe", "knode-mhe"])
        gaps = report["flights"][0]["yardsticks"]["mocap_gaps"]
        assert gaps["gaps"] == 7 and gaps["gap_s"] == 0.5 and gaps["every_s"] == 2.5
        scores[name] = gaps
    for base in ("ukf", "mhe"):
        prior = scores["true"]["rmse_m"][base]
        assert scores["trained"]["rmse_m"][base] == pytest.approx(prior, rel=1e-9)   # the same prior run twice
        true, learned = scores["true"]["rmse_m"][f"knode-{base}"], scores["trained"]["rmse_m"][f"knode-{base}"]
        assert true < learned < prior, (base, true, learned, prior)
        key = f"knode-{base}_vs_{base}"
        assert scores["true"]["gain_pct"][key] > scores["trained"]["gain_pct"][key] > 0
        low, high = scores["true"]["gain_interval_pct"][key]
        assert 0 < low <= scores["true"]["gain_pct"][key] <= high


def test_a_constant_offset_of_the_mocap_does_not_change_the_gap_score(circles):
    """The reference in the gaps is the mocap the estimators saw elsewhere: shift the room's origin and the
    estimates shift with it (the kinematic prior and the circle's jerk do not depend on where the room is)."""
    flight = circles[3]
    offset = np.array([3.0, -2.0, 0.5])
    moved = Flight(flight.t, flight.p + offset, flight.a_meas, flight.quat, dict(flight.channels), dict(flight.meta))
    model = _true_circle_model()
    scores = [evaluate_flights(model, [f], ["ukf", "knode-ukf"])["flights"][0]["yardsticks"]["mocap_gaps"]
              for f in (flight, moved)]
    for method in ("ukf", "knode-ukf"):
        assert scores[1]["rmse_m"][method] == pytest.approx(scores[0]["rmse_m"][method], rel=1e-6, abs=1e-9)
    assert scores[0]["rmse_m"]["ukf"] > 0.01          # not trivially zero: the estimates do drift in the gaps


def test_onboard_is_the_logged_estimate_scored_on_the_fast_reference():
    """A real NanoBench flight: the ``onboard`` velocity score is the RMS of the log's own est_stateEstimate_v*
    (at the flight's grid times) against the short derivative of the mocap, outside the gaps."""
    flight = read_flights([SAMPLE])[0]
    frame = pd.read_csv(SAMPLE)
    times = flight.meta["t0_source_s"] + flight.meta["flying_window"]["start_s"] + flight.t
    logged = np.column_stack([np.interp(times, frame["t"], frame[f"est_stateEstimate_v{axis}"]) for axis in "xyz"])
    np.testing.assert_allclose(flight.channels["v_onboard"], logged, atol=1e-8)

    prior = HybridModel(make_system("quadrotor"), "prior")
    report = evaluate_flights(prior, [flight], ["ukf", "onboard"])
    fast = report["flights"][0]["yardsticks"]["fast_reference"]
    inside = gap_mask(len(flight.t), GapPlan().windows(len(flight.t), flight.dt))
    derivative = fast_derivatives(flight.p, flight.dt)["v"]
    assert fast["velocity_rmse_m_s"]["onboard"] == pytest.approx(rms_norm((logged - derivative)[~inside]), rel=1e-6)
    assert fast["window_s"] == pytest.approx(0.05) and fast["samples"] == np.count_nonzero(~inside)
    assert set(fast["velocity_rmse_m_s"]) == {"ukf", "onboard"}
    assert "onboard" not in report["flights"][0]["mse"]            # it is not an estimator the paper scores
    assert "onboard" not in report["flights"][0]["yardsticks"]["mocap_gaps"]["rmse_m"]
    # not asked for, not scored
    without = evaluate_flights(prior, [flight], ["ukf"])["flights"][0]["yardsticks"]["fast_reference"]
    assert set(without["velocity_rmse_m_s"]) == {"ukf"}


def test_the_fast_reference_follows_what_the_paper_s_reference_smooths_away():
    """On a 2-Hz oscillation the 0.05-s derivative is within 1 % of the true velocity; the paper's 1.5-s
    Savitzky-Golay window (order 2) flattens it to a fraction."""
    from learnest.ingest.baseline import sg_references

    dt, omega = 0.01, 2 * np.pi * 2.0
    t = np.arange(0, 10, dt)
    p = np.column_stack([0.1 * np.sin(omega * t), np.zeros_like(t), np.ones_like(t)])
    true_v = 0.1 * omega * np.cos(omega * t)
    middle = slice(200, -200)
    fast = fast_derivatives(p, dt)["v"][middle, 0]
    assert np.max(np.abs(fast - true_v[middle])) < 0.01 * 0.1 * omega
    paper = sg_references(p, dt)["v"][middle, 0]
    assert np.sqrt(np.mean(paper**2)) < 0.2 * np.sqrt(np.mean(true_v[middle] ** 2))


def test_a_flight_too_short_for_one_gap_is_scored_without_it_and_says_why(tmp_path_factory):
    short = _circle(tmp_path_factory, 5, duration_s=3.0)
    assert len(short.t) * short.dt < 5.5
    report = evaluate_flights(_true_circle_model(), [short], ["ukf", "knode-ukf"])
    entry = report["flights"][0]
    gaps = entry["yardsticks"]["mocap_gaps"]
    assert gaps["gaps"] == 0 and gaps["rmse_m"] == {} and "too short for one mocap gap" in gaps["skipped"]
    assert entry["yardsticks"]["fast_reference"]["velocity_rmse_m_s"]["knode-ukf"] > 0   # the rest is scored
    assert entry["mse"]["ukf"] > 0
    assert report["headline"]["flights_with_gaps"] == 0
    assert report["headline"]["flights_without_gaps"] == [f"{short.name}: {gaps['skipped']}"]
    assert report["headline"]["flights_undecided"] == {"knode-ukf_vs_ukf": 1}      # counted, not dropped
    assert report["headline"]["flights_undecided_names"]["knode-ukf_vs_ukf"] == [f"{short.name}: {gaps['skipped']}"]
    assert "no gap score: the kept flight is" in format_report({**report, "model": "m:1"})


def test_the_report_leads_with_the_gap_headline_and_says_when_nothing_was_learned(circles):
    model = _true_circle_model()
    report = evaluate_flights(model, [circles[3], circles[4]], ["ukf", "knode-ukf"], gap_s=0.4, gap_every_s=2.0)
    json.dumps(report)
    head = report["headline"]
    assert head["yardstick"] == "mocap_gaps" and head["gap_s"] == 0.4 and head["every_s"] == 2.0
    gains = [f["yardsticks"]["mocap_gaps"]["gain_pct"]["knode-ukf_vs_ukf"] for f in report["flights"]]
    assert head["median_gain_pct"]["knode-ukf_vs_ukf"] == pytest.approx(float(np.median(gains)))
    assert head["flights_better"]["knode-ukf_vs_ukf"] == 2
    assert head["flights_worse_beyond_interval"]["knode-ukf_vs_ukf"] == 0
    # nine gaps each: every flight has an interval over its gaps, and each is counted once
    assert all(f["yardsticks"]["mocap_gaps"]["gain_interval_pct"]["knode-ukf_vs_ukf"] is not None
               and "signed-rank" in f["yardsticks"]["mocap_gaps"]["interval_method"] for f in report["flights"])
    assert head["flights_undecided"]["knode-ukf_vs_ukf"] == 0
    assert sum(head[f"flights_{c}"]["knode-ukf_vs_ukf"] for c in (
        "better_beyond_interval", "worse_beyond_interval", "within_interval", "undecided")) == head["flights_scored"] == 2
    for entry in report["flights"]:
        assert list(entry["yardsticks"]) == ["mocap_gaps", "fast_reference", "paper_sg"]
        assert entry["yardsticks"]["paper_sg"]["mse"] == entry["mse"]          # the paper's score, as before
        assert entry["yardsticks"]["mocap_gaps"]["gaps"] == 9                   # at 5, 7, ..., 21 s of 22 s
    assert report["learned"] is None and report["learned_note"] is None     # the model does not say
    text = format_report({**report, "model": "circle:1"})
    assert "carried the estimate through mocap gaps" in text.splitlines()[0]     # the answer first
    assert text.index("Mocap gaps") < text.index("Fast reference") < text.index("The paper's score (paper_sg)")

    model.meta["learned"] = False
    nothing = evaluate_flights(model, [circles[4]], ["ukf", "knode-ukf"], gap_s=0.0)
    assert nothing["learned"] is False and nothing["learned_note"] == NOTHING_LEARNED
    assert "turned off" in nothing["flights"][0]["yardsticks"]["mocap_gaps"]["skipped"]
    assert NOTHING_LEARNED in format_report({**nothing, "model": "circle:2"}).splitlines()[0]


def test_a_gap_plan_that_leaves_no_mocap_between_gaps_is_refused():
    with pytest.raises(InvalidInput, match="longer than the gap"):
        GapPlan(gap_s=1.0, every_s=1.0)
    with pytest.raises(InvalidInput, match="non-negative"):
        GapPlan(gap_s=-0.5)
    assert GapPlan().windows(551, 0.01) == [(500, 550)]       # the first gap fits exactly
    assert GapPlan().windows(549, 0.01) == []


@pytest.mark.data
def test_a_usd_log_s_onboard_estimate_is_scored_from_its_compressed_state_estimate():
    """A real uSD-card log (crazyswarm2-tools log182, stateEstimateZ.* in mm/s): ``onboard`` is scored on the
    fast reference from the flight's v_onboard, which is the logged estimate in m/s."""
    from pathlib import Path

    path = Path(__file__).resolve().parents[3] / "shared" / "data" / "crazyswarm2-tools" / "log182"
    flight = read_flights([path])[0]
    onboard = flight.channels["v_onboard"]
    speed = np.linalg.norm(fast_derivatives(flight.p, flight.dt)["v"], axis=1)
    assert 0.3 < np.percentile(np.linalg.norm(onboard, axis=1), 95) / np.percentile(speed, 95) < 3  # m/s, not mm/s
    report = evaluate_flights(HybridModel(make_system("quadrotor"), "prior"), [flight], ["ukf", "onboard"])
    fast = report["flights"][0]["yardsticks"]["fast_reference"]
    inside = gap_mask(len(flight.t), GapPlan().windows(len(flight.t), flight.dt))
    derivative = fast_derivatives(flight.p, flight.dt)["v"]
    assert fast["velocity_rmse_m_s"]["onboard"] == pytest.approx(rms_norm((onboard - derivative)[~inside]), rel=1e-9)


def _junk(folder):
    """A file that is no flight log: reading it would fail with another message than the gap plan's."""
    path = folder / "junk.csv"
    path.write_text("not,a,flight\n")
    return path


def test_the_command_line_refuses_gaps_without_mocap_between_them_before_reading_anything(capsys, tmp_path):
    from learnest.service.cli import main

    status = main(["evaluate", "--model", "nothing:1", str(_junk(tmp_path)), "--no-store", "--gap-s", "1",
                   "--gap-every-s", "0.5"])
    assert status == 2
    assert "must be longer than the gap" in capsys.readouterr().err


def test_a_gap_plan_that_would_never_end_is_refused_before_any_window():
    """1e-300-s gaps every 2e-300 s never reach the flight's end (5.0 + 2e-300 == 5.0): refused at once, by
    the plan itself, naming the field; so are gaps shorter than one sample and more than MAX_GAPS gaps."""
    import dataclasses

    from learnest.models.presets import MAX_GAPS

    with pytest.raises(InvalidInput, match="^gap_s must be 0 .no gaps. or at least 0.001 s, got 1e-300"):
        GapPlan(gap_s=1e-300, every_s=2e-300)
    with pytest.raises(InvalidInput, match="^gap_every_s must be longer than the gap"):
        GapPlan(gap_s=0.5, every_s=0.5 + 1e-12)
    with pytest.raises(InvalidInput, match="non-negative"):
        GapPlan(every_s=float("nan"))
    fine = GapPlan(gap_s=0.002, every_s=0.004)            # physically possible, finer than a 100 Hz grid
    assert fine.windows(10_000, 0.001)[:2] == [(5000, 5002), (5004, 5006)]
    with pytest.raises(InvalidInput, match=r"^gap_s must be 0 \(no gaps\) or at least one sample \(0.01 s\)"):
        fine.windows(10_000, 0.01)
    with pytest.raises(InvalidInput, match=r"^gap_every_s must be longer than the gap .* one sample \(0.01 s\)"):
        GapPlan(gap_s=0.5, every_s=0.505).windows(10_000, 0.01)
    with pytest.raises(InvalidInput, match=f"gap_every_s 0.02 s gives 49750 gaps .* at most {MAX_GAPS}"):
        GapPlan(gap_s=0.01, every_s=0.02).windows(100_000, 0.01)      # a 1000-s flight
    assert len(GapPlan(gap_s=0.01, every_s=0.02).windows(20_500, 0.01)) == MAX_GAPS   # 205 s: just within
    # the windows refuse a plan that escaped its constructor too (defence in depth: nothing unbounded runs)
    sneaked = GapPlan()
    object.__setattr__(sneaked, "gap_s", 1e-300)
    object.__setattr__(sneaked, "every_s", 2e-300)
    with pytest.raises(InvalidInput, match="^gap_s"):
        sneaked.windows(1_000, 0.01)
    with pytest.raises(InvalidInput, match="sample period"):
        GapPlan().windows(1_000, 0.0)
    assert dataclasses.replace(GapPlan(), gap_s=0.0).windows(1_000, 1e-300) == []   # off: nothing to lay


def test_the_command_line_refuses_a_gap_plan_that_never_ends(capsys, tmp_path):
    """`learnest evaluate --gap-s 1e-300 --gap-every-s 2e-300` (a MemoryError after minutes, before): a usage
    error naming the option, exit 2 (how fast: benchmarks/bench_service_hostile.py); also a spacing shorter
    than one --rate sample."""
    from learnest.service.cli import main

    junk = str(_junk(tmp_path))
    for options, named in ((["--gap-s", "1e-300", "--gap-every-s", "2e-300"], "argument --gap-s: must be 0"),
                           (["--gap-s", "0.5", "--gap-every-s", "0.505"], "argument --gap-every-s: must be longer"),
                           (["--gap-s", "0.004", "--gap-every-s", "1", "--rate", "100"],
                            "argument --gap-s: must be 0 (no gaps) or at least one sample (0.01 s)")):
        assert main(["evaluate", "--model", "nothing:1", junk, "--no-store", *options]) == 2
        assert named in capsys.readouterr().err


def test_the_headline_prints_as_a_sentence_and_stays_its_json_dict():
    """`le.evaluate`'s headline: print() gives the sentence (UKF pair first), repr the type and rounded gains,
    and it is still the dict the service stores (json, keys)."""
    from learnest.estimators.headline import Headline, ReportHeadline

    pairs = ("knode-mhe_vs_mhe", "knode-ukf_vs_ukf")
    head = ReportHeadline(Headline(
        median_gain_pct={"knode-mhe_vs_mhe": -2.94123456789, "knode-ukf_vs_ukf": 9.8912345678},
        flights_better=dict.fromkeys(pairs, 1), flights_worse_beyond_interval=dict.fromkeys(pairs, 0),
        flights_better_beyond_interval=dict.fromkeys(pairs, 0), flights_within_interval=dict.fromkeys(pairs, 2),
        flights_undecided=dict.fromkeys(pairs, 1), flights_scored=3, flights_with_gaps=2).to_dict())
    assert str(head) == (
        "KNODE-UKF carried the estimate through mocap gaps 9.9 % better than its prior UKF (median of 2 flights "
        "with gaps): better on 1 of 2; of 3 flights scored, worse beyond its 95 % interval on none, better beyond "
        "it on none, within it on 2, undecided (no interval) on 1. KNODE-MHE carried the estimate through mocap "
        "gaps 2.9 % worse than its prior MHE (median of 2 flights with gaps): better on 1 of 2; of 3 flights "
        "scored, worse beyond its 95 % interval on none, better beyond it on none, within it on 2, undecided (no "
        "interval) on 1.")
    assert repr(head).startswith("ReportHeadline(yardstick='mocap_gaps', median_gain_pct={'knode-mhe_vs_mhe': "
                                 "-2.94, 'knode-ukf_vs_ukf': 9.89}")
    assert json.loads(json.dumps(head))["median_gain_pct"]["knode-ukf_vs_ukf"] == 9.8912345678
    assert str(ReportHeadline(Headline(flights_scored=1, flights_without_gaps=["a: too short"]).to_dict())) == (
        "No flight had a mocap gap to score: the KNODE's gain is undecided on all 1 flight scored (a: too short).")
