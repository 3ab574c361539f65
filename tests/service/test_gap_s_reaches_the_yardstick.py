"""`gap_s` reaches the mocap-gap yardstick in two forms at most, from every surface: the value given (a Python
float, a command-line option, a JSON number), then the typed settings (`EvaluationSettings`), whose `GapPlan` is
what the yardstick runs.  The service's job crosses a process boundary through its stored arguments: there the
one more form allowed is that stored JSON, read back into the type at once (`EvaluationSettings.from_json`), and
the type travels on to the task.

Instrumented: the settings' constructor (every instance, whoever builds it, is recorded with the function that
built it), `from_json` (what it read) and the yardstick's entry point (`workflows.flights.flight_yardsticks`: the
plan it receives).  A surface that unpacks the settings into a dict or keyword arguments and builds them again,
or lays a `GapPlan` of its own, hands the yardstick a plan no settings built from the value given own: the test
fails, naming the function that built the settings the yardstick's plan came from.
"""
from __future__ import annotations

import contextlib
import copy
import inspect
import io
import json
import sys

import pytest
from utils.service import flight_csv, running_app, settings_for, train, wait_for_job

GAP_S = 0.37   # no default or other setting has it: what the yardstick gets can only come from here


class Trace:
    """What the instruments saw: settings built (instance, builder), JSON read back, plans the yardstick got."""

    def __init__(self) -> None:
        self.built: list[tuple[object, str]] = []
        self.read: list[dict] = []
        self.plans: list[object] = []

    def builders(self) -> list[str]:
        return [builder for _, builder in self.built]

    def origin(self, plan) -> tuple[object, str]:
        """The settings instance whose gap plan ``plan`` is, and the function that built it."""
        owners = [(settings, builder) for settings, builder in self.built if settings.gaps is plan]
        assert len(owners) == 1, (f"the yardstick got a gap plan ({plan}) that no settings instance owns: it was "
                                  "laid apart from the typed settings")
        return owners[0]


@pytest.fixture
def trace(monkeypatch) -> Trace:
    from learnest.estimators.evaluation_settings import EvaluationSettings
    from learnest.workflows import flights

    seen = Trace()
    post_init, from_json = EvaluationSettings.__post_init__, EvaluationSettings.from_json.__func__
    yardsticks = flights.flight_yardsticks

    def recording_post_init(self) -> None:
        post_init(self)
        # frame 1 is the dataclass's __init__; frame 2 the function that asked for the instance
        seen.built.append((self, sys._getframe(2).f_code.co_name))

    def recording_from_json(cls, data):
        seen.read.append(copy.deepcopy(dict(data)))
        return from_json(cls, data)

    def recording_yardsticks(*args, **kwargs):
        seen.plans.append(inspect.signature(yardsticks).bind(*args, **kwargs).arguments["plan"])
        return yardsticks(*args, **kwargs)

    monkeypatch.setattr(EvaluationSettings, "__post_init__", recording_post_init)
    monkeypatch.setattr(EvaluationSettings, "from_json", classmethod(recording_from_json))
    monkeypatch.setattr(flights, "flight_yardsticks", recording_yardsticks)
    return seen


@pytest.fixture(scope="module")
def registry(tmp_path_factory):
    """quad:1 trained on one stored flight; a second flight's file for the command line, a third stored flight for
    the API (each surface computes its own flight: none is answered from the result cache)."""
    from learnest.service.jobs.executors import InlineExecutor

    root = tmp_path_factory.mktemp("gap_s")
    home, logs = root / "home", root / "logs"
    logs.mkdir()
    files = [flight_csv(logs, seed) for seed in (0, 1, 2)]
    with running_app(home, executor=InlineExecutor()) as client:
        ids = []
        for path in files:
            with path.open("rb") as handle:
                response = client.post("/flights", files=[("files", (path.name, handle.read()))])
            assert response.status_code in (200, 201), response.text
            ids.append(response.json()["id"])
        train(client, "quad", ids[0])
    return {"home": home, "ids": ids, "file": files[1]}


@pytest.fixture
def cli_home(registry, monkeypatch):
    monkeypatch.setenv("LEARNEST_HOME", str(registry["home"]))
    for name in ("LEARNEST_DATABASE_URL", "LEARNEST_DASK", "LEARNEST_API_KEY"):
        monkeypatch.delenv(name, raising=False)
    return registry


