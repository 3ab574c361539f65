"""Every option and argument of every `learnest` subcommand says what it is for (`learnest X --help`)."""
from __future__ import annotations

import argparse
import re

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


# -- help a user can act on: the version, what each command does, every default and choice -------------------
def test_version_is_the_installed_packages(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as stop:
        build_parser().parse_args(["--version"])
    assert stop.value.code == 0
    assert capsys.readouterr().out == f"learnest {version('learnest')}\n"


def test_every_subcommand_page_opens_with_a_description():
    pages = [(path, parser) for path, parser in subcommands(build_parser()) if path]
    assert len(pages) >= 16      # the commands and the nested ones (flights list, models show, alias set)
    for path, parser in pages:
        text = " ".join(parser.format_help().split())
        assert parser.description and " ".join(parser.description.split()) in text, path
        assert parser.description[0].isupper() and parser.description.endswith("."), path


def _stated(default) -> str:
    return f"{default:g}" if isinstance(default, float) else str(default)


def test_every_option_with_a_default_states_it_in_its_help():
    """What `learnest X --help` prints for each option (argparse's expansion of its help) names the option's
    default, wherever it has one: an option left out is then never a guess."""
    checked, missing = 0, []
    for command, action in every_argument():
        default = action.default
        if default is None or default is False or default == argparse.SUPPRESS or action.nargs == 0:
            continue         # no default, or a flag (whose default is "not given")
        parser = dict(subcommands(build_parser()))[tuple(command.split()[1:])]
        shown = parser._get_formatter()._expand_help(action).replace("\n", " ")
        checked += 1
        if _stated(default) not in shown:
            missing.append(f"{command} {action.option_strings or action.dest}: {shown!r} lacks {_stated(default)!r}")
    assert checked > 30 and missing == []


@pytest.mark.parametrize("command, option, shown", [
    ("serve", "--workers", "(default: 1)"), ("reproduce", "--workers", "(default: 1)"),
    ("evaluate", "--horizon", "(default: 20)"), ("demo", "--name", "(default: demo)"),
    ("diagnose", "--methods", "comma-separated"), ("diagnose", "--methods", "(default: ukf,knode-ukf)"),
    ("diagnose", "--methods", "any of ukf, mhe, knode-ukf, knode-mhe"),
])
def test_the_defaults_and_choices_a_newcomer_looked_for(command, option, shown, capsys):
    assert main([command, "--help"]) == 0
    page = capsys.readouterr().out
    block = page[page.index(f"  {option}"):]
    block = " ".join(block[:block.index("\n  -", 1) if "\n  -" in block[1:] else None].split())
    assert shown in block


def test_methods_say_comma_separated_and_no_help_points_into_the_source():
    for command, action in every_argument():
        if action.dest == "methods":
            assert "comma-separated" in action.help, command
        assert not re.search(r"\w+\.py\b|PAPER_OBSERVER", action.help or ""), (command, action.help)
    [observer] = [a for c, a in every_argument() if c == "learnest reproduce" and a.dest == "observer"]
    assert "cartpole joint, robot smoother" in observer.help      # the tasks' defaults in words


def test_choices_are_listed_where_the_usage_hides_them():
    """An option with choices shows them as {a,b} unless it has a metavar: then its help names each."""
    for command, action in every_argument():
        if action.choices and action.metavar and not isinstance(action.choices, range):
            assert all(str(choice) in action.help for choice in action.choices), (command, action.dest)
