"""`learnest train / evaluate / diagnose` on the model registry (service.local): the CLI registers versions
under LEARNEST_HOME like the API does, and takes NAME, NAME:VERSION and NAME@ALIAS; a reference that names
nothing is exit code 2 with a one-line reason."""
import contextlib
import io
import json
from pathlib import Path

import pytest
from utils.service import running_app

SAMPLES = Path(__file__).resolve().parents[3] / "sample_logs"
TRAIN, OTHER = SAMPLES / "circle_rep1.csv", SAMPLES / "circle_rep2.csv"


def use_home(monkeypatch, home: Path) -> None:
    monkeypatch.setenv("LEARNEST_HOME", str(home))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)


def evaluation_count(home: Path) -> int:
    from sqlalchemy import func, select

    from learnest.service.config import Settings
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import Evaluation

    database = Database(Settings(home=home).url)
    with database.transaction() as session:
        count = session.scalar(select(func.count(Evaluation.id)))
    database.dispose()
    return int(count or 0)


def run_json(capsys, *argv) -> dict:
    from learnest.service.cli import main

    capsys.readouterr()
    assert main([*argv, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """circle:1 and circle:2, both trained (2 epochs) on circle_rep1 by `learnest train`."""
    from learnest.service.cli import main

    home = tmp_path_factory.mktemp("cli-registry") / "home"
    outputs = []
    with pytest.MonkeyPatch.context() as monkeypatch:
        use_home(monkeypatch, home)
        for _ in range(2):
            buffer = io.StringIO()  # capsys is function-scoped: catch stdout here
            with contextlib.redirect_stdout(buffer):
                assert main(["train", str(TRAIN), "--name", "circle", "--epochs", "2", "--json"]) == 0
            outputs.append(json.loads(buffer.getvalue()))
    return {"home": home, "outputs": outputs}


def test_train_twice_registers_versions_1_and_2_on_one_stored_flight(trained):
    from sqlalchemy import func, select

    from learnest.service.config import Settings
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import FlightFile, FlightRecord

    first, second = trained["outputs"]
    assert (first["version"], first["ref"], second["version"], second["ref"]) == (1, "circle:1", 2, "circle:2")
    assert first["training_flight"] == second["training_flight"] == "circle_rep1"
    assert (first["flight_stored"], second["flight_stored"]) == ("new", "existing")   # deduplicated by sha256
    assert first["epochs"] == 2 and first["final_loss"] is not None
    database = Database(Settings(home=trained["home"]).url)
    with database.transaction() as session:
        assert session.scalar(select(func.count(FlightRecord.id))) == 1
        assert session.scalar(select(FlightFile.original_name)) == "circle_rep1.csv"
    database.dispose()
    # the same registry through the HTTP API
    with running_app(trained["home"]) as client:
        versions = client.get("/models/circle").json()["versions"]
        assert [(v["version"], v["status"]) for v in versions] == [(1, "ready"), (2, "ready")]
        assert versions[0]["training_flight"]["name"] == "circle_rep1"


def test_evaluate_by_version_alias_and_bare_name(trained, monkeypatch, capsys):
    from learnest.service.config import Settings
    from learnest.service.storage import registry
    from learnest.service.storage.database import Database

    use_home(monkeypatch, trained["home"])
    database = Database(Settings(home=trained["home"]).url)
    with database.transaction() as session:  # PUT alias, through the Python registry API
        registry.set_alias(session, "circle", "production", 1)
    database.dispose()
    common = [str(TRAIN), str(OTHER), "--methods", "ukf,knode-ukf"]
    by_version = run_json(capsys, "evaluate", "--model", "circle:1", *common)
    by_alias = run_json(capsys, "evaluate", "--model", "circle@production", *common)
    latest = run_json(capsys, "evaluate", "--model", "circle", *common)
    assert (by_version["model"], by_alias["model"], latest["model"]) == ("circle:1", "circle:1", "circle:2")
    assert by_alias["flights"][1]["mse"] == by_version["flights"][1]["mse"]
    for report in (by_version, by_alias, latest):
        training, other = report["flights"]
        assert training["excluded"] and training["reason"].startswith("training flight")
        assert not other["excluded"] and set(other["mse"]) == {"ukf", "knode-ukf"}


def test_evaluate_stores_its_evaluation_and_export_writes_its_estimates(trained, monkeypatch, capsys, tmp_path):
    """`learnest evaluate` puts flights and evaluation in the registry (the web UI shows it) unless --no-store;
    --export and `learnest export ID` write the estimates; errors come before any work."""
    import pandas as pd
    import pyarrow.parquet as pq
    from mcap.reader import make_reader

    from learnest.service.cli import main

    use_home(monkeypatch, trained["home"])
    common = [str(TRAIN), str(OTHER), "--methods", "ukf,knode-ukf"]
    written = tmp_path / "estimates.csv"
    report = run_json(capsys, "evaluate", "--model", "circle:1", *common, "--export", str(written))
    evaluation_id, scored = report["evaluation_id"], report["flights"][1]
    assert [f["flight"] for f in report["flights"]] == ["circle_rep1", "circle_rep2"]
    assert scored["flight_id"] > 0 and len(scored["sha256"]) == 64 and report["units"]["groups"]["a"] == "m^2/s^4"
    with running_app(trained["home"]) as client:  # the same evaluation through the API and the web page
        stored = client.get(f"/evaluations/{evaluation_id}").json()
        assert stored["flights"] == report["flights"] and stored["model"] == "circle:1"
        assert client.get(f"/evaluations/{evaluation_id}/report.html").status_code == 200
    frame = pd.read_csv(written)
    assert set(frame["flight_id"]) == {scored["flight_id"]} and set(frame["method"]) == {"ukf", "knode-ukf"}

    mcap, parquet = tmp_path / "e.mcap", tmp_path / "e.parquet"
    assert main(["export", str(evaluation_id), "-o", str(mcap)]) == 0
    assert "1 flight(s) (circle_rep2)" in capsys.readouterr().out
    topics = {c.topic for c in make_reader(mcap.open("rb")).get_summary().channels.values()}
    assert {"/learnest/ukf/position", "/learnest/knode-ukf/velocity", "/learnest/reference/pose"} <= topics
    assert main(["export", str(evaluation_id), "-o", str(parquet), "--flight", str(scored["flight_id"])]) == 0
    assert pq.read_table(parquet).num_rows == len(frame)

    # --no-store computes the same numbers here and stores nothing; its --export writes the same table
    here = tmp_path / "here.parquet"
    unstored = run_json(capsys, "evaluate", "--model", "circle:1", *common, "--no-store", "--export", str(here))
    assert "evaluation_id" not in unstored and unstored["flights"][1]["mse"] == pytest.approx(scored["mse"], rel=1e-9)
    local = pq.read_table(here).to_pandas()
    assert local[["t_s", "p_x_m", "err_v_y_m_s"]].to_numpy() == pytest.approx(frame[["t_s", "p_x_m", "err_v_y_m_s"]]
                                                                               .to_numpy(), rel=1e-9, abs=1e-12)
    assert evaluation_count(trained["home"]) == evaluation_id   # nothing stored since (ids are never reused)

    capsys.readouterr()
    assert main(["export", "999999", "-o", str(tmp_path / "x.csv")]) == 2
    assert "evaluation 999999 not found" in capsys.readouterr().err
    assert main(["export", str(evaluation_id), "-o", str(tmp_path / "x.xlsx")]) == 2
    assert "cannot tell the export format" in capsys.readouterr().err
    assert main(["evaluate", "--model", "circle:1", str(OTHER), "--export", str(tmp_path / "x.txt")]) == 2
    assert "cannot tell the export format" in capsys.readouterr().err
    assert main(["evaluate", "--model", "circle:1", str(OTHER), "--rate", "50"]) == 2
    assert "--no-store" in capsys.readouterr().err


@pytest.mark.parametrize("ref, message", [
    ("nope", "no registered model named 'nope'"),
    ("circle:9", "model 'circle' has no version 9"),
    ("circle@staging", "model 'circle' has no alias 'staging'"),
    ("../circle", "must be 'name:version', 'name@alias' or 'name'"),
])
def test_unknown_reference_is_exit_code_2_with_the_reason(trained, monkeypatch, capsys, ref, message):
    from learnest.service.cli import main

    use_home(monkeypatch, trained["home"])
    capsys.readouterr()
    assert main(["evaluate", "--model", ref, str(OTHER)]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    if ":" not in ref and "@" not in ref and "/" not in ref:
        assert "registered models: circle" in err
    assert main(["diagnose", "--model", ref, str(OTHER)]) == 2
    assert message in capsys.readouterr().err


def test_no_registry_yet_is_a_clear_error_and_creates_nothing(tmp_path, monkeypatch, capsys):
    from learnest.service.cli import main

    home = tmp_path / "empty"
    use_home(monkeypatch, home)
    assert main(["evaluate", "--model", "circle", str(OTHER)]) == 2
    assert "nothing is registered under" in capsys.readouterr().err
    assert not home.exists()


def test_training_on_an_unreadable_file_registers_nothing(tmp_path, monkeypatch, capsys):
    from learnest.service.cli import main

    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"\x00\xff" * 100)
    use_home(monkeypatch, tmp_path / "home")
    assert main(["train", str(junk), "--name", "x", "--epochs", "1"]) == 2
    assert "junk.bin" in capsys.readouterr().err
    assert main(["train", str(TRAIN), "--name", "x", "--rate", "50"]) == 2
    assert "100 Hz" in capsys.readouterr().err
    with running_app(tmp_path / "home") as client:
        assert client.get("/models").json()["total"] == 0 and client.get("/flights").json()["total"] == 0


def test_flights_list_models_list_show_and_alias_set(trained, monkeypatch, capsys):
    """The registry from the shell: what `learnest train` stored, listed and shown, and an alias moved; the
    same rows the API shows."""
    from learnest.service.cli import main

    use_home(monkeypatch, trained["home"])
    flights = run_json(capsys, "flights", "list")
    assert [f["name"] for f in flights["items"]][0] == "circle_rep1" and flights["total"] >= 1
    assert run_json(capsys, "flights", "list", "--q", "REP1")["total"] == 1
    assert run_json(capsys, "flights", "list", "--q", "no-such")["items"] == []
    models = run_json(capsys, "models", "list")
    assert [(m["name"], m["versions"], m["latest_version"]) for m in models["items"]] == [("circle", 2, 2)]
    assert run_json(capsys, "models", "list", "--q", "zzz") == {"total": 0, "items": []}

    model = run_json(capsys, "models", "show", "circle")
    assert [v["ref"] for v in model["versions"]] == ["circle:1", "circle:2"]
    assert model["versions"][0]["hyperparameters"]["epochs"] == 2
    version = run_json(capsys, "models", "show", "circle:2")
    assert version["lineage"]["training_flight"]["name"] == "circle_rep1"
    assert version["lineage"]["training_flight"]["exists"] is True
    assert version["metrics"]["final_loss"] == trained["outputs"][1]["final_loss"]

    assert run_json(capsys, "alias", "set", "circle", "2", "staging") == \
        {"name": "circle", "alias": "staging", "version": 2, "previous_version": None}
    assert run_json(capsys, "models", "show", "circle@staging")["ref"] == "circle:2"
    capsys.readouterr()
    assert main(["alias", "set", "circle", "1", "staging"]) == 0
    assert capsys.readouterr().out.strip() == "circle@staging -> version 1 (was 2)"
    assert main(["models", "show", "circle"]) == 0
    text = capsys.readouterr().out
    assert "aliases" in text and "@staging" in text and "circle_rep1" in text
    assert main(["models", "show", "circle:1"]) == 0
    assert "trained on flight" in capsys.readouterr().out
    # a version or model that does not exist: exit 2, one line
    assert main(["alias", "set", "circle", "9", "staging"]) == 2
    assert "no version 9" in capsys.readouterr().err
    assert main(["models", "show", "nothing"]) == 2
    assert "no registered model named 'nothing'" in capsys.readouterr().err


def test_registry_command_arguments_are_checked_before_any_import(tmp_path):
    """A bad name, version or reference is exit 2 from argparse, before SQLAlchemy, the registry or torch load."""
    import subprocess
    import sys

    code = ("import sys; from learnest.service.cli import main; "
            "codes = [main(a) for a in (['alias', 'set', 'bad name', '1', 'p'], ['alias', 'set', 'm', '0', 'p'], "
            "['alias', 'set', 'm', '1', '@p'], ['models', 'show', 'm:x'], ['models', 'frob'])]; "
            "print(codes, ','.join(m for m in ('sqlalchemy', 'learnest.service.storage.registry', 'torch') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=tmp_path,
                         env={"LEARNEST_HOME": str(tmp_path / "home"), "PATH": "/usr/bin:/bin"})
    assert out.stdout.strip() == "[2, 2, 2, 2, 2]", out.stdout + out.stderr
    assert "must be at least 1" in out.stderr and "model name 'bad name'" in out.stderr
    assert not (tmp_path / "home").exists()


def test_evaluate_goes_on_past_an_unreadable_file_and_takes_a_cut(trained, monkeypatch, capsys, tmp_path):
    """One file without its accelerometer among the flights: named with its reason, the others stored (each
    said: new or existing, under which id) and scored, exit status 1, ``errors`` in the JSON; --cut reaches
    the flights read, stored or not."""
    import pandas as pd

    from learnest.service.cli import main

    use_home(monkeypatch, trained["home"])
    bad = tmp_path / "log20.csv"
    pd.read_csv(OTHER).drop(columns=["imu_acc_x", "imu_acc_y", "imu_acc_z"]).to_csv(bad, index=False)
    for store in ([], ["--no-store"]):
        capsys.readouterr()
        argv = ["evaluate", "--model", "circle:1", str(bad), str(TRAIN), str(OTHER), "--methods", "ukf",
                "--cut", "3:12", "--json", *store]
        assert main(argv) == 1
        captured = capsys.readouterr()
        report = json.loads(captured.out)
        assert [e["file"] for e in report["errors"]] == [str(bad)] and "imu_acc_x" in report["errors"][0]["message"]
        assert f"{bad}: not read:" in captured.err
        assert [f["flight"].split("-")[0] for f in report["flights"]] == ["circle_rep1", "circle_rep2"]
        if not store:
            assert [s["file"] for s in report["stored"]] == [str(TRAIN), str(OTHER)]
            assert all(s["stored"] in ("new", "existing") and s["flight_id"] > 0 for s in report["stored"])
            with running_app(trained["home"]) as client:
                flight = client.get(f"/flights/{report['stored'][1]['flight_id']}").json()
                assert flight["duration_s"] == pytest.approx(9.0, abs=0.011)     # the cut asked for
                assert flight["meta"]["cut_choice"] == "3:12"


def test_a_version_trained_with_identified_noise_stores_it_shows_it_and_evaluates_with_it(tmp_path, monkeypatch,
                                                                                          capsys):
    """`learnest train --noise identified`: the version's noise (the model's and its prior's, each identified on
    the training flight) is in `models show`, and `evaluate` runs each method with it, saying so; `--noise paper`
    runs both with the system's fixed noise, and gives other prior-only scores."""
    use_home(monkeypatch, tmp_path / "home")
    run_json(capsys, "train", str(TRAIN), "--name", "tuned", "--epochs", "2", "--noise", "identified")
    noise = run_json(capsys, "models", "show", "tuned:1")["noise"]
    for who in ("model", "prior"):
        assert noise[who]["source"] == "identified" and noise[who]["detail"]["flights"] == ["circle_rep1"]
        assert set(noise[who]["process_per_step"]) == {"p", "v", "a"}
    from learnest.service.cli import main

    capsys.readouterr()
    assert main(["models", "show", "tuned:1"]) == 0
    text = capsys.readouterr().out
    assert "noise of the model: identified" in text and "noise of its prior: identified" in text
    common = ["evaluate", "--model", "tuned", str(OTHER), "--methods", "ukf,knode-ukf", "--gap-s", "0"]
    identified = run_json(capsys, *common)
    paper = run_json(capsys, *common, "--noise", "paper")
    assert identified["noise"] == {"ukf": "identified", "knode-ukf": "identified"}
    assert paper["noise"] == {"ukf": "paper", "knode-ukf": "paper"}
    assert identified["median"]["ukf"] != pytest.approx(paper["median"]["ukf"], rel=1e-3)
