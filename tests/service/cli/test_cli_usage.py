"""A usage error is printed before anything heavy loads, and the demo's first and last lines are the ones a
newcomer acts on (cli.usage, the demo in cli.commands.science)."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from learnest.service.cli import main

REPO = Path(__file__).resolve().parents[3]
HEAVY = ("torch", "scipy", "casadi", "sqlalchemy", "fastapi", "matplotlib", "pandas")

# Runs `learnest ARGS` in a fresh interpreter and prints, after its exit status, which heavy modules it imported;
# an import hook prints a marker on stdout when torch starts loading (the demo's first line must come before it)
RUN = f"""
import sys
class Marker:
    def find_spec(self, name, path=None, target=None):
        if name == "torch":
            print("<torch starts loading>", flush=True)
            sys.meta_path.remove(self)
        return None
sys.meta_path.insert(0, Marker())
from learnest.service.cli import main
status = main(sys.argv[1:])
print("status", status, "heavy", sorted(m for m in {HEAVY} if m in sys.modules), flush=True)
sys.exit(status)
"""


def learnest(*args: str, home: Path, cwd: Path = REPO) -> subprocess.CompletedProcess:
    env = {**os.environ, "LEARNEST_HOME": str(home)}
    return subprocess.run([sys.executable, "-c", RUN, *args], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=600)


@pytest.mark.parametrize("args, error", [
    (["evaluate"], "evaluate needs --model REF and FILE..., or --new"),
    (["evaluate", "--model", "m:1", "sample_logs/circle_rep1.csv", "--methods", "ukf,kalman"], "kalman"),
    (["evaluate", "--model", "m:1", "sample_logs/circle_rep1.csv", "--gap-s", "3"], "must be longer than the gap"),
    (["diagnose", "--methods", "onboard", "sample_logs/circle_rep1.csv"], "onboard"),
    (["diagnose", "--simulate", "mass=1", "sample_logs/circle_rep1.csv"], "not both"),
    (["thrust-map", "--fit", "sample_logs/circle_rep1.csv"], "needs --fit and --score"),
    (["demo", "sample_logs", "--methods", "ukf,nope"], "nope"),
    (["train", "--name", "m", "--rate", "50", "sample_logs/circle_rep1.csv"], "100 Hz grid"),
])
def test_a_usage_error_is_printed_before_the_estimators_load(args, error, tmp_path):
    run = learnest(*args, home=tmp_path / "home")
    assert run.returncode == 2, run.stderr
    assert error in run.stderr and "Traceback" not in run.stderr
    assert "<torch starts loading>" not in run.stdout
    assert "heavy []" in run.stdout          # nor SciPy, CasADi, the database or the web stack
    assert not (tmp_path / "home").exists()  # and nothing stored


@pytest.mark.slow
def test_the_demo_speaks_first_says_what_it_registered_and_ends_with_a_command_that_works(tmp_path, monkeypatch,
                                                                                         capsys):
    from utils.service import flight_csv, settings_for

    folder = tmp_path / "logs"
    folder.mkdir()
    for seed in (0, 1):
        flight_csv(folder, seed)
    home, elsewhere = tmp_path / "home", tmp_path / "elsewhere"
    elsewhere.mkdir()
    first = learnest("demo", str(folder), "--methods", "ukf,knode-ukf", home=home, cwd=elsewhere)
    assert first.returncode == 0, first.stderr[-2000:]
    lines = first.stdout.splitlines()
    # its first line before torch begins to load: the seconds of imports are announced, not silent
    assert lines[0].startswith(f"demo: reading the flight logs in {folder}")
    assert lines.index("<torch starts loading>") > 0
    assert f"registered demo:1 in {home}" in first.stdout and "another version" not in first.stdout
    # the last line: the server command for the home the demo used, and the model's page under it
    last = [line for line in lines if not line.startswith("status ")][-1]
    assert re.fullmatch(rf"next: LEARNEST_HOME={re.escape(str(home))} learnest serve, then open "
                        r"http://127\.0\.0\.1:8000/ui/models/demo .*", last), last

    from fastapi.testclient import TestClient

    from learnest.service.app.factory import create_app

    with TestClient(create_app(settings_for(home), scheduler=False)) as client:   # what that server shows
        page = client.get("/ui/models/demo")
    assert page.status_code == 200 and "demo" in page.text

    # run again (here, in-process): another version, and it says so
    monkeypatch.setenv("LEARNEST_HOME", str(home))
    capsys.readouterr()
    assert main(["demo", str(folder), "--methods", "ukf,knode-ukf"]) == 0
    again = capsys.readouterr().out
    assert f"registered demo:2 in {home}: another version of demo (1 from earlier runs kept" in again
