"""A model trained on several flights, on every surface: `learnest train FILE... --validate`, POST /models with
flight_ids, the flight list's train form; the registry's lineage lists every training and validation flight
with its sha256 (also for versions stored before it kept the list), and a model that learned nothing says so in
words on the CLI, the JSON, `models show` and the version page."""
import contextlib
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
from utils.service import flight_csv, running_app, upload, wait_for_job

SAMPLES = Path(__file__).resolve().parents[2] / "sample_logs"
CIRCLES = [SAMPLES / f"circle_rep{i}.csv" for i in (1, 2, 3)]


def use_home(monkeypatch, home: Path) -> None:
    monkeypatch.setenv("LEARNEST_HOME", str(home))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)


def run(*argv) -> tuple[int, str]:
    from learnest.service.cli import main

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = main(list(argv))
    return code, buffer.getvalue()


def stored_sha256(home: Path) -> dict[str, str]:
    """{flight name: sha256 of its raw files} as the registry stored them."""
    from sqlalchemy import select

    from learnest.service.config import Settings
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import FlightRecord

    database = Database(Settings(home=home).url)
    with database.transaction() as session:
        rows = dict(session.execute(select(FlightRecord.name, FlightRecord.sha256)).all())
    database.dispose()
    return rows


def test_train_on_several_files_records_every_flight_and_its_sha256(tmp_path, monkeypatch):
    home = tmp_path / "home"
    use_home(monkeypatch, home)
    code, out = run("train", *map(str, CIRCLES), "--name", "pooled", "--epochs", "3", "--json")
    assert code == 0
    trained = json.loads(out)
    # one in five of three flights: the last one held out whole
    assert trained["training_flights"] == ["circle_rep1", "circle_rep2"]
    assert trained["validation_flights"] == ["circle_rep3"]
    assert isinstance(trained["learned"], bool) and trained["training_flight"] == "circle_rep1"
    assert trained["epochs"] == 3 and trained["ref"] == "pooled:1"

    sha = stored_sha256(home)
    assert len(sha) == 3
    code, out = run("models", "show", "pooled:1", "--json")
    shown = json.loads(out)
    assert [(f["name"], f["sha256"]) for f in shown["training_flights"]] == \
        [(n, sha[n]) for n in ("circle_rep1", "circle_rep2")]
    assert [(f["name"], f["sha256"]) for f in shown["lineage"]["validation_flights"]] == \
        [("circle_rep3", sha["circle_rep3"])]
    assert all(f["exists"] for f in shown["lineage"]["training_flights"])
    assert shown["training_flight"]["name"] == "circle_rep1"   # the single field, for older readers
    code, text = run("models", "show", "pooled:1")
    assert "trained on 2 flights" in text and sha["circle_rep2"][:12] in text
    assert "validated on 1 held-out flight(s)" in text and "circle_rep3" in text

    # --validate picks the held-out flight (already stored: found by content)
    code, out = run("train", *map(str, CIRCLES), "--name", "pooled", "--epochs", "2", "--validate",
                    str(CIRCLES[0]), "--json")
    chosen = json.loads(out)
    assert chosen["validation_flights"] == ["circle_rep1"]
    assert chosen["training_flights"] == ["circle_rep2", "circle_rep3"]
    assert chosen["flight_stored"] == "existing"

    # one file: the paper's protocol, as before
    code, out = run("train", str(CIRCLES[0]), "--name", "single", "--epochs", "2", "--json")
    single = json.loads(out)
    assert single["training_flights"] == ["circle_rep1"] and single["validation_flights"] == []

    # the same lineage through the API
    with running_app(home) as client:
        version = client.get("/models/pooled/versions/1").json()
        assert [f["sha256"] for f in version["training_flights"]] == [sha["circle_rep1"], sha["circle_rep2"]]
        assert [f["name"] for f in version["validation_flights"]] == ["circle_rep3"]
        assert version["learned"] is trained["learned"]
        page = client.get("/ui/models/pooled/versions/1").text
        assert "id='training-flights'" in page and "circle_rep2" in page and "id='validation-flights'" in page


