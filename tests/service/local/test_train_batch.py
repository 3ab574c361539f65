"""`learnest train` on several files of which some cannot be read: each such file is named with its reason,
the model is trained on the others (exit status 1, ``errors`` in the JSON), and ``--strict`` stops at the
first one, training nothing — as `ingest`, `evaluate` and `diagnose` treat a batch.  Simulated logs
(tests/utils/service.py) with known content: a NanoBench CSV without its accelerometer columns (refused when
its format is sniffed) and a Crazyflie uSD log cut to its first kilobyte (recognised, refused when read)."""
from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pandas as pd
import pytest
from utils.service import flight_csv, simulated_circle

from learnest.ingest.sim.export import write_flight


def use_home(monkeypatch, home: Path) -> None:
    monkeypatch.setenv("LEARNEST_HOME", str(home))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)


def run(*argv) -> tuple[int, str, str]:
    from learnest.service.cli import main

    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(map(str, argv)))
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def logs(tmp_path_factory) -> dict[str, Path]:
    """Two good simulated flights, a NanoBench CSV without imu_acc_x/y/z, and a uSD log cut to its first
    1000 bytes (its header and a few records: no mocap overlaps the accelerometer)."""
    folder = tmp_path_factory.mktemp("logs")
    good = [flight_csv(folder, seed) for seed in (0, 1)]
    no_acc = folder / "log20.csv"
    table = pd.read_csv(flight_csv(folder / "src", 2))
    table.drop(columns=["imu_acc_x", "imu_acc_y", "imu_acc_z"]).to_csv(no_acc, index=False)
    usd, = write_flight(simulated_circle(3), "usd", folder / "usd", "log07")
    truncated = folder / "log07"
    truncated.write_bytes(usd.read_bytes()[:1000])
    return {"good0": good[0], "good1": good[1], "no_acc": no_acc, "truncated": truncated}


def registered_models() -> int:
    code, out, _ = run("models", "list", "--json")
    return json.loads(out)["total"] if code == 0 else 0


def test_unreadable_files_are_named_and_the_model_is_trained_on_the_others(logs, tmp_path, monkeypatch):
    use_home(monkeypatch, tmp_path / "home")
    code, out, err = run("train", logs["good0"], logs["no_acc"], logs["good1"], logs["truncated"],
                         "--name", "batch", "--epochs", "2", "--json")
    assert code == 1, err
    trained = json.loads(out)
    assert trained["ref"] == "batch:1"
    assert sorted(trained["training_flights"] + trained["validation_flights"]) == ["flight0", "flight1"]
    errors = {Path(e["file"]).name: e["message"] for e in trained["errors"]}
    assert set(errors) == {"log20.csv", "log07"}
    assert "imu_acc_x" in errors["log20.csv"]
    assert "do not overlap in time" in errors["log07"]
    for name in ("log20.csv", "log07"):   # each named on stderr with its reason, before the summary line
        line = next(line for line in err.splitlines() if f"{name}: not read: " in line)
        assert line.endswith(errors[name])
    assert "2 file(s) could not be read" in err
    assert registered_models() == 1


def test_a_held_out_file_that_cannot_be_read_is_named_too(logs, tmp_path, monkeypatch):
    use_home(monkeypatch, tmp_path / "home")
    code, out, err = run("train", logs["good0"], "--validate", logs["good1"], logs["no_acc"],
                         "--name", "held", "--epochs", "2", "--json")
    assert code == 1, err
    trained = json.loads(out)
    assert trained["training_flights"] == ["flight0"] and trained["validation_flights"] == ["flight1"]
    assert [Path(e["file"]).name for e in trained["errors"]] == ["log20.csv"]


@pytest.mark.parametrize("bad", ["no_acc", "truncated"])
def test_strict_stops_at_the_first_unreadable_file_and_trains_nothing(logs, tmp_path, monkeypatch, bad):
    use_home(monkeypatch, tmp_path / "home")
    code, out, err = run("train", logs["good0"], logs[bad], logs["good1"], "--name", "strict", "--epochs", "2",
                         "--strict", "--json")
    assert code == 1 and out == ""
    assert f"{logs[bad]}: not read: " in err and "nothing was trained (--strict)" in err
    assert "Traceback" not in err
    assert registered_models() == 0


def test_no_readable_file_at_all_is_an_error_naming_each(logs, tmp_path, monkeypatch):
    use_home(monkeypatch, tmp_path / "home")
    code, out, err = run("train", logs["no_acc"], logs["truncated"], "--name", "none", "--epochs", "2")
    assert code == 2 and out == ""
    assert "no flight could be read" in err or "no flight log" in err
    assert "log20.csv" in err and "log07" in err and "imu_acc_x" in err
    assert registered_models() == 0


def test_the_library_call_lists_the_errors_and_strict_raises(logs, tmp_path, monkeypatch):
    from learnest.service.local import UnreadableFile, train

    use_home(monkeypatch, tmp_path / "home")
    with pytest.raises(UnreadableFile, match="imu_acc_x"):
        train([logs["no_acc"], logs["good0"]], "lib", epochs=1, strict=True)
    out = train([logs["no_acc"], logs["good0"]], "lib", epochs=1)
    assert out["training_flights"] == ["flight0"] and out["ref"] == "lib:1"
    assert [e["file"] for e in out["errors"]] == [str(logs["no_acc"])]
