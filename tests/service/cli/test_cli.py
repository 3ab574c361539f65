"""The learnest command line end to end: ingest --json, train, evaluate, and clean errors."""
import json
from pathlib import Path

import pytest

from learnest.service.cli import main

DATA = Path(__file__).resolve().parents[3].parent / "shared" / "data"
NANOBENCH = DATA / "nanobench"
needs_data = pytest.mark.data  # skipped by conftest.py when ../shared/data is absent


@needs_data
def test_ingest_json_reports_each_flight_and_flags_the_bad_one(capsys):
    files = [NANOBENCH / "B2_circle_medium_rep2.csv", NANOBENCH / "B2_circle_medium_rep3.csv",
             DATA / "crazyswarm2-tools" / "log182"]
    assert main(["ingest", *map(str, files), "--json"]) == 0
    flights = json.loads(capsys.readouterr().out)["flights"]
    assert [f["adapter"] for f in flights] == ["nanobench", "nanobench", "usd"]  # in the order given
    by_name = {Path(f["source"][0]).name: f for f in flights}
    assert by_name["B2_circle_medium_rep2.csv"]["quality"]["ok"]
    bad = by_name["B2_circle_medium_rep3.csv"]["quality"]
    assert not bad["ok"] and any("acc" in issue for issue in bad["issues"])
    for f in flights:
        assert f["rate_hz"] == pytest.approx(100.0) and f["clock_offset_s"] is None
        assert f["samples"] == pytest.approx(f["duration_s"] * 100 + 1, abs=1)


@needs_data
def test_train_then_evaluate_scores_other_flights_and_never_the_training_one(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path))
    train = NANOBENCH / "B2_circle_slow_rep1.csv"
    assert main(["train", str(train), "--name", "circle", "--epochs", "5", "--json"]) == 0
    trained = json.loads(capsys.readouterr().out)
    assert trained["training_flight"] == "B2_circle_slow_rep1"
    assert trained["version"] == 1 and trained["ref"] == "circle:1"   # registered, loadable by reference
    files = [train, NANOBENCH / "B2_circle_slow_rep2.csv", NANOBENCH / "B2_circle_medium_rep3.csv"]
    plot = tmp_path / "box.png"
    assert main(["evaluate", "--model", "circle", *map(str, files), "--methods", "ukf,knode-ukf", "--json",
                 "--plot", str(plot)]) == 0
    report = json.loads(capsys.readouterr().out)
    rows = {f["flight"]: f for f in report["flights"]}
    assert rows["B2_circle_slow_rep1"]["excluded"] and "training" in rows["B2_circle_slow_rep1"]["reason"]
    assert rows["B2_circle_medium_rep3"]["excluded"] and "quality" in rows["B2_circle_medium_rep3"]["reason"]
    scored = rows["B2_circle_slow_rep2"]
    assert not scored["excluded"] and set(scored["mse"]) == {"ukf", "knode-ukf"}
    # MSE over [p, v, a] is dominated by acceleration; on a clean flight it is small but not zero
    assert 1e-4 < scored["mse"]["ukf"] < 0.1
    assert report["median"]["ukf"] == scored["mse"]["ukf"]
    assert set(report["improvement_pct"]) == {"knode-ukf_vs_ukf"}
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_input_is_one_clear_line_without_traceback(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"\x00\xff" * 100)
    assert main(["ingest", str(junk)]) == 2
    err = capsys.readouterr().err
    assert "junk.bin" in err and "unrecognised format" in err and "Traceback" not in err
    # an unknown model and a malformed reference are each named for what they are (the flight file is
    # never reached: the reference is checked first)
    assert main(["evaluate", "--model", "nope", str(junk)]) == 2
    err = capsys.readouterr().err
    assert "no model 'nope'" in err and "junk.bin" not in err and "Traceback" not in err
    assert main(["evaluate", "--model", "../etc/passwd", str(junk)]) == 2
    err = capsys.readouterr().err
    assert "model reference '../etc/passwd' must be" in err and "junk.bin" not in err


@pytest.mark.parametrize("argv, message", [
    (["ingest", "--rate", "0"], "argument --rate: must be a positive number, got '0'"),
    (["ingest", "--rate", "-5"], "argument --rate: must be a positive number, got '-5'"),
    (["ingest", "--rate", "nan"], "argument --rate: must be a positive number, got 'nan'"),
    (["ingest", "--rate", "fast"], "argument --rate: must be a number, got 'fast'"),
    (["train", "--name", "m", "--epochs", "0"], "argument --epochs: must be at least 1, got '0'"),
    (["evaluate", "--model", "m", "--horizon", "-1"], "argument --horizon: must be at least 1, got '-1'"),
    (["evaluate", "--model", "m", "--plot", "/no/such/folder/box.png"], "folder /no/such/folder does not exist"),
    (["diagnose", "--model", "a b"], "argument --model: model reference 'a b' must be"),
])
def test_bad_arguments_are_refused_before_any_file_is_read(tmp_path, capsys, argv, message):
    """Each bad value is named with its option, and the missing flight file is never reached (its error
    would say 'no such file'), so no import or ingest ran first; no version number is spent."""
    missing = str(tmp_path / "missing.csv")
    assert main([argv[0], missing, *argv[1:]]) == 2
    err = capsys.readouterr().err
    assert message in err and "missing.csv" not in err and "Traceback" not in err


