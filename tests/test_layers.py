"""The architecture as tests: one-way imports (import-linter's contracts in pyproject.toml) and no cycles."""
import sys
from copy import deepcopy
from pathlib import Path

import grimp
import pytest
from importlinter.cli import lint_imports

import learnest  # first: grimp then reads the installed package's spec from sys.modules

PYPROJECT = Path(__file__).resolve().parents[1] / "pyproject.toml"


def test_import_contracts_hold(tmp_path, monkeypatch):
    """Layers ingest -> models -> estimators -> workflows -> service; the science imports no web/SQL/jobs code."""
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
        layers=["learnest.service", "learnest.workflows", "learnest.estimators", "learnest.models", "learnest.ingest"])
    assert {(d.importer, d.imported) for d in illegal} == {("learnest.estimators", "learnest.service")}


def _contract(name_start: str) -> dict:
    """The one contract of pyproject.toml whose name starts so."""
    import tomllib

    contracts = tomllib.loads(PYPROJECT.read_text())["tool"]["importlinter"]["contracts"]
    [contract] = [c for c in contracts if c["name"].startswith(name_start)]
    return contract


def _rooms_layers() -> list:
    """The service rooms contract of pyproject.toml as grimp layers ("a : b" is one layer of siblings that may
    import each other)."""
    rooms = _contract("service rooms")
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


def _forbidden_broken(graph, name_start: str) -> set:
    """(importer, forbidden) modules the forbidden contract of pyproject.toml named so finds on ``graph``, as
    import-linter checks it (on a copy: the check removes the contract's ignored imports from the graph it is given)."""
    from importlinter.contracts.forbidden import ForbiddenContract

    options = {k: v for k, v in _contract(name_start).items() if k not in ("name", "type")}
    contract = ForbiddenContract(name=name_start, session_options={"root_packages": ["learnest"]},
                                 contract_options=options)
    check = contract.check(deepcopy(graph), verbose=False)
    return {(c["downstream_module"], c["upstream_module"]) for c in check.metadata["invalid_chains"]}


def _cli_imports_broken(graph) -> set:
    """What the CLI contract finds on ``graph`` (`_forbidden_broken`)."""
    return _forbidden_broken(graph, "the CLI imports")


@pytest.mark.parametrize("imported, forbidden", [("learnest.models.presets", "learnest.models"),
                                                 ("learnest.service.storage.references", "learnest.service.storage"),
                                                 ("learnest.service.app.starting", "learnest.service.app"),
                                                 ("learnest.service.web.pages", "learnest.service.web")])
def test_the_cli_contract_is_live(graph, imported, forbidden):
    """The CLI reaches the science only through learnest.workflows and the service only through
    learnest.service.local: the contract holds on the package as it is (the facade's own imports of the models
    and the storage are no violation), and a command importing past them, below the facade or above it (the app,
    the web pages), would be found."""
    assert _cli_imports_broken(graph) == set()
    reaching_past = deepcopy(graph)
    reaching_past.add_import(importer="learnest.service.cli.arguments", imported=imported, line_number=1,
                             line_contents=f"import {imported}")
    assert _cli_imports_broken(reaching_past) == {("learnest.service.cli", forbidden)}


@pytest.mark.parametrize("trainer", ["learnest.models.training", "learnest.models.pooled_training"])
def test_the_workflows_train_only_through_algorithm1(graph, trainer):
    """Training has one home: no workflow imports a trainer itself (Table I and the diagnosis train through
    `estimators.algorithm1.Algorithm1`, which imports them), and one that did would be found."""
    assert _forbidden_broken(graph, "the workflows train") == set()
    by_hand = deepcopy(graph)
    by_hand.add_import(importer="learnest.workflows.table1", imported=trainer, line_number=1,
                       line_contents=f"import {trainer}")
    assert _forbidden_broken(by_hand, "the workflows train") == {("learnest.workflows", trainer)}
