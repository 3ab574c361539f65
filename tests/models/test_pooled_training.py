"""One KNODE trained on several flights of one vehicle (`train_on_flights`, `models.pooled_training`):
known answers on simulated flights.

- Flights flown by a Crazyflie with three times the prior's rotor drag: the model pooled over four flights
  predicts a fifth, never-seen flight better than the model of one flight, and both better than the prior.
- Records that follow the prior exactly (plus zero-mean process noise): nothing to learn, and the model says so
  (``learned`` False, the residual identically zero).
- Whole-flight validation never touches the training: replacing the held-out flight changes no training loss.
- A training set of two vehicles (declared names, masses, thrust maps, prior parameters) is refused, naming
  the flights.
- One flight is the paper's protocol, bit for bit.
"""
from dataclasses import replace

import numpy as np
import pytest

from learnest.errors import InvalidInput
from learnest.estimators.algorithm1 import Algorithm1
from learnest.estimators.flight_training import check_one_vehicle, default_validation, pooled_profile
from learnest.estimators.prepared import system_for
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.models.knode import HybridModel
from learnest.models.pooled_training import TrainingRecord, train_knode_pooled, train_members_pooled
from learnest.models.presets import CRAZYFLIE_TRAINING
from learnest.models.residual_frame import BODY_FEATURES, UNREAD_BODY_FEATURES
from learnest.models.systems import make_system
from learnest.models.training import ATTITUDE_INPUTS, BATTERY_INPUTS, NOT_LEARNED, attitude_blind, train_knode
from learnest.workflows.flights import train_on_flights

DRAG_TRUTH = {**cf.IDENTIFIED, "k_xy": 3 * cf.IDENTIFIED["k_xy"]}   # rotor drag the prior underestimates 3-fold


def _sims(truth, seeds, duration_s=20.0, **settings):
    return [simulate_crazyflie(SimulatedFlight(truth=truth, duration_s=duration_s, **settings), seed=s)
            for s in seeds]


def _one_step_error(model: HybridModel, flight) -> float:
    """Mean squared one-step prediction error (eq. 8) of the model on a flight's observer states."""
    _, zeta, u, _ = Algorithm1().observe_flight(flight, model.system.name)
    model = HybridModel(replace(model.system, dt=flight.dt), model.kind, model.residual)
    prediction = model.step(zeta[:-1], u[:-1], flight.dt)
    return float(np.mean(np.sum((prediction - zeta[1:]) ** 2, axis=1)))


@pytest.fixture(scope="module")
def drag_flights():
    return _sims(DRAG_TRUTH, range(6))


def test_pooled_training_on_four_flights_predicts_an_unseen_flight_better_than_one_flight(drag_flights):
    test = drag_flights[5]
    single = train_on_flights(drag_flights[:1], CRAZYFLIE_TRAINING, system="crazyflie")
    pooled = train_on_flights(drag_flights[:5], CRAZYFLIE_TRAINING, system="crazyflie")
    prior = HybridModel(system_for(test, "crazyflie"), "prior")
    errors = {name: _one_step_error(model, test) for name, model in
              (("prior", prior), ("single", single.model), ("pooled", pooled.model))}
    assert errors["pooled"] < errors["single"] < errors["prior"], errors
    # 4 trained, the default one in five held out whole: the last flight
    meta = pooled.model.meta
    assert [f["name"] for f in meta["training_flights"]] == [f.name for f in drag_flights[:4]]
    assert [f["name"] for f in meta["validation_flights"]] == [drag_flights[4].name]
    assert meta["validation"] == "held-out flights" and meta["learned"] is True and pooled.learned
    assert meta["training_flight"] == drag_flights[0].name and meta["system"] == "crazyflie"
    assert len(pooled.validation_losses) == CRAZYFLIE_TRAINING.epochs
    assert meta["best_validation_loss"] == pytest.approx(min(pooled.validation_losses))
    # every flight's own thrust gain is recorded and fed in: each sim's battery sags differently
    assert all(0.9 < f["thrust_gain"] < 1.1 for f in meta["training_flights"])


