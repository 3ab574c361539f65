"""A model's noise: the UKF's innovation likelihood against the Kalman filter's, maximum likelihood recovering a
simulated Q and R, and the noise travelling with the model into every estimator of an evaluation."""
import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from learnest.errors import InvalidInput
from learnest.estimators.gap_plan import GapPlan
from learnest.estimators.mocap_gaps import PositionGapModel, gap_mask, masked_measurements
from learnest.estimators.noise_identification import NoiseRecord, identify_noise
from learnest.estimators.params import EstimatorParams
from learnest.estimators.ukf import compiled_sigma_functions, run_ukf
from learnest.models.knode import HybridModel
from learnest.models.noise import IDENTIFIED, PAPER, NoiseModel, blocks
from learnest.models.systems import make_system

# the truth of the simulated flights: the paper's noise with these factors on each block's standard deviation
# (the order of what the real NanoBench flights identify: velocity and acceleration noise well above the paper's)
TRUE_FACTORS = {"Q:v": 20.0, "Q:a": 2.0, "R:p": 2.0, "R:a": 0.5}


def _scaled(noise: NoiseModel, system, factors: dict) -> NoiseModel:
    q, r = np.array(noise.process_std), np.array(noise.meas_std)
    for name, factor in factors.items():
        kind, block = name.split(":")
        if kind == "Q":
            q[blocks(system.state_names)[block]] *= factor
        else:
            r[blocks(system.meas_names)[block]] *= factor
    return NoiseModel(tuple(q), tuple(r), noise.initial_std)


def _simulate_chain(model: HybridModel, noise: NoiseModel, steps: int, seed: int):
    """The kinematic chain (linear) driven by white process noise Q, measured with white noise R."""
    rng = np.random.default_rng(seed)
    x = np.zeros((steps, model.n))
    x[0] = [0.0, 0.0, 1.0, 0.3, -0.2, 0.0, 0.0, 0.0, 0.0]
    q = np.asarray(noise.process_std)
    for k in range(steps - 1):
        x[k + 1] = model.step(x[k], np.zeros(0), model.system.dt) + rng.normal(size=model.n) * q
    y = model.h(x) + rng.normal(size=(steps, model.n_meas)) * np.asarray(noise.meas_std)
    return x, y


