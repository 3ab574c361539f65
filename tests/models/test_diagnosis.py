"""Diagnosis on data with an undeclared effect: the right effect first, its parameter within 20 % of
the truth, the error lower after the effect is added; and no effect claimed where there is none."""
import json

import numpy as np
import pytest

from learnest.ingest import read_flights
from learnest.ingest.frames import GRAVITY
from learnest.ingest.sim import Circle, Figure8, RandomWaypoints, SensorModel, simulate, write_flight
from learnest.models.diagnosis import fit, select_effects
from learnest.models.effects import LIBRARY
from learnest.service.cli import main
from learnest.workflows.diagnosis import (
    accelerometer_problem,
    diagnose_flights,
    diagnose_simulated,
    format_diagnosis,
    unchanged_prior_note,
)


def _flights(tmp_path, sensors, trajectory=lambda seed: RandomWaypoints(count=8, speed=0.8, seed=seed), n=2):
    files = []
    for seed in range(n):
        sim = simulate(trajectory(seed), sensors=sensors, seed=seed, name=f"f{seed}")
        files += write_flight(sim, "nanobench", tmp_path, f"flight{seed}")
    return read_flights(files)


def _first(result, effect_id):
    assert result["effects"], "no effect found"
    assert result["effects"][0]["id"] == effect_id, [e["id"] for e in result["effects"]]
    return result["effects"][0]


@pytest.mark.slow
def test_crazyflie_accelerometer_bias_is_found(tmp_path):
    bias = (0.3, -0.2, 0.25)
    result = diagnose_flights(_flights(tmp_path, SensorModel(bias=bias)), epochs=10)
    found = _first(result, "accel_bias")
    for axis, truth in zip("xyz", bias):
        assert found["params"][f"bias_{axis}"] == pytest.approx(truth, rel=0.2)
        lo, hi = found["ci95"][f"bias_{axis}"]
        assert lo < found["params"][f"bias_{axis}"] < hi
    assert result["after"]["ukf"] < result["before"]["ukf"]
    # the accelerometer innovations shrink once the bias is in the measurement model
    res = result["residuals"]
    assert sum(res["innovation_rms_after"][k] for k in ("ax", "ay", "az")) < \
        sum(res["innovation_rms_before"][k] for k in ("ax", "ay", "az"))


@pytest.mark.slow
def test_crazyflie_accelerometer_delay_of_tens_of_milliseconds_is_found(tmp_path):
    result = diagnose_flights(_flights(tmp_path, SensorModel(delay_s=0.04)), epochs=10)
    found = _first(result, "accel_delay")
    assert found["params"]["delay_s"] == pytest.approx(0.04, rel=0.2)
    assert result["after"]["ukf"] < result["before"]["ukf"]


@pytest.mark.slow
def test_crazyflie_accelerometer_scale_error_is_found(tmp_path):
    # thrust (body z) is what a quadrotor's accelerometer mostly sees; body x/y carry only rotor drag,
    # so only scale_z is identifiable in flight and x/y are left nominal here
    result = diagnose_flights(_flights(tmp_path, SensorModel(scale=(1.0, 1.0, 1.1))), epochs=10)
    found = _first(result, "accel_scale")
    assert found["params"]["scale_z"] == pytest.approx(1.1, rel=0.2)
    assert abs(found["params"]["scale_z"] - 1.1) < 0.01
    assert result["after"]["ukf"] < result["before"]["ukf"]


def test_accelerometer_model_reads_what_the_simulated_tilted_imu_reads(tmp_path):
    """The diagnosis' accelerometer model and the simulator share one misalignment convention: fitted on
    a tilted IMU's flights, roll and pitch come back with their signs."""
    tilt = (0.03, -0.02)
    problem = accelerometer_problem(_flights(tmp_path, SensorModel.ideal(misalignment=tilt)))
    values = fit(problem, [LIBRARY["accel_misalignment"]]).values
    assert values["roll_rad"] == pytest.approx(tilt[0], abs=1e-3)
    assert values["pitch_rad"] == pytest.approx(tilt[1], abs=1e-3)


def test_clean_crazyflie_flights_claim_no_effect(tmp_path):
    flights = _flights(tmp_path, SensorModel())
    selection = select_effects(accelerometer_problem(flights))
    assert selection["effects"] == []


