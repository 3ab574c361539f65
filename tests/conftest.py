"""Shared fixtures.  Tests import the installed `learnest` package, as a user would: no sys.path edits;
helpers live in `tests/utils` (importable as `utils` because pytest puts this folder on sys.path).

The folders mirror the packages (tests/ingest, tests/models, tests/estimators, tests/workflows, tests/service,
tests/docs; the cross-cutting checks stay here).  They have no `__init__.py`: pytest then imports each test
module under its file name alone, so test file names must stay unique across folders, and no test folder can
shadow `learnest` or the repository's top-level source folders as an importable package."""
import time
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
# what the README says of the whole suite: printed first, so a run that shows only dots for minutes is expected
SUITE_DURATION = "about 18 min on 2 idle cores, up to 25 under load"
_collecting_since = [time.monotonic()]


def _say(config, line: str) -> None:
    """One line on pytest's terminal, written out at once (also with -q, and when piped to a file)."""
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line(line)
        reporter.flush()


def pytest_sessionstart(session):
    """Say up front how long the suite takes: collection alone imports the stack (20 s under load)."""
    _collecting_since[0] = time.monotonic()
    _say(session.config, f"learnest's whole test suite takes {SUITE_DURATION}; collecting the tests ...")


def pytest_collection_finish(session):
    """Say how many tests run, then pytest's own progress (a dot per passed test, % at each line's end)."""
    _say(session.config, f"collected {len(session.items)} tests in {time.monotonic() - _collecting_since[0]:.0f} s; "
                         "running them")


def pytest_collection_modifyitems(config, items):
    """Tests marked `data` need the real flights in ../shared/data: skipped, with the reason, without them."""
    if SHARED_DATA.is_dir():
        return
    skip = pytest.mark.skip(reason=f"needs the real flights in {SHARED_DATA} (../shared/data beside the checkout)")
    for item in items:
        if item.get_closest_marker("data"):
            item.add_marker(skip)


@pytest.fixture
def data_dir(tmp_path):
    """An empty folder for the log files a test writes."""
    directory = tmp_path / "logs"
    directory.mkdir()
    return directory


@pytest.fixture(scope="module")
def sim():
    """An 8-s circle at 1 m with take-off and landing, 4 s on the floor after touchdown (room for a pick-up):
    the simulated flight that the flight-span and batch-upload tests write in every format, cut and upload."""
    from learnest.ingest.sim import simulate
    from learnest.ingest.sim.trajectories import Circle, Timing

    return simulate(Circle(radius=0.5, speed=0.8, duration_s=8.0), timing=Timing(sit_after_s=4.0), seed=3,
                    name="circle")