@needs_data
def test_ingest_strict_fails_when_a_flight_fails_quality(capsys):
    files = [str(NANOBENCH / "B2_circle_medium_rep2.csv"), str(NANOBENCH / "B2_circle_medium_rep3.csv")]
    assert main(["ingest", *files]) == 0             # a report: bad flights are listed, not an error
    assert "BAD" in capsys.readouterr().out
    assert main(["ingest", *files, "--strict"]) == 1
    assert "1 of 2 flight(s) failed the quality checks: B2_circle_medium_rep3" in capsys.readouterr().err
    assert main(["ingest", files[0], "--strict"]) == 0


def test_a_lone_half_of_a_vicon_cfclient_pair_is_named(tmp_path, capsys):
    """One Vicon export with two cfclient logs: the second log has no partner, and the error says so."""
    import numpy as np

    from learnest.ingest.formats.vicon_cfclient.writer import write_cfclient_csv, write_vicon_csv
    t = np.arange(200) / 100.0
    write_vicon_csv(tmp_path / "a_vicon.csv", t, np.tile([0.0, 0.0, 1.0], (200, 1)),
                    np.tile([0.0, 0.0, 0.0, 1.0], (200, 1)), 100.0)
    for name in ("a_cf.csv", "b_cf.csv"):
        write_cfclient_csv(tmp_path / name, t + 5.0, np.tile([0.0, 0.0, 1.0], (200, 1)))
    files = [str(tmp_path / n) for n in ("a_vicon.csv", "a_cf.csv", "b_cf.csv")]
    assert main(["ingest", *files]) == 2
    err = capsys.readouterr().err
    assert "b_cf.csv" in err and "needs a Vicon export" in err and "Traceback" not in err


def test_a_model_reference_is_checked_without_the_database_stack():
    """The reference's form is checked from `service.storage.references` alone: parsing the arguments loads no
    SQLAlchemy, registry or torch (the checks run before any heavy import, as the error promises)."""
    import subprocess
    import sys

    code = ("import sys; from learnest.service.cli import build_parser; "
            "build_parser().parse_args(['evaluate', '--model', 'quad@production', 'f.csv']); "
            "print(','.join(m for m in ('sqlalchemy', 'learnest.service.storage.registry', 'torch') "
            "if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd="/")
    assert out.stdout.strip() == ""


@pytest.mark.parametrize("value, message", [("-1", "must be at least 0, got '-1'"),
                                            ("x", "must be a whole number, got 'x'")])
def test_reproduce_refuses_a_bad_first_seed_before_running_anything(capsys, value, message):
    assert main(["reproduce", "--task", "cartpole", "--first-seed", value]) == 2
    err = capsys.readouterr().err
    assert f"argument --first-seed: {message}" in err and "Traceback" not in err and "Table I" not in err


def test_train_json_says_which_residual_scale_was_kept_and_why(tmp_path, monkeypatch, capsys):
    """Two simulated flights whose logs declare two trajectory families: by default each family is held out in
    turn and the scale chosen is in the JSON, the text and `models show`; with `--group-by none` the whole residual
    is kept and the reason says so."""
    from utils.service import flight_csv

    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    files = [flight_csv(tmp_path, seed) for seed in (0, 1)]
    for path, family in zip(files, ("circle", "figure8")):
        path.with_name(f"{path.stem}_metadata.yaml").write_text(f"trajectory_type: {family}\n")
    assert main(["train", *map(str, files), "--name", "fam", "--epochs", "2", "--json"]) == 0
    trained = json.loads(capsys.readouterr().out)
    assert trained["residual_scale_groups"] == ["circle", "figure8"]
    assert trained["residual_scale"] in (0.0, 0.25, 0.5, 0.75, 1.0)
    assert trained["residual_scale_note"].startswith("chosen with circle, figure8 held out in turn: ")
    assert main(["models", "show", "fam:1"]) == 0
    assert f"residual scale {trained['residual_scale']:g}: {trained['residual_scale_note']}" in capsys.readouterr().out
    assert main(["train", *map(str, files), "--name", "whole", "--epochs", "2", "--group-by", "none"]) == 0
    text = capsys.readouterr().out
    assert "residual scale 1: grouping switched off (group by none): the whole residual, no scale chosen" in text
    assert main(["train", *map(str, files), "--name", "bad", "--epochs", "2", "--group-by", "name:x"]) == 2
    assert "exactly one capture group" in capsys.readouterr().err