def test_bias_and_misalignment_at_constant_thrust_are_reported_as_confounded(tmp_path):
    flights = _flights(tmp_path, SensorModel(bias=(0.3, 0.0, 0.0)),
                       trajectory=lambda seed: Circle(radius=0.5, speed=0.3, duration_s=20), n=1)
    selection = select_effects(accelerometer_problem(flights))
    assert selection["effects"][0]["id"] in ("accel_bias", "accel_misalignment")
    pairs = [set(c["effects"]) for c in selection["confounded"]]
    assert {"accel_bias", "accel_misalignment"} in pairs


# an IMU pitched 2.5° against the mocap body reads like an x bias of −g·sin(2.5°) = −0.428 m/s²;
# the sensor's 30 Hz low-pass and the vehicle's rotor drag are on, so the model is not the ideal one
TILTED_IMU = SensorModel(misalignment=(0.0, np.radians(2.5)), lowpass_hz=30.0)
TILT_AS_BIAS = -GRAVITY * np.sin(np.radians(2.5))


def _alternative(effect, rival_id):
    (alt,) = [a for a in effect["alternatives"] if a["id"] == rival_id]
    return alt


def test_a_tilt_on_flights_with_varied_thrust_is_a_tilt_and_the_bias_reading_is_shown(tmp_path):
    flights = _flights(tmp_path, TILTED_IMU, n=2, trajectory=lambda seed: (
        Figure8(size=0.8, period=4.0, duration_s=16) if seed == 0 else Circle(radius=0.6, speed=1.2, duration_s=16)))
    selection = select_effects(accelerometer_problem(flights))
    found = _first(selection, "accel_misalignment")
    assert found["params"]["pitch_rad"] == pytest.approx(np.radians(2.5), rel=0.2)
    # roll's interval holds its prior value 0: reported, not claimed
    assert found["claimed"] == {"roll_rad": False, "pitch_rad": True}
    bias = _alternative(found, "accel_bias")
    assert bias["params"]["bias_x"] == pytest.approx(TILT_AS_BIAS, rel=0.1)
    assert bias["fraction_of_chosen"] >= 0.9 and bias["units"]["bias_x"] == "m/s²"
    assert {"accel_misalignment", "accel_bias"} in [set(c["effects"]) for c in selection["confounded"]]


def test_a_tilt_at_constant_thrust_is_reported_with_bias_as_confounded(tmp_path, capsys):
    flights = _flights(tmp_path, TILTED_IMU, trajectory=lambda seed: Circle(radius=0.5, speed=0.3, duration_s=20), n=1)
    selection = select_effects(accelerometer_problem(flights))
    top = selection["effects"][0]
    assert top["id"] in ("accel_bias", "accel_misalignment")
    rival = "accel_bias" if top["id"] == "accel_misalignment" else "accel_misalignment"
    assert _alternative(top, rival)["fraction_of_chosen"] > 0.95
    assert {"accel_misalignment", "accel_bias"} in [set(c["effects"]) for c in selection["confounded"]]
    # the text report names the alternative with the value it would take
    text = format_diagnosis({"system": "quadrotor", "effects": [{**top, "channel": "accelerometer"}],
                             "confounded": selection["confounded"], "before": {}, "after": {}})
    assert f"alternative: {rival} with" in text and "cannot tell apart" in text


def test_a_z_scale_on_fast_vertical_motion_is_not_inflated_by_the_reference_smoothing(tmp_path):
    """The mocap reference is smoothed; the accelerometer must be compared after the same filter, or
    fast motion is attenuated on one side only and every gain comes back too large (1.08 read as 1.131)."""
    sensors = SensorModel(scale=(1.0, 1.0, 1.08), lowpass_hz=30.0)
    fast_climbs = RandomWaypoints(count=10, speed=2.0, box=((-0.5, 0.5), (-0.5, 0.5), (0.3, 1.8)), seed=0)
    sim = simulate(fast_climbs, sensors=sensors, seed=0, name="climbs")
    selection = select_effects(accelerometer_problem(read_flights(write_flight(sim, "usd-v1", tmp_path, "climbs"))))
    found = _first(selection, "accel_scale")
    assert abs(found["params"]["scale_z"] - 1.08) < 0.2 * 0.08
    for effect in selection["effects"]:      # the sensor filter's lag, if reported, is reported as what it is
        if effect["id"] == "accel_delay":
            assert effect["params"]["delay_s"] == pytest.approx(sensors.accelerometer_group_delay_s(), abs=0.005)


