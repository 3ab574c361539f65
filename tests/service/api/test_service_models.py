"""HTTP service, /models and /jobs: training as a job, immutable versions with provenance, aliases, loading
"name:version" / "name@alias" from the API and from Python (service.storage.registry.load_model_ref)."""
import json
import threading

import numpy as np
import pytest
from utils.service import (
    EPOCHS,
    flight_csv,
    running_app,
    settings_for,
    train,
    upload,
    wait_for_job,
)


def test_training_registers_versions_and_aliases(tmp_path, data_dir):
    from learnest.service.storage.registry import load_model_ref

    home = tmp_path / "home"
    with running_app(home) as client:
        flight = upload(client, flight_csv(data_dir, 0)).json()
        accepted = client.post("/models", json={"name": "quad", "flight_id": flight["id"], "epochs": EPOCHS,
                                                "hidden": 8, "lr": 0.01})
        assert accepted.status_code == 202, accepted.text
        assert accepted.json()["version"] == 1 and accepted.json()["status"] == "training"
        assert accepted.headers["location"] == f"/jobs/{accepted.json()['job_id']}"
        job = wait_for_job(client, accepted.json()["job_id"])
        assert job["state"] == "succeeded" and job["progress"] == 1.0 and job["kind"] == "training"
        assert job["result"]["name"] == "quad" and job["result"]["version"] == 1 and job["error"] is None

        v1 = client.get("/models/quad/versions/1").json()
        assert v1["status"] == "ready"
        assert v1["training_flight"] == {"id": flight["id"], "sha256": flight["sha256"], "name": flight["name"]}
        assert v1["hyperparameters"]["epochs"] == EPOCHS and v1["hyperparameters"]["hidden"] == 8
        assert v1["hyperparameters"]["lr"] == 0.01 and v1["hyperparameters"]["validation_fraction"] == 0.2
        assert len(v1["losses"]) == EPOCHS and v1["training_seconds"] > 0
        assert v1["prior"]["system"] == "quadrotor" and v1["parent"] is None
        assert v1["code_version"]["package"] == "learnest" and v1["code_version"]["version"]
        assert {"torch", "casadi", "filterpy", "numpy"} <= set(v1["library_versions"])
        assert all(v1["library_versions"][k] for k in ("torch", "casadi", "filterpy", "numpy"))

        # a derived version: next integer, parent recorded
        second = train(client, "quad", flight["id"], parent="quad:1")
        assert second["version"] == 2
        assert client.get("/models/quad/versions/2").json()["parent"] == "quad:1"

        # aliases
        assert client.put("/models/quad/aliases/production", json={"version": 1}).json() == \
            {"name": "quad", "alias": "production", "version": 1}
        assert client.get("/models/quad/aliases/production").json()["version"] == 1
        model = client.get("/models/quad").json()
        assert model["aliases"] == {"production": 1} and model["latest_version"] == 2
        assert [v["version"] for v in model["versions"]] == [1, 2] and model["versions"][0]["aliases"] == ["production"]
        listing = client.get("/models").json()
        assert listing["items"][0]["name"] == "quad" and listing["items"][0]["version_count"] == 2
        assert client.put("/models/quad/aliases/production", json={"version": 7}).status_code == 404
        assert client.put("/models/quad/aliases/staging", json={"version": 2}).status_code == 200
        assert client.delete("/models/quad/aliases/staging").status_code == 204
        assert client.get("/models/quad/aliases/staging").status_code == 404

        weights = client.get("/models/quad/versions/1/weights")
        assert weights.status_code == 200 and json.loads(weights.content)["format"] == "learnest-model/1"

    # from Python (and the CLI): by alias and by version, through the registry
    by_alias = load_model_ref("quad@production", settings_for(home))
    by_version = load_model_ref("quad:1", settings_for(home))
    latest = load_model_ref("quad", settings_for(home))
    assert by_alias.meta["ref"] == by_version.meta["ref"] == "quad:1" and latest.meta["version"] == 2
    stored = json.loads(weights.content)["residual"]["layers"]
    for (w, b), (w_ref, b_ref) in zip(by_alias.residual.layers, stored):
        np.testing.assert_array_equal(w, np.asarray(w_ref))
        np.testing.assert_array_equal(b, np.asarray(b_ref))
    assert by_alias.meta["training_flight"] == flight["name"]
    with pytest.raises(LookupError, match="no alias 'staging'"):
        load_model_ref("quad@staging", settings_for(home))