def test_the_ukf_log_likelihood_of_a_linear_model_is_the_kalman_filters():
    """On the linear kinematic chain the UKF is the Kalman filter, so its innovation log-likelihood per step must
    be filterpy's KalmanFilter.log_likelihood, in the C loop and in the Python one alike."""
    system = make_system("quadrotor", prior_params={"omega": 0.0, "decay": 0.0})
    model = HybridModel(system, "prior")
    noise = _scaled(NoiseModel.paper(system), system, TRUE_FACTORS)
    x, y = _simulate_chain(model, noise, 300, seed=1)
    x0 = x[0] + 0.01
    kf = KalmanFilter(dim_x=9, dim_z=6)
    kf.F = np.array([model.step(e, np.zeros(0), system.dt) for e in np.eye(9)]).T
    kf.H = np.array([model.h(e) for e in np.eye(9)]).T
    kf.Q, kf.R, kf.x, kf.P = noise.Q, noise.R, x0.copy(), noise.P0.copy()
    expected = []
    for k in range(len(y)):
        if k:
            kf.predict()
        kf.update(y[k])
        expected.append(kf.log_likelihood)
    params = EstimatorParams.from_noise(model, system.dt, noise, x0)
    python = run_ukf(params, y, None).log_likelihoods
    native = run_ukf(params, y, None, sigma_functions=compiled_sigma_functions(model, system.dt)).log_likelihoods
    np.testing.assert_allclose(python, expected, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(native, expected, rtol=1e-6, atol=1e-6)


def test_maximum_likelihood_recovers_a_simulated_q_and_r_within_20_percent():
    """Simulated flights whose process and sensor noise are known: the identified variance of every searched block
    (velocity and acceleration process noise, mocap and accelerometer noise) is within 20 % of the truth."""
    system = make_system("quadrotor", prior_params={"omega": 0.0, "decay": 0.0})
    model = HybridModel(system, "prior")
    paper = NoiseModel.paper(system)
    truth = _scaled(paper, system, TRUE_FACTORS)
    records = []
    for seed in (2, 3):
        x, y = _simulate_chain(model, truth, 2500, seed)
        records.append(NoiseRecord(f"sim{seed}", model, y, np.zeros((len(y), 0)), x[0], system.dt))
    found = identify_noise(records, paper)
    assert found.source == IDENTIFIED
    for name, factor in TRUE_FACTORS.items():
        assert found.detail["factors"][name] ** 2 == pytest.approx(factor ** 2, rel=0.2), name
    np.testing.assert_allclose(np.diag(found.Q)[3:], np.diag(truth.Q)[3:], rtol=0.2)
    np.testing.assert_allclose(np.diag(found.R), np.diag(truth.R), rtol=0.2)
    likelihood = found.detail["log_likelihood_per_step"]
    assert likelihood["identified"] > likelihood["start"]
    assert found.detail["held"] == ["Q:p"] and not found.detail["at_bound"]
    # begun near the answer (as a KNODE's search begins at its prior's), the search lands on the same noise
    # in fewer filter runs, its factors still on the start's noise
    nearby = _scaled(paper, system, {name: 1.15 * factor for name, factor in TRUE_FACTORS.items()})
    near = identify_noise(records, paper, initial=nearby)
    for name, factor in found.detail["factors"].items():
        assert near.detail["factors"][name] == pytest.approx(factor, rel=0.05), name
    assert near.detail["evaluations"] < found.detail["evaluations"]
    assert near.detail["log_likelihood_per_step"]["start"] == likelihood["start"]


def test_the_hidden_mocap_likelihood_recovers_a_simulated_q_within_20_percent():
    """The flights' objective (the innovations' likelihood plus that of the mocap hidden in gaps under the
    filter's prediction) on simulated flights with known noise: the identified velocity and acceleration process
    variances are within 20 % of the truth, the sensors' noise held at theirs, as on real flights."""
    system = make_system("quadrotor", prior_params={"omega": 0.0, "decay": 0.0})
    model = HybridModel(system, "prior")
    truth = _scaled(NoiseModel.paper(system), system, TRUE_FACTORS)
    start = NoiseModel(NoiseModel.paper(system).process_std, truth.meas_std, truth.initial_std)
    plan, records = GapPlan(), []
    for seed in (4, 5):
        x, y = _simulate_chain(model, truth, 20000, seed)   # 200 s each: the hidden mocap is a fifth of it
        inside = gap_mask(len(y), plan.windows(len(y), system.dt))
        y_gap, u_gap = masked_measurements(y, np.zeros((len(y), 0)), inside)
        records.append(NoiseRecord(f"sim{seed}", PositionGapModel(model), y_gap, u_gap, x[0], system.dt,
                                   hidden=y[:, :3].copy(), inside=inside))
    found = identify_noise(records, start, measurement_blocks=())
    assert "plus the likelihood of the mocap hidden in gaps" in found.detail["method"]
    for name in ("Q:v", "Q:a"):
        assert found.detail["factors"][name] ** 2 == pytest.approx(TRUE_FACTORS[name] ** 2, rel=0.2), name


def test_identification_refuses_what_it_cannot_use():
    system = make_system("quadrotor")
    model = HybridModel(system, "prior")
    with pytest.raises(InvalidInput, match="at least one flight"):
        identify_noise([], NoiseModel.paper(system))
    short = NoiseRecord("short", model, np.zeros((50, 6)), np.zeros((50, 0)), np.zeros(9), 0.01)
    with pytest.raises(InvalidInput, match="warm-up"):
        identify_noise([short], NoiseModel.paper(system))
    with pytest.raises(InvalidInput, match="no state block named w"):
        identify_noise([short], NoiseModel.paper(system), process_blocks=("w",))


def test_a_models_noise_is_stored_with_it_and_runs_each_filter(tmp_path):
    """The noise survives save/load, `prepare` gives the KNODE its noise and the prior its own, and
    ``noise="paper"`` gives both the system's fixed noise."""
    from learnest.estimators.prepared import noise_models

    system = make_system("crazyflie")
    paper = NoiseModel.paper(system)
    own = _scaled(paper, system, {"Q:v": 10.0})
    prior = _scaled(paper, system, {"Q:v": 30.0, "Q:a": 3.0})
    own = NoiseModel(own.process_std, own.meas_std, own.initial_std, IDENTIFIED, {"flights": ["a"]})
    prior = NoiseModel(prior.process_std, prior.meas_std, prior.initial_std, IDENTIFIED)
    model = HybridModel(system, "prior", noise=own, prior_noise=prior)
    model.save(tmp_path / "m.json")
    loaded = HybridModel.load(tmp_path / "m.json")
    assert loaded.noise == own and loaded.prior_noise == prior
    assert noise_models(loaded, system) == (own, prior)
    assert noise_models(loaded, system, PAPER) == (paper, paper)
    assert noise_models(HybridModel(system, "prior"), system) == (paper, paper)
    np.testing.assert_allclose(own.apply(system).Q, own.Q)
    with pytest.raises(InvalidInput, match="noise must be one of"):
        noise_models(loaded, system, "tuned")
    with pytest.raises(InvalidInput, match="does not fit"):
        own.apply(make_system("cartpole"))
    with pytest.raises(InvalidInput, match="finite and non-negative"):
        NoiseModel((float("nan"),), (1.0,), (1.0,))


@pytest.mark.data
def test_an_evaluation_runs_each_model_with_its_own_noise_and_says_which():
    """On a real flight: the report names the noise of every method, the prior rows change when the prior's
    noise changes and the KNODE rows do not, and noise="paper" puts both back on the fixed noise."""
    from pathlib import Path

    import learnest as le
    from learnest.estimators.prepared import system_for

    shared = Path(__file__).resolve().parents[3] / "shared" / "data"
    flight = le.read_flights([shared / "nanobench" / "B2_circle_medium_rep1.csv"])[0]
    system = system_for(flight, "crazyflie")
    paper = NoiseModel.paper(system)
    tuned = _scaled(paper, system, {"Q:v": 30.0, "Q:a": 3.0})
    tuned = NoiseModel(tuned.process_std, tuned.meas_std, tuned.initial_std, IDENTIFIED)
    # a "KNODE" that is the prior with the fixed noise, beside its prior with tuned noise: only the prior rows move
    model = HybridModel(system, "prior", noise=paper, prior_noise=tuned)
    methods = ("ukf", "knode-ukf")
    identified = le.evaluate(model, [flight], methods=methods, gap_s=0)
    fixed = le.evaluate(model, [flight], methods=methods, gap_s=0, noise="paper")
    assert identified["noise"] == {"ukf": IDENTIFIED, "knode-ukf": PAPER}
    assert fixed["noise"] == {"ukf": PAPER, "knode-ukf": PAPER}
    assert identified["flights"][0]["noise"] == identified["noise"]
    assert identified["median"]["knode-ukf"] == pytest.approx(fixed["median"]["knode-ukf"], rel=1e-9)
    assert fixed["median"]["ukf"] == pytest.approx(fixed["median"]["knode-ukf"], rel=1e-9)
    assert identified["median"]["ukf"] != pytest.approx(fixed["median"]["ukf"], rel=1e-3)


def test_a_training_asked_to_identify_noise_stores_the_models_and_its_priors(tmp_path):
    """``KNODE(noise="identified")``: the trained model carries its own noise and its prior's, both identified on
    its training flight from the paper's noise (the sensors' noise kept), and both survive the model file."""
    from pathlib import Path

    import learnest as le

    sample = Path(__file__).resolve().parents[2] / "sample_logs" / "circle_rep1.csv"
    flight = le.read_flights([sample])[0]
    knode = le.KNODE(epochs=3, noise="identified").fit(flight)
    model = knode.model_
    paper = NoiseModel.paper(model.system)
    for noise in (model.noise, model.prior_noise):
        assert noise.source == IDENTIFIED and noise.detail["flights"] == [flight.name]
        assert noise.meas_std == paper.meas_std and set(noise.detail["factors"]) == {"Q:v", "Q:a"}
        assert noise.detail["log_likelihood_per_step"]["identified"] >= noise.detail["log_likelihood_per_step"]["start"]
    model.save(tmp_path / "knode.json")
    assert HybridModel.load(tmp_path / "knode.json").noise == model.noise
    default = le.KNODE(epochs=3).fit(flight).model_.noise           # identified by default
    assert default.source == IDENTIFIED and default.process_std == model.noise.process_std
    assert le.KNODE(epochs=3, noise="paper").fit(flight).model_.noise is None   # the paper's protocol on request
