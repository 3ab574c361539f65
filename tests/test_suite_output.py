"""What a newcomer sees of the suite: how long it takes, said first and in the README, then its progress; and no
deprecation warning that a dependency's own advice fixes."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PYTEST = Path(sys.executable).parent / "pytest"    # the venv's: `python -m pytest` would import the checkout


def test_the_suite_says_how_long_it_takes_before_collecting_then_how_many_tests_run():
    run = subprocess.run([str(PYTEST), "-q", "-p", "no:cacheprovider",
                          "tests/test_public_api.py::test_the_distribution_installs_one_top_level_name"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout[-2000:]
    first, second = run.stdout.splitlines()[:2]
    assert first == ("learnest's whole test suite takes about 18 min on 2 idle cores, up to 25 under load; "
                     "collecting the tests ...")
    assert second.startswith("collected 1 tests in ") and second.endswith(" s; running them")


def test_the_readme_gives_the_test_commands_duration_beside_it():
    readme = (REPO / "README.md").read_text(encoding="utf-8")
    command = readme.index(".venv/bin/pytest -q\n```")
    after = readme[command:command + 600]
    assert "about 18 min on 2 idle cores" in after and "up to 25" in after


def test_the_test_client_warns_of_nothing():
    """Starlette's TestClient wants httpx2 (its StarletteDeprecationWarning says so): the test extra installs it."""
    run = subprocess.run([sys.executable, "-c", "import warnings; warnings.simplefilter('error'); "
                                                "import starlette.testclient"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr[-1500:]
