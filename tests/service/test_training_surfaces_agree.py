"""The same flights and settings give the same model in a notebook (`read_flights` + `train_on_flights`) and
through the registry (`learnest train FILE...`: the flights stored, reloaded and trained in a job).

Eight simulated Crazyflie flights of two declared trajectory families, three circles then five figure-eights: one
in five of the eight (`default_validation`: the 4th and the 8th, the first and the last figure-eight) is held out
whole.  The residual's scale is chosen by holding out each family in turn (`estimators.group_training`); the
inner training on the five figure-eights must hold out both named figure-eights on either surface (picking its
own one in five of its five flights would hold out the last one only), else the inner residuals, the gap scores
and the chosen scale depend on where the model was trained.
"""
import contextlib
import io
import json
from dataclasses import replace

import numpy as np

FAMILIES = ("circle",) * 3 + ("figure_eight",) * 5
EPOCHS = 6


def write_flights(folder) -> list:
    from learnest.ingest.formats.nanobench import writer as nanobench
    from learnest.models import crazyflie as cf
    from learnest.models.crazyflie.simulate_crazyflie import SimulatedFlight, simulate_crazyflie

    paths = []
    for seed, family in enumerate(FAMILIES):
        flight = simulate_crazyflie(SimulatedFlight(truth={**cf.IDENTIFIED, "k_xy": 4 * cf.IDENTIFIED["k_xy"]},
                                                    duration_s=14.0), seed=seed)
        paths.append(folder / f"f{seed}_{family}.csv")
        nanobench.write(paths[-1], flight.t + 1.7e9, flight.p, flight.quat, flight.channels["acc_body"] / cf.GRAVITY,
                        motors=flight.channels["motors"], vbat=flight.channels["vbat"],
                        metadata={"trajectory_type": family})
    return paths


def test_the_library_and_the_cli_train_the_same_model(tmp_path, monkeypatch):
    from learnest.ingest import read_flights
    from learnest.models.presets import CRAZYFLIE_TRAINING
    from learnest.service.cli import main
    from learnest.service.storage.registry import load_model_ref
    from learnest.workflows.flights import train_on_flights

    paths = write_flights(tmp_path)
    flights = read_flights(paths)
    assert all(f.quality["ok"] for f in flights)
    library = train_on_flights(flights, replace(CRAZYFLIE_TRAINING, epochs=EPOCHS), system="crazyflie").model

    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["train", *map(str, paths), "--system", "crazyflie", "--name", "same", "--epochs", str(EPOCHS),
                     "--json"]) == 0
    cli = json.loads(out.getvalue())
    stored = load_model_ref("same:1")

    held = ["f3_figure_eight", "f7_figure_eight"]
    assert cli["validation_flights"] == held
    assert [f["name"] for f in library.meta["validation_flights"]] == held
    choice, stored_choice = library.meta["residual_scale_choice"], stored.meta["residual_scale_choice"]
    # the inner training without the circles holds out both named figure-eights, the one without the
    # figure-eights its own one in five of the three circles, on both surfaces
    assert choice["inner_trainings"]["circle"]["validation_flights"] == held
    assert choice["inner_trainings"]["figure_eight"]["validation_flights"] == ["f2_circle"]
    assert stored_choice["inner_trainings"] == choice["inner_trainings"]
    assert stored_choice["scales"] == choice["scales"]    # every inner gap gain, to the last bit
    assert cli["residual_scale"] == library.meta["residual_scale"] == choice["chosen"]
    assert stored.meta["best_epoch"] == library.meta["best_epoch"]
    for (w, b), (w0, b0) in zip(stored.residual.layers, library.residual.layers, strict=True):
        np.testing.assert_array_equal(w, w0)
        np.testing.assert_array_equal(b, b0)