def _run_cli(*argv: str) -> dict:
    from learnest.service.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(list(argv)) == 0
    return json.loads(out.getvalue())


def _assert_reached(trace: Trace, report: dict) -> None:
    """The yardstick ran on gaps of GAP_S, and the report says so."""
    assert trace.plans, "the yardstick never ran"
    assert all(plan.gap_s == GAP_S for plan in trace.plans)
    scored = [f for f in report["flights"] if not f["excluded"]]
    assert scored and all(f["yardsticks"]["mocap_gaps"]["gap_s"] == GAP_S for f in scored)


def test_from_the_notebook_the_value_then_the_settings(trace):
    import learnest as le
    from learnest.models.knode import HybridModel
    from learnest.models.systems import make_system

    flights = le.read_flights(["sample_logs/circle_rep1.csv"])
    report = le.evaluate(HybridModel(make_system("quadrotor"), "prior"), flights, methods=("ukf",), gap_s=GAP_S)
    _assert_reached(trace, report)
    # le.evaluate builds the settings once, from the float it was given; the yardstick runs their plan
    assert trace.builders() == ["evaluate"] and trace.read == []
    for plan in trace.plans:
        settings, builder = trace.origin(plan)
        assert builder == "evaluate" and type(settings.gap_s) is float


def test_from_the_command_line_the_option_then_the_settings(trace, cli_home):
    report = _run_cli("evaluate", "--model", "quad:1", str(cli_home["file"]), "--methods", "ukf",
                      "--gap-s", str(GAP_S), "--no-store", "--json")
    _assert_reached(trace, report)
    # built from the parsed options (checked before any flight is read, then for the run), never from JSON
    assert set(trace.builders()) == {"evaluation_settings"} and trace.read == []
    for plan in trace.plans:
        assert trace.origin(plan)[1] == "evaluation_settings"


def _stored_settings(home, evaluation_id: int) -> dict:
    from learnest.service.storage.database import Database
    from learnest.service.storage.tables import Evaluation

    database = Database(settings_for(home).url)
    try:
        with database.transaction() as session:
            return dict(session.get(Evaluation, evaluation_id).settings)
    finally:
        database.dispose()


def _assert_stored_then_typed(trace: Trace, first_builder: str, stored: dict) -> None:
    """Through a job: the settings built once from the value given (by ``first_builder``), stored as their JSON
    (the row's ``stored``), read back into the type once; the yardstick runs the plan of what was read back."""
    assert trace.builders()[-1] == "from_json" and set(trace.builders()[:-1]) == {first_builder}
    given = trace.built[0][0]
    assert trace.read == [given.to_json()] == [stored] and stored["gap_s"] == GAP_S
    read_back = trace.built[-1][0]
    for plan in trace.plans:
        assert trace.origin(plan) == (read_back, "from_json")


def test_from_the_command_line_through_the_registry_the_option_the_stored_json_then_the_settings(trace, cli_home):
    report = _run_cli("evaluate", "--model", "quad:1", str(cli_home["file"]), "--methods", "ukf",
                      "--gap-s", str(GAP_S), "--json")
    _assert_reached(trace, report)
    _assert_stored_then_typed(trace, "evaluation_settings", _stored_settings(cli_home["home"],
                                                                              report["evaluation_id"]))


def test_from_the_api_the_json_number_the_stored_json_then_the_settings(trace, registry):
    from learnest.service.jobs.executors import InlineExecutor

    with running_app(registry["home"], executor=InlineExecutor()) as client:
        response = client.post("/evaluations", json={"model": "quad:1", "flights": [registry["ids"][2]],
                                                     "methods": ["ukf"], "gap_s": GAP_S})
        assert response.status_code == 202, response.text
        accepted = response.json()
        assert wait_for_job(client, accepted["job_id"])["state"] == "succeeded"
        report = client.get(f"/evaluations/{accepted['evaluation_id']}").json()
    _assert_reached(trace, report)
    # the request's validation builds the settings; the job reads its stored row back into them
    _assert_stored_then_typed(trace, "settings_in_bounds", _stored_settings(registry["home"],
                                                                             accepted["evaluation_id"]))
