"""Every option and argument of every `learnest` subcommand says what it is for (`learnest X --help`)."""
from __future__ import annotations

import argparse

import pytest

from learnest.service.cli import build_parser, main, subcommands


def every_argument():
    for path, parser in subcommands(build_parser()):
        for action in parser._actions:
            if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
                continue
            yield " ".join(("learnest", *path)), action


def test_every_option_of_every_subcommand_has_help_text():
    arguments = list(every_argument())
    assert len(arguments) > 80    # the walk reaches the nested subcommands (models show, alias set, ...)
    missing = [f"{command} {action.option_strings or action.dest}" for command, action in arguments
               if not (action.help or "").strip() or action.help == argparse.SUPPRESS]
    assert missing == []


@pytest.mark.parametrize("command", [["diagnose"], ["evaluate"], ["train"], ["demo"], ["alias", "set"],
                                     ["models", "show"], ["serve"]])
def test_help_prints_the_text_of_each_option(command, capsys):
    assert main([*command, "--help"]) == 0
    text = capsys.readouterr().out
    parser = dict(subcommands(build_parser()))[tuple(command)]
    for action in parser._actions:
        if action.help and action.help != argparse.SUPPRESS and not isinstance(action, argparse._HelpAction):
            # argparse rewraps the text: compare its first words
            assert " ".join(action.help.split()[:3]) in " ".join(text.split()), action.dest


def test_a_missing_file_is_refused_before_any_work(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    missing = tmp_path / "nope.csv"
    for argv in (["evaluate", "--model", "m:1", str(missing)], ["train", "--name", "m", str(missing)],
                 ["diagnose", str(missing)], ["demo", str(tmp_path / "no-folder")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "no such file or folder" in err and "nope.csv" in err or "no-folder" in err
        assert "%" not in err and "\r" not in err     # no progress bar started
    assert not (tmp_path / "home").exists()            # nothing stored


def test_a_prior_whose_inputs_the_flight_lacks_is_refused_and_nothing_is_registered(tmp_path, capsys, monkeypatch):
    from pathlib import Path

    monkeypatch.setenv("LEARNEST_HOME", str(tmp_path / "home"))
    log = Path(__file__).resolve().parents[3] / "sample_logs" / "circle_rep1.csv"   # no motors, no battery
    assert main(["train", "--name", "cf", "--system", "crazyflie", "--epochs", "2", str(log)]) == 2
    err = capsys.readouterr().err
    assert "circle_rep1: the 'crazyflie' prior needs motors, vbat" in err and "Traceback" not in err
    assert main(["models", "list", "--json"]) == 0
    assert '"total": 0' in capsys.readouterr().out      # no half-made model, no failed version
