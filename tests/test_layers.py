"""The architecture as tests: one-way imports (import-linter's contracts in pyproject.toml) and no cycles."""
import sys
from pathlib import Path

import grimp
import pytest
from importlinter.cli import lint_imports

import learnest  # first: grimp then reads the installed package's spec from sys.modules

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def test_import_contracts_hold(tmp_path, monkeypatch):
    """Layers ingest -> models -> estimators -> service; the science imports no web/SQL/jobs code."""
    # import-linter puts the working directory first on sys.path: from the repository root that would be the
    # checkout's learnest/ folder, not the installed package the contracts are about
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", list(sys.path))
    assert lint_imports(config_filename=str(PYPROJECT), no_cache=True) == 0


@pytest.fixture(scope="module")
def graph():
    return grimp.build_graph("learnest", cache_dir=None)


def test_no_import_cycles_between_modules(graph):
    cycles = sorted({tuple(sorted((module, imported)))
                     for module in graph.modules for imported in graph.find_modules_directly_imported_by(module)
                     if imported.startswith("learnest.") and graph.chain_exists(importer=imported, imported=module)})
    assert cycles == [], cycles


def test_the_contracts_catch_a_violation(graph):
    """The layer check is live: an estimator importing the service would be found."""
    graph.add_import(importer="learnest.estimators.ukf", imported="learnest.service.jobs", line_number=1,
                     line_contents="from learnest.service import jobs")
    illegal = graph.find_illegal_dependencies_for_layers(
        layers=["learnest.service", "learnest.estimators", "learnest.models", "learnest.ingest"])
    assert {(d.importer, d.imported) for d in illegal} == {("learnest.estimators", "learnest.service")}