def test_post_models_with_flight_ids_trains_one_model_and_the_web_form_takes_checked_flights(tmp_path, data_dir):
    home = tmp_path / "home"
    with running_app(home) as client:
        flights = [upload(client, flight_csv(data_dir, seed)).json() for seed in range(3)]
        ids = [f["id"] for f in flights]
        accepted = client.post("/models", json={"name": "many", "flight_ids": ids, "validation_ids": [ids[0]],
                                                "epochs": 2})
        assert accepted.status_code == 202, accepted.text
        job = wait_for_job(client, accepted.json()["job_id"])
        assert job["state"] == "succeeded", job
        assert job["result"]["training_flights"] == [flights[1]["name"], flights[2]["name"]]
        assert job["result"]["validation_flights"] == [flights[0]["name"]]
        version = client.get("/models/many/versions/1").json()
        assert [f["id"] for f in version["training_flights"]] == ids[1:]
        assert [f["sha256"] for f in version["validation_flights"]] == [flights[0]["sha256"]]
        assert version["training_flight"]["id"] == ids[1]
        assert version["metrics"]["validation"] == "held-out flights"
        lineage = client.get("/models/many/versions/1/lineage").json()
        assert [f["href"] for f in lineage["training_flights"]] == [f"/flights/{i}" for i in ids[1:]]
        # one way to name the flights, not two; a flight twice; every flight held out
        both = client.post("/models", json={"name": "x", "flight_id": ids[0], "flight_ids": ids})
        assert both.status_code == 422 and "flight_id" in both.text
        assert client.post("/models", json={"name": "x", "flight_ids": [ids[0], ids[0]]}).status_code == 422
        held = client.post("/models", json={"name": "x", "flight_ids": ids[:2], "validation_ids": ids[:2]})
        assert held.status_code == 422 and "every flight is held out" in held.text

        # the flight list: a checkbox per flight and a train form with the prior and the epochs
        home_page = client.get("/").text
        assert "id='train-form'" in home_page and "name='flight_ids'" in home_page and "name='system'" in home_page
        posted = client.post("/ui/models", data={"name": "checked", "flight_ids": [str(i) for i in ids],
                                                 "epochs": "2", "system": "quadrotor"}, follow_redirects=False)
        assert posted.status_code == 303, posted.text
        job_id = int(posted.headers["location"].rsplit("/", 1)[1])
        assert wait_for_job(client, job_id)["state"] == "succeeded"
        version = client.get("/models/checked/versions/1").json()
        assert len(version["training_flights"]) == 2 and len(version["validation_flights"]) == 1
        assert "on 3 flights" in client.get("/ui/jobs").text
        nothing = client.post("/ui/models", data={"name": "none", "epochs": "2"})
        assert nothing.status_code == 422 and "choose the flight(s) to train on" in nothing.text

        # flights uploaded as two vehicles: refused at once, naming them
        red = upload(client, flight_csv(data_dir, 3), vehicle="cf_red").json()
        blue = upload(client, flight_csv(data_dir, 4), vehicle="cf_blue").json()
        refused = client.post("/models", json={"name": "two", "flight_ids": [red["id"], blue["id"]]})
        assert refused.status_code == 422
        assert f"cf_red: {red['name']}; cf_blue: {blue['name']}" in refused.text


def test_of_several_files_those_failing_the_quality_checks_are_left_out_and_said(tmp_path, monkeypatch, data_dir):
    use_home(monkeypatch, tmp_path / "home")
    short = flight_csv(data_dir, 5, name="short.csv", seconds=6.0)   # too little flying left after the cuts
    code, out = run("train", str(CIRCLES[0]), str(CIRCLES[1]), str(short), "--name", "some", "--epochs", "2", "--json")
    assert code == 0
    trained = json.loads(out)
    assert trained["training_flights"] == ["circle_rep1"] and trained["validation_flights"] == ["circle_rep2"]
    assert len(trained["skipped_flights"]) == 1 and trained["skipped_flights"][0].startswith("short (")
    code, _ = run("train", str(short), "--name", "some", "--epochs", "2")
    assert code != 0