def test_no_effect_but_a_moved_error_is_explained():
    """With no effect the prior is unchanged: a KNODE method's error moves only because it was retrained,
    and the report says so; prior-only estimators that did not move are not blamed, nothing moved: no note."""
    same = {"system": "quadrotor", "effects": [], "confounded": [], "before": {"ukf": 1.0, "knode-ukf": 2.0}}
    assert unchanged_prior_note({**same, "after": {"ukf": 1.0, "knode-ukf": 2.0}}) is None
    note = unchanged_prior_note({**same, "after": {"ukf": 1.0, "knode-ukf": 2.24}})
    assert note is not None and "knode-ukf" in note and "trained again" in note and "ukf," not in note
    assert note in format_diagnosis({**same, "after": {"ukf": 1.0, "knode-ukf": 2.24}})
    found = {**same, "effects": [{"id": "accel_bias"}]}
    assert unchanged_prior_note({**found, "after": {"ukf": 0.5, "knode-ukf": 1.0}}) is None


@pytest.mark.slow
def test_cartpole_with_the_papers_cart_mass_error():
    result = diagnose_simulated("cartpole", "", seed=0, eval_samples=1500)
    found = _first(result, "cart_mass")
    assert found["params"]["m_c"] == pytest.approx(1.5, rel=0.2)
    assert result["after"]["ukf"] < result["before"]["ukf"]
    assert result["after"]["knode-ukf"] < result["before"]["knode-ukf"]


@pytest.mark.slow
def test_robot_with_the_papers_quadratic_drag():
    result = diagnose_simulated("robot", "", seed=0, epochs=300, eval_samples=1000)
    found = _first(result, "quadratic_drag")
    assert found["params"]["c"] == pytest.approx(0.1, rel=0.2)
    assert result["after"]["ukf"] < result["before"]["ukf"]


def _robot_drag_selection(truth: str, throttle_mean: float, throttle_weave: tuple) -> dict:
    """Effect selection on 10 s of the simulated robot (observer states), the true drag given by ``truth``."""
    from dataclasses import replace

    from learnest.estimators.observers import pretraining_observer
    from learnest.models.systems import make_system
    from learnest.workflows.diagnosis import dynamics_problem, effects_for, parse_simulate

    robot = replace(make_system("robot"), throttle_mean=throttle_mean, throttle_weave=throttle_weave)
    robot = robot.with_true_params(**parse_simulate("robot", truth))
    run = robot.simulate(10_000, 1000)
    zeta = pretraining_observer(robot, run.y, run.u, robot.dt)
    return select_effects(dynamics_problem(robot, zeta, run.u, robot.dt, effects_for("robot", "dynamics")))


def test_robot_rolling_resistance_at_varied_speed_is_linear_drag_not_quadratic():
    """k = 0.15 1/s of rolling resistance must not be reported as quadratic drag (c = 0.169).  With the speed
    varied (1-4 m/s) the two differ, and the linear one is found with its value."""
    selection = _robot_drag_selection("linear_drag=0.15,c=0", throttle_mean=0.7, throttle_weave=(0.8, 0.48))
    found = _first(selection, "linear_drag")
    assert found["params"]["k"] == pytest.approx(0.15, rel=0.1)
    assert found["claimed"] == {"k": True}
    assert "quadratic_drag" not in {e["id"] for e in selection["effects"]}
    for pair in selection["confounded"]:     # if listed at all, as a rival the data rejected
        assert pair["data_prefer"] == "linear_drag"


