"""Static checks as tests: ruff on the package's source folders, mypy on the installed package.

mypy reads the installed package as one folder: a wheel (`pip install .`) or an editable install in strict mode
(`pip install -e . --config-settings editable_mode=strict`), whose folder of links looks like the wheel. A
default editable install maps `learnest.ingest` onto the repository's `ingest/` with an import hook that only
Python's import system follows, so mypy would not find the subpackages; the test says so instead.

Files colleagues are rewriting are not clean yet; they are named below so that every other file is held
to the checks now, and the lists shrink as those rewrites land (delete an entry once its file is clean).
"""
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = ROOT / "pyproject.toml"
# the docs hook ships too
PACKAGE_FOLDERS = ["ingest", "models", "estimators", "workflows", "service", "learnest", "docs/_hooks"]

# ruff violations in files being rewritten (they are checked again once removed from here): none left
RUFF_NOT_YET_CLEAN: list[str] = []
# mypy errors in files being rewritten (paths inside the installed package)
MYPY_NOT_YET_CLEAN: list[str] = []


def _ruff(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", *args], cwd=ROOT, input=stdin,
                          capture_output=True, text=True, timeout=120)


def test_ruff_clean_on_the_package():
    """`ruff check ingest models estimators workflows service learnest` passes (but for the files named above)."""
    excluded = ["--extend-exclude", ",".join(RUFF_NOT_YET_CLEAN)] if RUFF_NOT_YET_CLEAN else []
    result = _ruff(*excluded, *PACKAGE_FOLDERS)
    assert result.returncode == 0, result.stdout + result.stderr


def test_ruff_check_catches_a_violation():
    """The check is live: the project's configuration run on a module with an unused import and a too
    long line fails, so the test above cannot pass by checking nothing."""
    source = "import os\n\nVALUE = '" + "x" * 130 + "'\n"
    result = _ruff("--stdin-filename", "service/_probe.py", "-", stdin=source)
    assert result.returncode == 1, result.stdout + result.stderr
    assert "F401" in result.stdout and "E501" in result.stdout


def test_the_exempt_files_exist():
    """An exemption for a renamed or deleted file would silently cover nothing: drop it instead."""
    missing = [f for f in RUFF_NOT_YET_CLEAN + MYPY_NOT_YET_CLEAN if not (ROOT / f).is_file()]
    assert missing == []


@pytest.fixture(scope="module")
def mypy_run(tmp_path_factory) -> tuple[int, str, dict[str, int]]:
    """One mypy run shared by the two mypy tests."""
    import learnest

    folder = Path(learnest.__file__).parent
    if not (folder / "ingest").is_dir():
        pytest.fail(f"learnest is installed from {folder}, without its subpackages beside it: a default editable "
                    "install, which mypy cannot read. Reinstall with: pip install -c constraints.txt -e '.[test]' "
                    "--config-settings editable_mode=strict")
    return _mypy_errors(tmp_path_factory.mktemp("mypy"))


def _mypy_errors(tmp_path: Path) -> tuple[int, str, dict[str, int]]:
    """Run mypy on the installed `learnest` (from an empty folder, so the source tree is not what it sees);
    return its exit code, its output and the number of errors per file (relative to the package)."""
    result = subprocess.run([sys.executable, "-m", "mypy", "--config-file", str(PYPROJECT), "--cache-dir",
                             str(tmp_path / "cache"), "-p", "learnest"], cwd=tmp_path, capture_output=True,
                            text=True, timeout=900)
    counts: dict[str, int] = {}
    for match in re.finditer(r"^(\S+?\.py):\d+: error:", result.stdout, flags=re.MULTILINE):
        path = match.group(1).replace("\\", "/").split("site-packages/learnest/", 1)[-1]
        counts[path] = counts.get(path, 0) + 1
    return result.returncode, result.stdout + result.stderr, counts


@pytest.mark.slow
def test_mypy_clean_outside_the_files_being_rewritten(mypy_run):
    """No mypy error in any file but those named in MYPY_NOT_YET_CLEAN."""
    code, output, counts = mypy_run
    assert code in (0, 1), output  # 2: mypy itself failed (bad configuration, crash)
    assert (code == 1) == bool(counts), output  # its errors were read: a format change cannot hide them
    unexpected = {path: n for path, n in counts.items() if path not in MYPY_NOT_YET_CLEAN}
    assert unexpected == {}, output


@pytest.mark.slow
def test_mypy_clean_on_the_installed_package(mypy_run):
    """`mypy -p learnest` on the installed package reports nothing."""
    code, output, _ = mypy_run
    assert code == 0, output
    checked = re.search(r"no issues found in (\d+) source files", output)
    assert checked and int(checked.group(1)) > 100, output  # the whole package, not a folder excluded by mistake
