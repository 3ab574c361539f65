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


def _rooms_layers() -> list:
    """The service rooms contract of pyproject.toml as grimp layers ("a : b" is one layer of siblings that may
    import each other)."""
    import tomllib

    contracts = tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]["contracts"]
    [rooms] = [c for c in contracts if c["name"].startswith("service rooms")]
    return [grimp.Layer(*(name.strip() for name in layer.split(":")), independent=False) for layer in rooms["layers"]]


def test_the_service_rooms_contract_is_live(graph):
    """The rooms hold on the package as it is, and a storage module importing a service function (a room
    reaching up) would be found."""
    layers = _rooms_layers()
    assert [layer.module_tails for layer in layers][-3:] == [{"learnest.service.jobs"}, {"learnest.service.storage"},
                                                            {"learnest.service.config"}]
    assert graph.find_illegal_dependencies_for_layers(layers=layers) == set()
    reaching_up = grimp.build_graph("learnest", cache_dir=None)   # the module's graph stays as the package is
    reaching_up.add_import(importer="learnest.service.storage.registry", imported="learnest.service.operations.catalog",
                           line_number=1, line_contents="from ..operations import catalog")
    illegal = reaching_up.find_illegal_dependencies_for_layers(layers=layers)
    assert {(d.importer, d.imported) for d in illegal} == {("learnest.service.storage", "learnest.service.operations")}