def test_robot_drag_at_constant_speed_is_reported_as_confounded():
    """At a constant 2 m/s, k·v and c·v² are the same deceleration (k = 2c): whichever is chosen, the other
    must be listed as confounded with its own value, and the data must not be said to prefer one."""
    selection = _robot_drag_selection("linear_drag=0.2,c=0", throttle_mean=0.4, throttle_weave=(0.0, 0.0))
    (first,) = selection["effects"]
    assert first["id"] in ("linear_drag", "quadratic_drag")
    (pair,) = selection["confounded"]
    assert set(pair["effects"]) == {"linear_drag", "quadratic_drag"} and pair["data_prefer"] is None
    assert "cannot be told apart" in pair["note"]
    values = {**first["params"], **first["alternatives"][0]["params"]}
    assert values["k"] == pytest.approx(0.2, rel=0.05) and values["c"] == pytest.approx(0.1, rel=0.05)


def test_cartpole_without_an_effect_claims_none(capsys):
    assert main(["diagnose", "--system", "cartpole", "--simulate", "m_c=1.0", "--json", "--epochs", "50"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["effects"] == [] and result["system"] == "cartpole"
    assert result["before"] == result["after"]


def test_bad_simulate_spec_is_a_clear_error(capsys):
    assert main(["diagnose", "--system", "cartpole", "--simulate", "warp_drive=3"]) == 2
    assert "warp_drive" in capsys.readouterr().err


@pytest.mark.parametrize("angle_deg, alike", [(2.0, True), (89.0, False)])
def test_a_near_tie_says_whether_the_two_effects_act_alike(angle_deg, alike):
    """Two one-parameter effects whose residual sensitivities make a known angle: parallel ones are "alike",
    orthogonal ones are a tie the data cannot break, and the note must not call them alike."""
    from learnest.models.diagnosis import ResidualProblem, confounded_pairs
    from learnest.models.effects import Effect, Param

    rng = np.random.default_rng(0)
    u = rng.normal(size=200)
    w = rng.normal(size=200)
    w -= (w @ u) / (u @ u) * u                                # w ⟂ u, same scale
    w *= np.linalg.norm(u) / np.linalg.norm(w)
    angle = np.radians(angle_deg)
    v = np.cos(angle) * u + np.sin(angle) * w                 # cos(u, v) = cos(angle)
    a = Effect("effect_a", "quadrotor", "measurement", (Param("alpha", "", 0.0, -1.0, 1.0),), "a")
    b = Effect("effect_b", "quadrotor", "measurement", (Param("beta", "", 0.0, -1.0, 1.0),), "b")
    problem = ResidualProblem("toy", [a, b],
                              lambda values, rows: (values["alpha"] * u + values["beta"] * v)[rows, None], n_rows=200)
    (pair,) = confounded_pairs(problem, [a], {"alpha": 0.0}, [(a, b, 3.0)])
    assert pair["cosine"] == pytest.approx(abs(np.cos(angle)), abs=1e-4)
    assert ("act alike" in pair["note"]) is alike
    assert ("act differently" in pair["note"]) is not alike


@pytest.mark.parametrize("angle_deg", [2.0, 89.0])
def test_a_rival_admitted_by_its_share_alone_is_a_close_rival_the_data_rank_lower(angle_deg):
    """A rival that removes ≥ 90 % of the chosen effect's residual but scores ΔBIC_eff ≥ 10 worse is listed,
    and said to be ranked lower by the data, not "cannot be told apart"; a share above 1 reads as a multiple."""
    from learnest.models.diagnosis import ResidualProblem, confounded_pairs
    from learnest.models.effects import Effect, Param
    from learnest.workflows.diagnosis import confounded_label, how_much

    rng = np.random.default_rng(1)
    u, w = rng.normal(size=(2, 200))
    v = np.cos(np.radians(angle_deg)) * u + np.sin(np.radians(angle_deg)) * w
    a = Effect("effect_a", "quadrotor", "measurement", (Param("alpha", "", 0.0, -1.0, 1.0),), "a")
    b = Effect("effect_b", "quadrotor", "measurement", (Param("beta", "", 0.0, -1.0, 1.0),), "b")
    problem = ResidualProblem("toy", [a, b],
                              lambda values, rows: (values["alpha"] * u + values["beta"] * v)[rows, None], n_rows=200)
    (pair,) = confounded_pairs(problem, [a], {"alpha": 0.0}, [(a, b, 12.0, 7.36)])
    assert pair["data_prefer"] == "effect_a"
    assert confounded_label(pair) == "close rival (the data prefer effect_a)"
    assert "removes 7.4× the residual effect_a removes" in pair["note"] and "the data prefer effect_a" in pair["note"]
    assert how_much(1.0001) == "explains 100 % as much"
    assert ("act alike" in pair["note"]) is (angle_deg < 10)
    assert how_much(7.36) == "removes 7.4× as much" and how_much(0.93) == "explains 93 % as much"
    (tie,) = confounded_pairs(problem, [a], {"alpha": 0.0}, [(a, b, 3.0, 0.99)])
    assert tie["data_prefer"] is None and confounded_label(tie) == "cannot tell apart"


def test_select_effects_names_each_candidate_it_fits_and_its_fraction_only_grows(tmp_path):
    problem = accelerometer_problem(_flights(tmp_path, SensorModel(bias=(0.3, -0.2, 0.25)), n=1))
    seen: list[tuple[str, float]] = []
    selection = select_effects(problem, on_stage=lambda name, fraction: seen.append((name, fraction)))
    assert selection["effects"][0]["id"] == "accel_bias"
    # the first step fits every candidate once, each named with its place among them
    ids = [e.id for e in problem.candidates]
    first = [name for name, _ in seen[:len(ids)]]
    assert first == [f"fitting effects on {problem.name} ({i}, {k + 1}/{len(ids)})" for k, i in enumerate(ids)]
    assert seen[-1] == (f"fitting effects on {problem.name} (bootstrap intervals)", 3 / 4)   # max_effects 3
    fractions = [f for _, f in seen]
    assert fractions == sorted(fractions) and 0.0 == fractions[0] and fractions[-1] < 1.0
    # telling the stages changes nothing in the answer
    assert select_effects(problem)["values"] == selection["values"]


def test_diagnosis_stages_map_each_part_into_its_share_and_never_go_back():
    from learnest.workflows.diagnosis_stages import DiagnosisStages, stage_kind

    seen: list[tuple[str, float]] = []
    stages = DiagnosisStages(lambda name, fraction: seen.append((name, fraction)),
                             {"effects": 1.0, "before": 0.0, "after": 2.0, "scoring": 1.0})
    stages.report("effects", "fitting effects on x (a, 1/2)", 0.5)
    stages.report("after", "pre-training observer (f, 2/2)")
    progress = stages.epochs("after", "the repaired prior", 4)
    for epoch in range(4):
        progress(epoch, 0.1)
    stages.report("effects", "late report of an earlier part", 1.0)   # never back
    stages.report("scoring", "scoring before/after (f, 1/1)", 7.0)     # clamped to the part's end
    assert [f for _, f in seen] == [0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.75, 1.0]
    assert seen[2][0] == "training the KNODE on the repaired prior (epoch 1/4)"
    assert stage_kind(seen[2][0]) == "training the KNODE on the repaired prior"
    assert stage_kind("reading 2 file(s)") == "reading 2 file(s)"
    assert DiagnosisStages(None, {"a": 1.0}).part("a") is None


def test_a_kinematic_prior_repair_is_registered_only_when_held_out_flights_improve(tmp_path, monkeypatch, capsys):
    """The quadrotor (kinematic prior) path is gated as the Crazyflie one is: clean flights give no identified
    effect, the repaired model is the prior retrained, and nothing is registered without --force; with it,
    the version carries the warning."""
    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    files = []
    for seed in range(2):
        sim = simulate(RandomWaypoints(count=8, speed=0.8, seed=seed), sensors=SensorModel(), seed=seed,
                       name=f"f{seed}")
        files += [str(p) for p in write_flight(sim, "nanobench", tmp_path, f"flight{seed}")]
    args = ["diagnose", *files, "--system", "quadrotor", "--methods", "ukf", "--epochs", "1", "--register", "q"]
    assert main([*args, "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["repair"]["improves"] is False and "registered" not in report
    assert "does not improve" in report["not_registered"] and "--force" in report["not_registered"]
    assert main([*args, "--force", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["registered"]["version"] == 1 and "--force" in report["registered"]["warning"]
    assert main(["models", "show", "q:1", "--json"]) == 0
    shown = capsys.readouterr().out
    assert "--force" in shown and "quadrotor" in shown
