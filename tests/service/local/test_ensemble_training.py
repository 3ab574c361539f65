"""`learnest train --ensemble K`: the registry stores a model whose residual is the mean of K members trained from
different seeds, and says how many; an evaluation runs its KNODE with the members' spread in its process noise."""
from __future__ import annotations

import json

import numpy as np

from learnest.estimators.prepared import prepare
from learnest.ingest import read_flights
from learnest.ingest.formats.nanobench import writer as nanobench
from learnest.models import crazyflie as cf
from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie
from learnest.service.cli import main
from learnest.service.local import load_model


def test_train_with_an_ensemble_stores_its_members_and_their_spread_joins_the_knode_noise(tmp_path, monkeypatch,
                                                                                            capsys):
    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    truth = {**cf.IDENTIFIED, "k_xy": 3 * cf.IDENTIFIED["k_xy"]}
    paths = []
    for seed in range(3):
        flight = simulate_crazyflie(SimulatedFlight(truth=truth, duration_s=12.0), seed=seed)
        paths.append(str(tmp_path / f"sim{seed}.csv"))
        nanobench.write(paths[-1], flight.t + 1.7e9, flight.p, flight.quat, flight.channels["acc_body"] / cf.GRAVITY,
                        motors=flight.channels["motors"], vbat=flight.channels["vbat"])
    assert main(["train", *paths, "--name", "ens", "--system", "crazyflie", "--epochs", "20", "--ensemble", "3",
                 "--group-by", "none", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["version"] == 1
    model = load_model("ens:1")
    assert model.residual.frame == "body" and len(model.residual.members) == 3
    assert model.meta["ensemble"]["members"] == 3 and model.meta["ensemble"]["seeds"] == [0, 1, 2]
    x = np.zeros((1, 9))
    u = np.array([[0.0, 0.0, 0.0, 1.0, 4e4, 4e4, 4e4, 4e4, 3.9]])
    np.testing.assert_allclose(model.residual(x, u), np.mean([m(x, u) for m in model.residual.members], axis=0),
                               atol=1e-12)
    scored = read_flights([paths[0]])[0]
    knode_q = np.diag(prepare(model, scored).model.system.Q)
    own = np.square(np.asarray(model.noise.process_std))     # identified on the training flights, by default
    assert model.noise.source == "identified"
    assert np.all(knode_q[6:] > own[6:])   # the spread added, acceleration rows
    assert np.array_equal(knode_q[:6], own[:6])
    assert main(["models", "show", "ens:1"]) == 0
    shown = capsys.readouterr().out
    assert "residual: body frame" in shown and "mean of an ensemble of 3" in shown, shown