def _not_learned_model():
    """A real KNODE that learned nothing: records that are the kinematic prior's own steps (the prior predicts
    the held-out one exactly) leave no epoch better than the prior."""
    from learnest.models.knode import HybridModel
    from learnest.models.presets import CRAZYFLIE_TRAINING
    from learnest.models.systems import make_system
    from learnest.models.pooled_training import TrainingRecord, train_knode_pooled
    from learnest.service.jobs.tasks import training_metrics

    system = make_system("quadrotor", dt=0.01)
    prior = HybridModel(system, "prior")
    records = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        x = np.zeros((400, 9))
        x[0, 3:] = rng.normal(size=6)
        for k in range(len(x) - 1):
            x[k + 1] = prior.step(x[k], None, 0.01)
        records.append(TrainingRecord(f"r{seed}", x, np.zeros((400, 0)), 0.01))
    result = train_knode_pooled(system, records, [False, False, True], replace(CRAZYFLIE_TRAINING, epochs=20))
    return result.model, training_metrics(result.model)


def test_a_version_that_learned_nothing_says_so_on_every_surface(tmp_path, monkeypatch, data_dir):
    from learnest.models.training import NOT_LEARNED
    from learnest.service.cli import format_trained
    from learnest.service.config import Settings
    from learnest.service.jobs.training import training_config
    from learnest.service.storage.blobs import BlobStore
    from learnest.service.storage.database import Database
    from learnest.service.storage.registry import register_model
    from learnest.service.storage.tables import FlightRecord

    model, metrics = _not_learned_model()
    assert model.meta["learned"] is False and metrics["learned"] is False
    assert metrics["learned_note"] == NOT_LEARNED
    home = tmp_path / "home"
    use_home(monkeypatch, home)
    with running_app(home) as client:
        upload(client, flight_csv(data_dir, 0))
    database = Database(Settings(home=home).url)
    with database.transaction() as session:
        flight = session.get(FlightRecord, 1)
    register_model(database, BlobStore(home / "blobs"), "flat", model, flight=flight,
                   hyperparameters=training_config({"epochs": 20}), metrics=metrics)
    database.dispose()
    with running_app(home) as client:
        version = client.get("/models/flat/versions/1").json()
        assert version["learned"] is False and version["learned_note"] == NOT_LEARNED
        assert NOT_LEARNED in client.get("/ui/models/flat/versions/1").text
        assert "not learned: equals its prior" in client.get("/ui/models/flat").text
    code, text = run("models", "show", "flat:1")
    assert code == 0 and f"NOT LEARNED: {NOT_LEARNED}" in text
    out = {"ref": "flat:1", "system": "quadrotor", "training_flights": ["a", "b"], "validation_flights": ["c"],
           "training_flight": "a", "flight_id": 1, "epochs": 20, "seconds": 1.0, "best_epoch": -1,
           "command_seconds": 2.0, "home": str(home), "learned": False, "learned_note": NOT_LEARNED}
    assert format_trained(out).endswith(f"NOT LEARNED: {NOT_LEARNED}")
    learned = format_trained({**out, "learned": True, "prior_validation_loss": 2e-3, "best_validation_loss": 1.5e-3})
    assert "NOT LEARNED" not in learned and learned.endswith("the held-out one-step loss is 25.0 % below the prior's")
    assert "trained on 2 flights (a, b), validated on 1 held-out flight(s) (c)" in learned


def test_migrating_to_0007_lists_each_versions_one_training_flight(tmp_path):
    from alembic import command
    from alembic.config import Config
    from sqlalchemy import text

    from learnest.service.storage.database import MIGRATIONS, Database

    database = Database(f"sqlite:///{tmp_path / 'old.db'}")
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    with database.engine.begin() as connection:
        config.attributes["connection"] = connection
        command.upgrade(config, "0006_registry")
        connection.execute(text("INSERT INTO registered_models (name, created_at) VALUES ('quad', '2026-01-01')"))
        connection.execute(text(
            "INSERT INTO model_versions (name, version, status, training_flight_id, training_flight_sha256, "
            "training_flight_name, hyperparameters, created_at) "
            "VALUES ('quad', 1, 'ready', 7, 'abc', 'circle', '{}', '2026-01-01')"))
    database.migrate()
    with database.engine.begin() as connection:
        flights, held = connection.execute(text("SELECT training_flights, validation_flights FROM model_versions"
                                                )).one()
    assert json.loads(flights) == [{"id": 7, "name": "circle", "sha256": "abc"}] and json.loads(held) == []
    database.dispose()
