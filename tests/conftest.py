"""Shared fixtures.  Tests import the installed `learnest` package, as a user would: no sys.path edits;
helpers live in `tests/utils` (importable as `utils` because pytest puts this folder on sys.path)."""
from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


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