def test_records_that_follow_the_prior_teach_nothing_and_the_model_says_so():
    """The 'flights' are the Crazyflie prior itself, integrated along simulated flights' inputs with zero-mean
    process noise: the best one-step predictor of a record it never saw is the prior, so no epoch beats it."""
    records = []
    for seed in range(4):
        flight = simulate_crazyflie(SimulatedFlight(duration_s=12), seed=seed)
        system, zeta, u, _ = Algorithm1().observe_flight(flight, "crazyflie")
        prior = HybridModel(system, "prior")
        rng = np.random.default_rng(100 + seed)
        noise = np.r_[np.full(3, 1e-5), np.full(3, 1e-3), np.full(3, 3e-2)]
        x = np.empty_like(zeta)
        x[0] = zeta[0]
        for k in range(len(x) - 1):
            x[k + 1] = prior.step(x[k], u[k], flight.dt) + noise * rng.standard_normal(9)
        records.append(TrainingRecord(flight.name, x, u, flight.dt))
    result = train_knode_pooled(system, records, [False, False, False, True], CRAZYFLIE_TRAINING)
    meta = result.model.meta
    assert meta["best_epoch"] == -1 and meta["learned"] is False and not result.learned
    assert meta["learned_note"] == NOT_LEARNED
    assert meta["envelope"]["residual_rms"] == 0.0
    x, u, dt = records[3].zeta, records[3].u, records[3].dt
    assert np.array_equal(result.model.step(x, u, dt), HybridModel(system, "prior").step(x, u, dt))