def test_version_numbers_are_reserved_at_request_time(tmp_path, data_dir):
    with running_app(tmp_path / "home") as client:
        flight_id = upload(client, flight_csv(data_dir, 1)).json()["id"]
        answers = []

        def request():
            answers.append(client.post("/models", json={"name": "race", "flight_id": flight_id, "epochs": 1}).json())
        threads = [threading.Thread(target=request) for _ in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert sorted(a["version"] for a in answers) == [1, 2, 3, 4]
        # while training, a version exists with its status but is not usable
        pending = client.get("/models/race").json()["versions"]
        assert {v["status"] for v in pending} <= {"training", "ready"}
        for answer in answers:
            assert wait_for_job(client, answer["job_id"])["state"] == "succeeded"
        assert {v["status"] for v in client.get("/models/race").json()["versions"]} == {"ready"}


def test_training_on_a_flight_that_failed_quality_needs_include_bad(tmp_path, data_dir):
    # a 6 s recording has a flying part < 5 s: it fails the quality checks
    table_path = flight_csv(data_dir, 2, name="hover.csv", seconds=6.0)
    with running_app(tmp_path / "home") as client:
        bad = upload(client, table_path).json()
        assert bad["quality"]["ok"] is False
        refused = client.post("/models", json={"name": "m", "flight_id": bad["id"], "epochs": 1})
        assert refused.status_code == 422 and "quality" in refused.json()["detail"]
        assert client.get("/flights", params={"quality": "bad"}).json()["total"] == 1

        forced = client.post("/models", json={"name": "m", "flight_id": bad["id"], "epochs": 1, "include_bad": True})
        assert forced.status_code == 202
        assert wait_for_job(client, forced.json()["job_id"])["state"] == "succeeded"


def test_model_references_parse():
    from learnest.service.storage.registry import parse_ref

    assert str(parse_ref("quad:3")) == "quad:3" and parse_ref("quad:3").version == 3
    assert parse_ref("quad@production").alias == "production" and parse_ref("quad").version is None
    for bad in ("", "quad:", "quad@", "../x:1", "a:b", "quad:1@x"):
        with pytest.raises(ValueError):
            parse_ref(bad)


def test_training_with_the_crazyflie_prior_is_recorded_and_names_missing_inputs(tmp_path, data_dir):
    """The prior is a per-model choice: an unknown one is refused at the door, the chosen one is kept in
    the version's hyperparameters, and a flight without motor PWM / battery voltage fails the job with a
    message naming them (the kinematic prior trains on the same flight in the test above)."""
    with running_app(tmp_path / "home") as client:
        flight = upload(client, flight_csv(data_dir, 0)).json()
        wrong = client.post("/models", json={"name": "cf", "flight_id": flight["id"], "system": "helicopter"})
        assert wrong.status_code == 422
        accepted = client.post("/models", json={"name": "cf", "flight_id": flight["id"], "epochs": EPOCHS,
                                                "system": "crazyflie"})
        assert accepted.status_code == 202, accepted.text
        job = wait_for_job(client, accepted.json()["job_id"])
        assert job["state"] == "failed"
        assert "motor PWM" in job["error"] and "battery voltage" in job["error"]
        version = client.get("/models/cf/versions/1").json()
        assert version["hyperparameters"]["system"] == "crazyflie" and version["status"] == "failed"


def test_several_flights_by_name_groups_choose_the_residual_scale_and_the_version_says_so(tmp_path, data_dir):
    """POST /models with flight_ids and group_by "name:REGEX": each named group is held out in turn, and the
    version's residual_scale, residual_scale_groups and residual_scale_note (and its metadata) say what was kept;
    a grouping rule that cannot be read is refused before any job starts."""
    with running_app(tmp_path / "home") as client:
        ids = [upload(client, flight_csv(data_dir, seed)).json()["id"] for seed in (0, 1, 2)]
        refused = client.post("/models", json={"name": "g", "flight_ids": ids, "epochs": 2, "group_by": "name:("})
        assert refused.status_code == 422 and "does not compile" in refused.text
        refused = client.post("/models", json={"name": "g", "flight_ids": ids, "epochs": 2,
                                               "group_by": r"name:^(flight)(\d)"})
        assert refused.status_code == 422 and "exactly one capture group" in refused.text
        accepted = client.post("/models", json={"name": "g", "flight_ids": ids, "epochs": 2,
                                                "group_by": r"name:^flight(\d)"})
        assert accepted.status_code == 202, accepted.text
        assert wait_for_job(client, accepted.json()["job_id"])["state"] == "succeeded"
        version = client.get("/models/g/versions/1").json()
        assert version["hyperparameters"]["group_by"] == r"name:^flight(\d)"
        # identified unless asked for the paper's: the version says so, for the model and its prior
        assert version["hyperparameters"]["noise"] == "identified"
        assert {version["noise"][who]["source"] for who in ("model", "prior")} == {"identified"}
        assert version["residual_scale_groups"] == ["0", "1", "2"]
        assert version["residual_scale"] in (0.0, 0.25, 0.5, 0.75, 1.0)
        assert version["residual_scale_note"].startswith("chosen with 0, 1, 2 held out in turn: ")
        meta = client.get("/models/g/versions/1/metadata").json()
        assert meta["residual_scale"] == version["residual_scale"] and meta["residual_scale_groups"] == ["0", "1", "2"]
        assert set(meta["residual_scale_choice"]["groups"]) == {"0", "1", "2"}


def test_a_version_trained_with_identified_noise_carries_it_and_its_evaluations_say_so(tmp_path, data_dir):
    """POST /models with "noise": "identified": the version's noise names the flight it was identified on, and an
    evaluation runs each method with its model's noise ("noise" in the report), or with the fixed noise when asked."""
    with running_app(tmp_path / "home") as client:
        ids = [upload(client, flight_csv(data_dir, seed)).json()["id"] for seed in (0, 1)]
        assert client.post("/models", json={"name": "n", "flight_id": ids[0], "epochs": 2,
                                            "noise": "tuned"}).status_code == 422
        accepted = client.post("/models", json={"name": "n", "flight_id": ids[0], "epochs": 2, "noise": "identified"})
        assert accepted.status_code == 202, accepted.text
        assert wait_for_job(client, accepted.json()["job_id"])["state"] == "succeeded"
        version = client.get("/models/n/versions/1").json()
        for who in ("model", "prior"):
            assert version["noise"][who]["source"] == "identified"
            assert version["noise"][who]["detail"]["factors"].keys() == {"Q:v", "Q:a"}
        reports = {}
        for noise in ("identified", "paper"):
            started = client.post("/evaluations", json={"model": "n:1", "flights": [ids[1]], "methods": ["ukf"],
                                                        "gap_s": 0, "noise": noise})
            assert started.status_code == 202, started.text
            assert wait_for_job(client, started.json()["job_id"])["state"] == "succeeded"
            reports[noise] = client.get(f"/evaluations/{started.json()['evaluation_id']}").json()
        assert reports["identified"]["noise"] == {"ukf": "identified"}
        assert reports["paper"]["noise"] == {"ukf": "paper"}
        assert reports["identified"]["median"]["ukf"] != reports["paper"]["median"]["ukf"]