def _records(n: int, seed: int = 0) -> list[TrainingRecord]:
    """Smooth random-motion records of the kinematic quadrotor (observer-like states, noise)."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        t = np.arange(300 + 50 * i) * 0.01
        p = np.column_stack([np.sin(t * rng.uniform(0.5, 2)), np.cos(t * rng.uniform(0.5, 2)), 0.1 * t])
        v = np.gradient(p, 0.01, axis=0)
        a = np.gradient(v, 0.01, axis=0)
        out.append(TrainingRecord(f"r{i}", np.hstack([p, v, a]) + 1e-3 * rng.standard_normal((len(t), 9)),
                                  np.zeros((len(t), 0)), 0.01))
    return out


def test_the_held_out_flight_never_enters_training():
    """Swap the held-out record for a different one: every training loss stays the same to the last bit
    (the loss, the residual's standardisation and the envelope see training records only), while the
    validation curve follows the new record."""
    system = make_system("quadrotor", dt=0.01)
    config = replace(CRAZYFLIE_TRAINING, epochs=15)
    records = _records(3)
    first = train_knode_pooled(system, records, [False, False, True], config)
    other = _records(4, seed=9)[3]
    second = train_knode_pooled(system, [*records[:2], replace(other, name="r2")], [False, False, True], config)
    assert first.losses == second.losses
    assert first.validation_losses != second.validation_losses
    assert first.model.meta["envelope"] == second.model.meta["envelope"]
    assert first.model.meta["training_records"] == ["r0", "r1"] and first.model.meta["validation_records"] == ["r2"]


def test_one_record_pooled_is_train_knode_bit_for_bit():
    system = make_system("quadrotor", dt=0.01)
    config = replace(CRAZYFLIE_TRAINING, epochs=10, validation_fraction=0.0)
    record = _records(1)[0]
    alone = train_knode(system, record.zeta, record.u, record.dt, config)
    pooled = train_knode_pooled(system, [record], [False], config)
    assert alone.losses == pooled.losses
    for (w1, b1), (w2, b2) in zip(alone.model.residual.layers, pooled.model.residual.layers):
        assert np.array_equal(w1, w2) and np.array_equal(b1, b2)
    # a flight alone is the paper's protocol: tests/estimators/test_algorithm1.py


@pytest.mark.parametrize("n, held", [(1, []), (2, [1]), (4, [3]), (5, [4]), (10, [4, 9]), (16, [4, 9, 15])])
def test_one_flight_in_five_is_held_out_by_default(n, held):
    assert default_validation(n) == held


def test_validation_choices_that_leave_nothing_or_name_a_stranger_are_refused(drag_flights):
    with pytest.raises(InvalidInput, match="every flight is held out"):
        train_on_flights(drag_flights[:2], validate=[f.name for f in drag_flights[:2]])
    with pytest.raises(InvalidInput, match="nowhere.*not among"):
        train_on_flights(drag_flights[:2], validate=["nowhere"])
    with pytest.raises(InvalidInput, match="more than once.*sim_crazyflie_0"):
        train_on_flights([drag_flights[0], drag_flights[0]])
    with pytest.raises(InvalidInput, match="held_out has 1 entries for 2 records"):
        train_knode_pooled(make_system("quadrotor", dt=0.01), _records(2), [False])


def test_flights_of_two_declared_vehicles_are_refused_naming_them():
    a, b = _sims(cf.IDENTIFIED, (0, 1), duration_s=8)
    a.meta["vehicle"], b.meta["vehicle"] = "cf_red", "cf_blue"
    with pytest.raises(InvalidInput, match=r"different vehicles \(cf_red: sim_crazyflie_0; cf_blue: sim_crazyflie_1\)"):
        train_on_flights([a, b], replace(CRAZYFLIE_TRAINING, epochs=1), system="crazyflie")
    a.meta["vehicle"] = b.meta["vehicle"] = "cf_red"
    a.meta["mass_kg"], b.meta["mass_kg"] = 0.032, 0.037
    with pytest.raises(InvalidInput, match=r"different masses \(32.0 g: sim_crazyflie_0; 37.0 g: sim_crazyflie_1\)"):
        train_on_flights([a, b], replace(CRAZYFLIE_TRAINING, epochs=1), system="crazyflie")


def test_a_flight_whose_thrust_map_is_another_vehicles_is_refused_naming_both_flights():
    """Other motors: a thrust map without the prior's quadratic PWM term gives 16 % more thrust at hover PWM,
    far outside one vehicle's spread of thrust gains, whatever its battery did."""
    ours = _sims(cf.IDENTIFIED, (0,), duration_s=10)[0]
    other = _sims({**cf.IDENTIFIED, "q_pwm2": 0.0}, (1,), duration_s=10)[0]
    other.meta["name"] = "other_motors"
    with pytest.raises(InvalidInput, match=r"disagree on the thrust map: thrust gain 1\.1\d+ on other_motors against "
                                           r"(1\.0|0\.9)\d+ on sim_crazyflie_0"):
        train_on_flights([ours, other], replace(CRAZYFLIE_TRAINING, epochs=1), system="crazyflie")
    # the kinematic prior has no thrust map: the same flights train one model
    assert train_on_flights([ours, other], replace(CRAZYFLIE_TRAINING, epochs=1)).model.kind == "knode"


def test_flights_with_different_prior_parameters_are_refused():
    flights = _sims(cf.IDENTIFIED, (0, 1), duration_s=8)
    systems = [system_for(f, "crazyflie") for f in flights]
    systems[1] = replace(systems[1], prior_params={**systems[1].prior_params, "m_kg": 0.03})
    with pytest.raises(InvalidInput, match=r"sim_crazyflie_1 and sim_crazyflie_0 have different prior parameters "
                                           r"\(m_kg\)"):
        check_one_vehicle(flights, systems, [1.0, 1.0])


def test_the_notebook_knode_fits_one_flight_or_a_list_of_flights(drag_flights):
    import learnest as le

    knode = le.KNODE(epochs=3).fit(drag_flights[:3])
    assert knode.system_ == "crazyflie"          # the simulated logs carry motor PWM and battery voltage
    assert knode.training_flights_ == ["sim_crazyflie_0", "sim_crazyflie_1"]
    assert knode.validation_flights_ == ["sim_crazyflie_2"] and isinstance(knode.learned_, bool)
    assert len(knode.validation_losses_) == 3 and knode.model_.kind == "knode"
    chosen = le.KNODE(epochs=2).fit(drag_flights[:3], validate=["sim_crazyflie_0"])
    assert chosen.validation_flights_ == ["sim_crazyflie_0"]
    one = le.KNODE(epochs=2).fit(drag_flights[0])
    assert one.training_flights_ == ["sim_crazyflie_0"] and one.validation_flights_ == []
    with pytest.raises(InvalidInput, match="a Flight or a list of Flights.*got str"):
        le.KNODE(epochs=2).fit([drag_flights[0], "sample_logs/circle_rep1.csv"])


def test_the_prior_validation_loss_is_the_held_out_loss_before_any_update():
    system = make_system("quadrotor", dt=0.01)
    records = _records(3)
    result = train_knode_pooled(system, records, [False, False, True], replace(CRAZYFLIE_TRAINING, epochs=3))
    prior = HybridModel(system, "prior")
    held = records[2]
    expected = np.mean(np.sum((prior.step(held.zeta[:-1], held.u[:-1], held.dt) - held.zeta[1:]) ** 2, axis=1))
    assert result.model.meta["prior_validation_loss"] == pytest.approx(expected, rel=1e-9)


def test_each_record_is_stepped_by_its_own_sample_period():
    """Records of the kinematic prior itself on a 100 Hz, a 250 Hz and a 50 Hz grid: the prior predicts every
    pair exactly only when each is stepped by its own record's dt (the pooled loss of the prior is then ~0)."""
    system = make_system("quadrotor", dt=0.01)
    prior = HybridModel(system, "prior")
    records = []
    for i, dt in enumerate((0.01, 0.004, 0.02)):
        x = np.zeros((200, 9))
        x[0, 3:] = [0.3, -0.2, 0.1, 1.0, 0.5, -0.4]
        for k in range(len(x) - 1):
            x[k + 1] = prior.step(x[k], None, dt)
        records.append(TrainingRecord(f"r{i}", x, np.zeros((200, 0)), dt))
    result = train_knode_pooled(system, records, [False, True, True], replace(CRAZYFLIE_TRAINING, epochs=1))
    assert result.model.meta["prior_validation_loss"] < 1e-20
    wrong = train_knode_pooled(system, [replace(r, dt=0.01) for r in records], [False, True, True],
                               replace(CRAZYFLIE_TRAINING, epochs=1))
    assert wrong.model.meta["prior_validation_loss"] > 1e-6


@pytest.mark.data
def test_the_shared_nanobench_flights_are_one_vehicle_and_a_changed_thrust_map_is_not():
    """All 29 NanoBench flights of CF_01 that pass the quality checks (circles, figure-eights, helices, ramps; one
    flown by another controller) pass the one-vehicle check; the same flights with one flight's motors giving
    20 % more thrust per PWM (other motors, or another vehicle's log) are refused, naming that flight."""
    from pathlib import Path

    from learnest.ingest import read_flights
    from learnest.models.inputs import thrust_calibration

    shared = Path(__file__).resolve().parents[3] / "shared" / "data"
    flights = [f for f in read_flights(sorted([*shared.glob("nanobench/*.csv"), *shared.glob("nanobench-more/*.csv")]))
               if f.quality["ok"]]
    assert len(flights) == 29
    systems = [system_for(f, "crazyflie") for f in flights]
    gains = [thrust_calibration(f, s)["thrust_gain"] for f, s in zip(flights, systems)]
    check_one_vehicle(flights, systems, gains)
    gains[7] *= 1.2
    with pytest.raises(InvalidInput, match=f"thrust gain 1\\.1\\d+ on {flights[7].name} against"):
        check_one_vehicle(flights, systems, gains)


def test_a_pooled_models_profile_holds_the_rates_its_flights_share_and_none_it_saw_several_of():
    from learnest.ingest.profile import profile_mismatches

    flights = _sims(cf.IDENTIFIED, (0, 1, 2), duration_s=6)
    for flight, acc in zip(flights, (77.5, 98.2, 100.1)):
        flight.meta["original_rates"] = {"acc": acc, "mocap": 100.0}
    profile = pooled_profile(flights)
    assert profile["rates_hz"]["acc"] is None and profile["rates_hz"]["mocap"] == 100.0
    assert pooled_profile(flights[1:])["rates_hz"]["acc"] == pytest.approx(99.2)
    # an evaluation flight at any of the rates trained on is not "another rate"; a 250 Hz log still is
    assert profile_mismatches(profile, {**profile, "rates_hz": {"acc": 77.5, "mocap": 100.0, "grid": None}}) == []
    other = profile_mismatches(profile, {**profile, "rates_hz": {"acc": 77.5, "mocap": 250.0, "grid": None}})
    assert other == ["another mocap rate: 250 Hz, model trained at 100 Hz"]


def test_a_model_trained_with_nothing_held_out_says_it_was_not_checked():
    from learnest.models.training import NOT_CHECKED

    system = make_system("quadrotor", dt=0.01)
    record = _records(1)[0]
    alone = train_knode(system, record.zeta, record.u, record.dt, replace(CRAZYFLIE_TRAINING, epochs=2,
                                                                           validation_fraction=0.0))
    pooled = train_knode_pooled(system, _records(2), [False, False], replace(CRAZYFLIE_TRAINING, epochs=2))
    for result in (alone, pooled):
        assert result.model.meta["learned"] is True and result.model.meta["learned_note"] == NOT_CHECKED
        assert result.model.meta["best_validation_loss"] is None


def _yawed(zeta: np.ndarray, u: np.ndarray, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    """The same states and inputs seen from a frame turned by ``yaw`` about the vertical: positions, velocities and
    accelerations rotated, the attitude quaternion (scalar last) premultiplied by the yaw's."""
    c, s = np.cos(yaw), np.sin(yaw)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    zeta = zeta.copy()
    for block in (slice(0, 3), slice(3, 6), slice(6, 9)):
        zeta[:, block] = zeta[:, block] @ turn.T
    qx, qy, qz, qw = u[:, :4].T
    hz, hw = np.sin(yaw / 2), np.cos(yaw / 2)       # q_yaw = (0, 0, sin ψ/2, cos ψ/2)
    u = u.copy()
    u[:, :4] = np.stack([hw * qx - hz * qy, hw * qy + hz * qx, hw * qz + hz * qw, hw * qw - hz * qz], axis=1)
    return zeta, u


def test_a_pooled_body_frame_residual_turns_with_the_vehicle_and_still_learns_the_drag(drag_flights):
    """The Crazyflie's residual reads the body frame (`models.residual_frame`): seen from a frame turned about the
    vertical, the correction it adds to ȧ turns with it exactly, and it adds nothing to ṗ and v̇.  Pooled, it is
    blind to the battery (its first layer's battery column is exact zeros), and the 3-fold rotor drag (a function of
    the body velocity) is still learned: the unseen flight is predicted better than by the prior."""
    test = drag_flights[5]
    blind = train_on_flights(drag_flights[:5], CRAZYFLIE_TRAINING, system="crazyflie")
    residual = blind.model.residual
    assert residual.frame == "body"
    assert np.all(residual.layers[0][0][:, list(BODY_FEATURES).index("vbat")] == 0.0)
    assert set(ATTITUDE_INPUTS) <= set(blind.model.meta["residual_blind"])
    _, zeta, u, _ = Algorithm1().observe_flight(test, "crazyflie")
    added = residual(zeta, u)
    assert np.all(added[:, :6] == 0.0) and np.abs(added[:, 6:]).max() > 0
    yaw = 2.1
    turned = residual(*_yawed(zeta, u, yaw))
    np.testing.assert_allclose(turned[:, 6:], _yawed(added, u, yaw)[0][:, 6:], atol=1e-12)
    system = system_for(test, "crazyflie")
    prior = HybridModel(system, "prior")
    assert _one_step_error(blind.model, test) < _one_step_error(prior, test)


def test_a_pooled_body_residual_leaves_the_drag_along_the_thrust_axis_to_the_prior(drag_flights):
    """A body residual does not read the velocity along the thrust axis (`UNREAD_BODY_FEATURES`): on an unseen
    flight's states, moving the velocity along the thrust axis b₃ changes the KNODE's ȧ exactly as it changes the
    prior's (the residual's derivative there is zero), so an MHE draws no vertical velocity from a vertical drag the
    flights never determined.  Across the axis it still learns the 3-fold rotor drag: its effective k_xy,
    −tau_s · b₁ᵀ∂ȧ/∂v_bx, moves from the prior's 0.40 towards the truth's 1.2 (about 0.7 on these flights)."""
    model = train_on_flights(drag_flights[:5], CRAZYFLIE_TRAINING, system="crazyflie").model
    assert UNREAD_BODY_FEATURES == ("vbz",)
    assert np.all(model.residual.layers[0][0][:, list(BODY_FEATURES).index("vbz")] == 0.0)
    _, zeta, u, _ = Algorithm1().observe_flight(drag_flights[5], "crazyflie")
    prior = HybridModel(model.system, "prior")
    R = np.array(cf.rotation_columns(*u[:, :4].T)).transpose(2, 0, 1)    # (T, 3, 3), body -> world
    step = 0.05                                                             # m/s

    def change(candidate, axis):
        moved = zeta.copy()
        moved[:, 3:6] += step * R[:, :, axis]
        return candidate.f_c(moved, u) - candidate.f_c(zeta, u)

    np.testing.assert_allclose(change(model, 2), change(prior, 2), rtol=0, atol=1e-9)
    assert np.abs(change(prior, 2)[:, 6:]).max() > 0.05          # the prior's own k_z is there
    params = model.system.prior_params
    across = np.einsum("ti,ti->t", change(model, 0)[:, 6:], R[:, :, 0]) / step
    assert np.median(-params["tau_s"] * across) > params["k_xy"] + 0.15


def test_attitude_blind_leaves_a_system_without_attitude_inputs_alone():
    quadrotor = make_system("quadrotor")
    assert attitude_blind(quadrotor) is quadrotor
    crazyflie = make_system("crazyflie")
    inputs, outputs = attitude_blind(crazyflie).residual_masks()
    names = [*crazyflie.state_names, *crazyflie.input_names]
    assert [k for k, m in zip(names, inputs) if m == 0.0] == [*crazyflie.residual_blind, *ATTITUDE_INPUTS]
    np.testing.assert_array_equal(outputs, crazyflie.residual_masks()[1])
    inputs, _ = attitude_blind(crazyflie, battery=True).residual_masks()
    assert [k for k, m in zip(names, inputs) if m == 0.0] == [*crazyflie.residual_blind, *ATTITUDE_INPUTS,
                                                              *BATTERY_INPUTS]


@pytest.mark.parametrize("frame", ["state", "body"])
def test_members_trained_side_by_side_are_the_members_trained_alone(frame):
    """An ensemble's members train as one stacked network (on one thread per core): member k must come out as
    `train_knode_pooled` trains it alone from seed + k (its initial weights and its mini-batch order), in the state
    frame of the kinematic prior and the body frame of the Crazyflie prior."""
    if frame == "state":
        system, records = make_system("quadrotor", dt=0.01), _records(3)
    else:
        records = []
        for seed in range(3):
            flight = simulate_crazyflie(SimulatedFlight(duration_s=4), seed=seed)
            system, zeta, u, _ = Algorithm1().observe_flight(flight, "crazyflie")
            records.append(TrainingRecord(flight.name, zeta, u, flight.dt))
    config = replace(CRAZYFLIE_TRAINING, epochs=6, batch_size=128, seed=3, residual_frame=frame)
    together = train_members_pooled(system, records, [False, False, True], config, members=3)
    for k, member in enumerate(together):
        alone = train_knode_pooled(system, records, [False, False, True], replace(config, seed=3 + k))
        assert member.model.meta["training"]["seed"] == 3 + k
        assert member.model.meta["best_epoch"] == alone.model.meta["best_epoch"]
        np.testing.assert_allclose(member.losses, alone.losses, rtol=1e-9)
        np.testing.assert_allclose(member.validation_losses, alone.validation_losses, rtol=1e-9)
        for (w, b), (w_alone, b_alone) in zip(member.model.residual.layers, alone.model.residual.layers):
            np.testing.assert_allclose(w, w_alone, rtol=1e-9, atol=1e-12)
            np.testing.assert_allclose(b, b_alone, rtol=1e-9, atol=1e-12)
    assert together[0].model.residual.layers[0][0].tolist() != together[1].model.residual.layers[0][0].tolist()
